"""Trajectory and tracking metrics: ATE, RPE, per-axis errors, reprojection error (16), improvement (17).

Poses are 4x4 homogeneous matrices, ``(F, 4, 4)``, given as numpy arrays or torch tensors; everything
is computed in float64 and returned as float64 tensors (statistics as Python floats).

ATE and RPE follow evo (github.com/MichaelGrupp/evo) exactly, so that numbers equal
``evo_ape tum gt est -a`` (translation part, SE(3) Umeyama alignment, no scale) and ``evo_rpe tum gt est``
(translation part / rotation angle in degrees, consecutive pairs) on the same associated poses.
Trajectories are camera-to-world ``T_world_cam`` (TUM files), already associated frame by frame.

References:
    Umeyama, "Least-squares estimation of transformation parameters between two point patterns", PAMI 1991.
    Sturm et al., "A benchmark for the evaluation of RGB-D SLAM systems", IROS 2012 (ATE, RPE).
    Gedik & Alatan, FUSION 2013, eqs. (16) and (17), Tables III, V and VI.
"""

from __future__ import annotations

import logging
import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack.geometry import T_inv, make_T, matrix_to_euler, project, rotation_angle, transform_points

logger = logging.getLogger(__name__)

_F64 = torch.float64
# Consecutive pairs in seconds accept a time step this much short of delta (TUM stamps have 1 us resolution),
# so that 3 frames at exactly 30 Hz make delta = 0.1 s despite rounding.
_SECONDS_EPS = 1e-6


class UmeyamaResult(NamedTuple):
    R: Tensor  # (..., 3, 3)
    t: Tensor  # (..., 3)
    s: Tensor  # (...) scale, 1 without scale


class ATEResult(NamedTuple):
    rmse_m: float
    mean: float  # metres
    median: float  # metres
    max: float  # metres
    errors: Tensor  # (F,) metres, per frame after alignment
    T_align: Tensor  # (4, 4) maps the estimate onto the ground truth


class RPEResult(NamedTuple):
    trans_rmse_m: float
    trans_mean_m: float
    rot_rmse_deg: float
    rot_mean_deg: float
    trans_errors: Tensor  # (P,) metres
    rot_errors_deg: Tensor  # (P,) degrees
    pairs: Tensor  # (P, 2) int64 frame indices (i, j)


class PerAxisErrors(NamedTuple):
    rot_deg: Tensor  # (F, 3) |d rho|, |d theta|, |d phi| in degrees
    trans_m: Tensor  # (F, 3) |d tx|, |d ty|, |d tz| in metres
    rot_mean_deg: Tensor  # (3,)
    trans_mean_m: Tensor  # (3,)


def _as_f64(x, name: str) -> Tensor:
    """A tensor stays on its device; arrays and lists (host data) come to the CPU."""
    return x.detach().to(_F64) if isinstance(x, Tensor) else torch.as_tensor(x, dtype=_F64, device="cpu")


def _as_poses(T, name: str) -> Tensor:
    T = _as_f64(T, name)
    if T.dim() != 3 or T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must be (F, 4, 4) poses, got {tuple(T.shape)}")
    if not torch.isfinite(T).all():
        raise ValueError(f"{name} has non-finite entries")
    return T


def _pose_pair(T_est, T_gt) -> tuple[Tensor, Tensor]:
    T_est, T_gt = _as_poses(T_est, "T_est"), _as_poses(T_gt, "T_gt")
    if T_est.shape != T_gt.shape:
        raise ValueError(f"T_est {tuple(T_est.shape)} and T_gt {tuple(T_gt.shape)} must have the same frames")
    if T_est.shape[0] == 0:
        raise ValueError("empty trajectories")
    return T_est, T_gt


def _rms(x: Tensor) -> float:
    return math.sqrt(float((x * x).mean()))


def umeyama_alignment(src, dst, with_scale: bool = False) -> UmeyamaResult:
    """Least-squares similarity ``dst ~ s R src + t`` between corresponding points (Umeyama 1991).

    Args:
        src, dst: (..., N, 3) corresponding points.
        with_scale: also estimate the scale ``s`` (eq. 42); else ``s = 1`` (SE(3) alignment).
    Returns:
        ``UmeyamaResult(R (..., 3, 3), t (..., 3), s (...))``. With fewer than three non-collinear points
        the rotation is not unique; a minimiser is still returned.
    """
    src, dst = _as_f64(src, "src"), _as_f64(dst, "dst")
    if src.shape != dst.shape or src.shape[-1] != 3 or src.dim() < 2 or src.shape[-2] == 0:
        raise ValueError(
            f"umeyama_alignment: src and dst must be equal (..., N>0, 3), got {tuple(src.shape)} and {tuple(dst.shape)}"
        )
    mu_src, mu_dst = src.mean(-2), dst.mean(-2)  # eqs. (34), (35)
    xs, ys = src - mu_src[..., None, :], dst - mu_dst[..., None, :]
    cov = ys.transpose(-1, -2) @ xs / src.shape[-2]  # eq. (38)
    U, d, Vh = torch.linalg.svd(cov)
    S = torch.ones_like(d)
    S[..., 2] = torch.where(torch.det(U) * torch.det(Vh) < 0, -1.0, 1.0)  # eq. (43): keep det(R) = +1
    R = U @ (S[..., :, None] * Vh)  # eq. (40)
    if with_scale:
        var_src = (xs * xs).sum((-1, -2)) / src.shape[-2]  # eq. (36)
        s = (d * S).sum(-1) / var_src  # eq. (42)
    else:
        s = torch.ones(src.shape[:-2], dtype=_F64, device=src.device)
    t = mu_dst - s[..., None] * (R @ mu_src[..., None])[..., 0]  # eq. (41)
    return UmeyamaResult(R, t, s)


def ate(T_est, T_gt, align: bool = True) -> ATEResult:
    """Absolute trajectory error, translation part, as ``evo_ape tum gt est -a``.

    Args:
        T_est, T_gt: (F, 4, 4) associated poses ``T_world_cam``.
        align: first map the estimate onto the ground truth with the SE(3) Umeyama fit of the positions.
    Returns:
        ``ATEResult``; ``errors[i] = || t_gt,i - (R t_est,i + t) ||``.
    """
    T_est, T_gt = _pose_pair(T_est, T_gt)
    p_est, p_gt = T_est[:, :3, 3], T_gt[:, :3, 3]
    if align:
        R, t, _ = umeyama_alignment(p_est, p_gt)
        T_align = make_T(R, t)
    else:
        T_align = torch.eye(4, dtype=_F64, device=p_est.device)
    errors = (transform_points(T_align, p_est) - p_gt).norm(dim=-1)
    return ATEResult(
        _rms(errors), float(errors.mean()), float(np.median(errors.cpu().numpy())), float(errors.max()), errors, T_align
    )


def _pairs_by_accumulation(steps: np.ndarray, delta: float, tol: float, all_pairs: bool, eps: float) -> list:
    """evo's ``filter_pairs_by_path`` on arbitrary non-negative per-frame steps (F-1,)."""
    if all_pairs:
        acc = np.concatenate([[0.0], np.cumsum(steps)])
        pairs = []
        for i in range(acc.size - 1):
            ahead = acc[i + 1 :] - acc[i]
            k = int(np.argmin(np.abs(ahead - delta)))
            if abs(ahead[k] - delta) <= tol:
                pairs.append((i, i + 1 + k))
        return pairs
    ids, current = [0], 0.0
    for i, step in enumerate(steps.tolist(), start=1):
        current += step
        if current >= delta - eps:
            ids.append(i)
            current = 0.0
    return list(zip(ids[:-1], ids[1:], strict=True))


def rpe_pairs(
    T_est, delta: float = 1, unit: str = "frames", timestamps=None, all_pairs: bool = False, rel_delta_tol: float = 0.1
) -> Tensor:
    """Frame index pairs (P, 2) for the RPE, chosen as evo does (on the estimate, ``pairs_from_reference=False``).

    * ``frames``: consecutive ``(0, d), (d, 2d), ...``; with ``all_pairs`` every ``(i, i + d)``.
    * ``meters``: path length along the estimate, evo's ``filter_pairs_by_path`` (``--delta_unit m``).
    * ``seconds``: the same rule on elapsed time from ``timestamps`` (F,) (evo has no time unit; this is its
      path rule with time as the distance, accepting a step ``1e-6 s`` short of delta in consecutive mode).
    ``all_pairs`` with metres/seconds takes for each i the j closest to delta ahead, within ``rel_delta_tol * delta``.
    """
    T_est = _as_poses(T_est, "T_est")
    F = T_est.shape[0]
    if not delta > 0:
        raise ValueError(f"rpe: delta must be positive, got {delta}")
    if unit == "frames":
        if float(delta) != int(delta):
            raise ValueError(f"rpe: delta in frames must be an integer, got {delta}")
        d = int(delta)
        starts = range(F - d) if all_pairs else range(0, F - d, d)
        pairs = [(i, i + d) for i in starts]
    elif unit == "meters":
        p = T_est[:, :3, 3].cpu().numpy()
        steps = np.linalg.norm(p[1:] - p[:-1], axis=1)
        pairs = _pairs_by_accumulation(steps, float(delta), float(delta) * rel_delta_tol, all_pairs, eps=0.0)
    elif unit == "seconds":
        if timestamps is None:
            raise ValueError("rpe: unit='seconds' needs timestamps (F,)")
        ts = _as_f64(timestamps, "timestamps").cpu().numpy()
        if ts.shape != (F,) or np.any(np.diff(ts) <= 0):
            raise ValueError(f"rpe: timestamps must be strictly increasing with shape ({F},), got {ts.shape}")
        pairs = _pairs_by_accumulation(np.diff(ts), float(delta), float(delta) * rel_delta_tol, all_pairs, _SECONDS_EPS)
    else:
        raise ValueError(f"rpe: unit must be 'frames', 'meters' or 'seconds', got {unit!r}")
    if not pairs:
        raise ValueError(f"rpe: delta = {delta} {unit} gives no pair among {F} poses")
    return torch.tensor(pairs, dtype=torch.long, device=T_est.device)


def rpe(
    T_est,
    T_gt,
    delta: float = 1,
    unit: str = "frames",
    timestamps=None,
    all_pairs: bool = False,
    rel_delta_tol: float = 0.1,
) -> RPEResult:
    """Relative pose error as ``evo_rpe`` (TUM RGB-D benchmark definition).

    For each pair (i, j) from :func:`rpe_pairs`: ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with ground truth Q and
    estimate P (both ``T_world_cam``, (F, 4, 4)); the translation error is ``||t(E)||`` in metres, the rotation
    error the angle of ``R(E)`` in degrees. RMSE equals evo's ``stats['rmse']``; the mean is ``stats['mean']``.
    """
    T_est, T_gt = _pose_pair(T_est, T_gt)
    pairs = rpe_pairs(T_est, delta, unit, timestamps, all_pairs, rel_delta_tol)
    i, j = pairs.unbind(-1)
    Q_rel = T_inv(T_gt[i]) @ T_gt[j]
    P_rel = T_inv(T_est[i]) @ T_est[j]
    E = T_inv(Q_rel) @ P_rel  # P,4,4
    trans = E[:, :3, 3].norm(dim=-1)
    rot = torch.rad2deg(rotation_angle(E[:, :3, :3]))
    return RPEResult(_rms(trans), float(trans.mean()), _rms(rot), float(rot.mean()), trans, rot, pairs)


class SharedError(NamedTuple):
    ate_m: float  # sqrt(max(mean_i <e_a,i, e_b,i>, 0)) of the SE(3)-aligned position errors, metres
    rpe_trans_m: float  # the same for the delta-1 relative translation errors t(E) of :func:`rpe`, metres
    scale_a: float  # Sim(3) Umeyama scale mapping a's positions onto the ground truth
    scale_b: float


def shared_error(T_a, T_b, T_gt) -> SharedError:
    """The part of two estimates' errors they have in common.

    With per-frame error vectors ``e_a = c + n_a`` and ``e_b = c + n_b`` (``c`` common to both, ``n_a``, ``n_b``
    independent of each other and of ``c``), ``mean <e_a, e_b> -> mean |c|^2``; reported as the square root (0
    when the mean is negative). For RPE (per-frame, nearly independent errors over many frames) two different
    methods share the ground truth's own errors and those of the sensor data both read, so ``rpe_trans_m`` is
    an estimate of a floor for any method that reads the same data. ATE errors are smooth drifts over few
    independent stretches: two drifts correlate by chance, so ``ate_m`` is no floor (it is ~ATE on exact ground
    truth too).

    Args:
        T_a, T_b, T_gt: (F, 4, 4) ``T_world_cam`` of two estimates and the ground truth, associated.
    """
    T_a, T_gt = _pose_pair(T_a, T_gt)
    T_b, _ = _pose_pair(T_b, T_gt)

    def ate_vectors(T):
        R, t, _ = umeyama_alignment(T[:, :3, 3], T_gt[:, :3, 3])
        return transform_points(make_T(R, t), T[:, :3, 3]) - T_gt[:, :3, 3]

    def rpe_vectors(T):
        Q_rel = T_inv(T_gt[:-1]) @ T_gt[1:]
        return (T_inv(Q_rel) @ T_inv(T[:-1]) @ T[1:])[:, :3, 3]  # t(E) of rpe(), delta 1 frame

    def common(ea, eb):
        return float((ea * eb).sum(-1).mean().clamp_min(0).sqrt())

    def scale(T):
        return float(umeyama_alignment(T[:, :3, 3], T_gt[:, :3, 3], with_scale=True).s)

    return SharedError(
        common(ate_vectors(T_a), ate_vectors(T_b)), common(rpe_vectors(T_a), rpe_vectors(T_b)), scale(T_a), scale(T_b)
    )


def per_axis_errors(T_est, T_gt) -> PerAxisErrors:
    """Per-axis rotation and translation errors of object poses (the quantities behind Table VI).

    The paper's state holds the Euler angles (rho, theta, phi) about x, y, z and the translation of the object in
    the camera, ``T_cam_obj``; its per-axis errors compare these components. Here, per frame,
    ``rot_deg = |wrap(euler(R_est) - euler(R_gt))|`` (wrapped to [0, 180] degrees) and
    ``trans_m = |t_est - t_gt|``, without alignment. Euler differences are ill-conditioned near
    ``|theta| = 90`` degrees (gimbal lock).

    Args:
        T_est, T_gt: (F, 4, 4) estimated and ground-truth object poses ``T_cam_obj``.
    """
    T_est, T_gt = _pose_pair(T_est, T_gt)
    d = matrix_to_euler(T_est[:, :3, :3]) - matrix_to_euler(T_gt[:, :3, :3])
    d = torch.remainder(d + torch.pi, 2 * torch.pi) - torch.pi  # F,3 in [-pi, pi)
    rot_deg = torch.rad2deg(d.abs())
    trans_m = (T_est[:, :3, 3] - T_gt[:, :3, 3]).abs()
    return PerAxisErrors(rot_deg, trans_m, rot_deg.mean(0), trans_m.mean(0))


def _reprojection_inputs(K, T_cam_obj, points_obj, pixels, valid):
    K, T = _as_f64(K, "K"), _as_f64(T_cam_obj, "T_cam_obj")
    X, x = _as_f64(points_obj, "points_obj"), _as_f64(pixels, "pixels")
    if K.shape[-2:] != (3, 3) or T.shape[-2:] != (4, 4) or X.shape[-1] != 3 or x.shape[-1] != 2:
        raise ValueError(
            "reprojection_error expects K (...,3,3), T_cam_obj (...,4,4), points_obj (...,N,3), pixels (...,N,2); "
            f"got {tuple(K.shape)}, {tuple(T.shape)}, {tuple(X.shape)}, {tuple(x.shape)}"
        )
    if X.shape[:-1] != x.shape[:-1]:
        raise ValueError(f"points_obj {tuple(X.shape)} and pixels {tuple(x.shape)} must have the same (..., N)")
    if valid is None:
        valid = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
    valid = torch.as_tensor(valid, device=x.device).bool()
    if valid.shape != x.shape[:-1]:
        raise ValueError(f"valid {tuple(valid.shape)} must be (..., N) = {tuple(x.shape[:-1])}")
    return K, T, X, x, valid


def reprojection_errors(K, T_cam_obj, points_obj, pixels, valid=None) -> Tensor:
    """Per-feature reprojection error, eq. (16): ``|| x_i - pi(K (R X_o,i + t)) ||`` in pixels.

    Args:
        K: (..., 3, 3) intrinsics of the camera the pixels live in.
        T_cam_obj: (..., 4, 4) estimated object pose in that camera (compose the depth-to-colour extrinsic
            first for eq. (7)).
        points_obj: (..., N, 3) model points X_o,i in the object frame.
        pixels: (..., N, 2) observed pixels x_i.
        valid: (..., N) bool, default all; invalid features get error 0.
    Returns:
        (..., N) errors. Pool over a sequence as ``e[valid].mean()`` (Table III: all tracked features).
    """
    K, T, X, x, valid = _reprojection_inputs(K, T_cam_obj, points_obj, pixels, valid)
    x_proj = project(K, transform_points(T, X))  # ...,N,2
    err = (x - x_proj).norm(dim=-1)
    return torch.where(valid, err, torch.zeros_like(err))


def reprojection_error(K, T_cam_obj, points_obj, pixels, valid=None) -> Tensor:
    """Mean reprojection error over the valid features, eq. (16): (...) pixels, NaN where none is valid.

    Shapes as :func:`reprojection_errors`.
    """
    K, T, X, x, valid = _reprojection_inputs(K, T_cam_obj, points_obj, pixels, valid)
    err = reprojection_errors(K, T, X, x, valid)
    count = valid.sum(-1)
    return torch.where(count > 0, err.sum(-1) / count.clamp_min(1), torch.full_like(err[..., 0], float("nan")))


def percentage_improvement(err_proposed, err_baseline):
    """Eq. (17): ``PI = (error_conventional - error_proposed) / error_conventional * 100``.

    Scalars give a float, arrays a float64 tensor (broadcast). Positive means the proposed method is better.
    """
    p, b = _as_f64(err_proposed, "err_proposed"), _as_f64(err_baseline, "err_baseline")
    if (b == 0).any():
        raise ValueError("percentage_improvement: baseline error is 0, improvement undefined")
    pi = (b - p) / b * 100.0  # eq. (17)
    return float(pi) if pi.dim() == 0 else pi


def trajectory_metrics(timestamps, T_est, T_gt, gt_valid=None) -> dict:
    """Numbers for a run's ``metrics.json``, on the frames with ground truth only.

    Args:
        timestamps: (F,) seconds.
        T_est, T_gt: (F, 4, 4) ``T_world_cam``; rows of T_gt where ``gt_valid`` is False are ignored.
        gt_valid: (F,) bool, default all.
    Returns:
        ``ate_rmse_m`` (SE(3)-aligned, as evo_ape -a), ``rpe_trans_m`` and ``rpe_rot_deg`` (RMSE over consecutive
        frame pairs, delta 1 frame, as evo_rpe), their means/medians/max and ``frames_with_gt``. Metrics that
        cannot be computed (ATE needs 3 frames, RPE 2) are None.
    """
    ts = _as_f64(timestamps, "timestamps")
    F = ts.shape[0] if ts.dim() == 1 else -1
    if gt_valid is None:
        gt_valid = torch.ones(max(F, 0), dtype=torch.bool, device=ts.device)
    valid = torch.as_tensor(gt_valid, device=ts.device).bool()
    if F < 0 or valid.shape != (F,):
        raise ValueError(
            f"trajectory_metrics: timestamps {tuple(ts.shape)} and gt_valid {tuple(valid.shape)} must be (F,)"
        )
    T_est = _as_f64(T_est, "T_est")
    T_gt = _as_f64(T_gt, "T_gt")
    if T_est.shape != (F, 4, 4) or T_gt.shape != (F, 4, 4):
        raise ValueError(
            f"trajectory_metrics: T_est {tuple(T_est.shape)} and T_gt {tuple(T_gt.shape)} must be ({F}, 4, 4)"
        )
    T_est, T_gt = T_est[valid], T_gt[valid]
    n = int(valid.sum())
    out = {"frames_with_gt": n}
    keys = ("ate_rmse_m", "ate_mean_m", "ate_median_m", "ate_max_m")
    keys_rpe = ("rpe_trans_m", "rpe_rot_deg", "rpe_trans_mean_m", "rpe_rot_mean_deg")
    out.update(dict.fromkeys(keys + keys_rpe))
    if n >= 3:
        a = ate(T_est, T_gt)
        out.update(zip(keys, (a.rmse_m, a.mean, a.median, a.max), strict=True))
    if n >= 2:
        r = rpe(T_est, T_gt, delta=1, unit="frames")
        out.update(zip(keys_rpe, (r.trans_rmse_m, r.rot_rmse_deg, r.trans_mean_m, r.rot_mean_deg), strict=True))
    if n < 3:
        logger.warning("only %d frames with ground truth: metrics needing more are None", n)
    return out
