"""Replay recorded observations through the differentiable back end, in windows of T frames.

A :class:`Windows` batch holds B windows (from one or several sequences) of T frames each, padded to N features:
everything :func:`torchtrack.filter.frame.ekf_frame` and a weighting need, plus the ground truth. :func:`rollout`
runs the weighting and the fusion EKF over them exactly as the tracker does (the same per-frame back end; a model
re-selection resets the filter to the recorded model pose, as the tracker's ``_new_model`` does) and returns the
poses and the innovation likelihoods, differentiable in the weighting's parameters.

Each window starts from the pose of its first frame (zero velocity and the initial covariance, as after a model
selection): its ground truth, so that its error is the drift of the back end over the window (a relative pose
error with a delta of up to T frames), or on unlabelled footage the tracker's recorded estimate
(:func:`torchtrack.learn.train.sequence_windows`). Truncated backpropagation: windows are independent.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.filter.cues import CUE_INDEX
from torchtrack.filter.frame import Observation, ekf_frame
from torchtrack.filter.fusion import FusionEKF
from torchtrack.filter.noise_scale import NoiseScale, ScaleState
from torchtrack.filter.weighting import Variances, WeightingInputs, pixel_only_variances
from torchtrack.geometry import T_inv


@dataclass
class Windows:
    """B windows of T frames, padded to N features; frame-major (T, B, ...) so that a frame is one slice.

    Attributes:
        start_T_cam_obj: (B, 4, 4) the filter's starting pose at the frame before the window (the model's pose, its
            ground truth, or the tracker's recorded estimate where it has none).
        dt: (T, B) seconds; points_obj, points_d: (T, B, N, 3); pixels: (T, B, N, 2); valid: (T, B, N) bool;
        has_depth: (T, B, N) bool, the valid ones measured with their 3D point (the others: pixel only);
        cues: (T, B, N, C) (:data:`torchtrack.filter.cues.CUE_NAMES`).
        K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4); focal: (B,) depth focal length (eq. 12's f).
        reselected: (T, B) bool, the model was re-selected after frame t's update; model_T_cam_obj: (T, B, 4, 4)
            the pose the filter is then reset to.
        T_cam_obj_gt: (T, B, 4, 4) ground truth of each frame's update; gt_valid: (T, B) bool.
        start_noise: (B, 2) the tracker's online noise scale k [pix, xyz] before the window's first update, and
            start_noise_dof (B, 2) the redundancy behind it (:class:`~torchtrack.filter.noise_scale.ScaleState`).
    """

    start_T_cam_obj: Tensor
    dt: Tensor
    points_obj: Tensor
    points_d: Tensor
    pixels: Tensor
    valid: Tensor
    has_depth: Tensor
    cues: Tensor
    K: Tensor
    T_color_depth: Tensor
    focal: Tensor
    reselected: Tensor
    model_T_cam_obj: Tensor
    T_cam_obj_gt: Tensor
    gt_valid: Tensor
    start_noise: Tensor
    start_noise_dof: Tensor

    @property
    def frames(self) -> int:
        return self.dt.shape[0]

    def observation(self, t: int) -> Observation:
        return Observation(self.dt[t], self.points_obj[t], self.points_d[t], self.pixels[t], self.valid[t], self.K,
                           self.T_color_depth, has_depth=self.has_depth[t])  # fmt: skip

    def weighting_inputs(self, t: int) -> WeightingInputs:
        """What a weighting sees at frame t: the winner's d_TIM (eq. 10) rebuilt from the cues, and the cues."""
        c = self.cues[t]
        d_tim = torch.where(
            c[..., CUE_INDEX["sim_won"]] > 0.5, c[..., CUE_INDEX["d_tim_sim"]], c[..., CUE_INDEX["d_tim_int"]]
        )
        points_d = self.points_d[t]
        valid = self.valid[t] & self.has_depth[t]  # the weighting sees the features with depth, as in the tracker
        return WeightingInputs(d_tim.to(points_d.dtype), points_d[..., 2], points_d, valid, self.focal, cues=c)


def concat_windows(parts: list[Windows]) -> Windows:
    """Concatenate window batches along B, padding N to the widest (zeros, invalid)."""
    n = max(p.valid.shape[-1] for p in parts)
    out = {}
    for f in fields(Windows):
        vals = [getattr(p, f.name) for p in parts]
        if f.name in ("points_obj", "points_d", "pixels", "valid", "has_depth", "cues"):
            vals = [_pad_features(v, n) for v in vals]
        out[f.name] = torch.cat(vals, dim=0 if f.name in PER_WINDOW else 1)  # per window: (B, ...); else (T, B, ...)
    return Windows(**out)


PER_WINDOW = (
    "start_T_cam_obj",
    "K",
    "T_color_depth",
    "focal",
    "start_noise",
    "start_noise_dof",
)  # (B, ...); else (T, B, ...)


def _pad_features(x: Tensor, n: int) -> Tensor:
    """Pad dim 2 (features) of a (T, B, N, ...) tensor to n."""
    if x.shape[2] >= n:
        return x
    pad = x.new_zeros(*x.shape[:2], n - x.shape[2], *x.shape[3:])
    return torch.cat([x, pad], 2)


class Rollout(NamedTuple):
    """Outputs of :func:`rollout`, frame-major.

    T_cam_obj: (T, B, 4, 4) posterior pose of each frame (before any reset at that frame's re-selection).
    nll: (T, B) innovation negative log-likelihood (0 unless asked for); n_used: (T, B) measurements used.
    var_pix, var_xyz: (T, B, N) the weighting's variances.
    """

    T_cam_obj: Tensor
    nll: Tensor
    n_used: Tensor
    var_pix: Tensor
    var_xyz: Tensor


def rollout(
    ekf: FusionEKF,
    weighting: Callable[[WeightingInputs], Variances],
    win: Windows,
    *,
    gate: float | None = None,
    refit: float | None = None,
    with_nll: bool = False,
    noise_scale: NoiseScale | None = None,
) -> Rollout:
    """Run ``weighting`` and :func:`~torchtrack.filter.frame.ekf_frame` over the T frames of ``win``.

    Each window starts at ``win.start_T_cam_obj`` with zero velocity. With ``noise_scale`` (the filter's online
    scale, ``ekf.noise``) every frame uses ``R = k R0`` as the tracker does, k starting at the tracker's recorded
    scale (``win.start_noise``) and updated from the replayed residuals (without gradient); None: R0 as given."""
    state = ekf.initial_state(win.start_T_cam_obj)
    scale = None if noise_scale is None else ScaleState(win.start_noise, win.start_noise_dof)
    poses, nll, n_used, vp, vx = [], [], [], [], []
    for t in range(win.frames):
        inputs = win.weighting_inputs(t)  # over the features with depth, as in the tracker
        var = pixel_only_variances(weighting(inputs), win.valid[t], inputs.valid)
        out = ekf_frame(ekf, state, win.observation(t), var, gate=gate, refit=refit, with_nll=with_nll,
                        noise_scale=noise_scale, scale_state=scale)  # fmt: skip
        scale = out.noise
        poses.append(out.T_cam_obj)
        nll.append(out.nll)
        n_used.append(3 * out.used_xyz.sum(-1) + 2 * out.used_pix.sum(-1))
        vp.append(var.var_pix)
        vx.append(var.var_xyz)
        reset = win.reselected[t]
        state = out.posterior
        if bool(reset.any()):  # the tracker's model re-selection: the filter restarts at the new model's pose
            state = ekf.initial_state(win.model_T_cam_obj[t]).select(reset, state)
    return Rollout(torch.stack(poses), torch.stack(nll), torch.stack(n_used), torch.stack(vp), torch.stack(vx))


def pose_errors(T_est: Tensor, T_gt: Tensor) -> tuple[Tensor, Tensor]:
    """Translation (m) and rotation (rad) error of ``inv(T_gt) @ T_est``, (...,) each. The rotation error is
    ``||R_err - I||_F / sqrt(2) = 2 sin(angle / 2)`` (equal to the angle to 1e-3 relative below 5 deg): smooth at 0."""
    E = T_inv(T_gt) @ T_est
    eye = torch.eye(3, dtype=E.dtype, device=E.device)
    return E[..., :3, 3].norm(dim=-1), (E[..., :3, :3] - eye).flatten(-2).norm(dim=-1) / 2**0.5


def supervised_loss(out: Rollout, win: Windows, w_trans: float = 1.0, w_rot: float = 1.0, eps: float = 1e-4) -> Tensor:
    """Mean over the frames with ground truth of ``w_trans * rho(e_t) + w_rot * rho(e_r)``, e_t in metres, e_r in
    radians, ``rho(e) = sqrt(e^2 + eps^2) - eps`` (Charbonnier: L1-like, so one lost window does not dominate)."""
    e_t, e_r = pose_errors(out.T_cam_obj, win.T_cam_obj_gt.to(out.T_cam_obj.dtype))
    loss = w_trans * _charbonnier(e_t, eps) + w_rot * _charbonnier(e_r, eps)
    mask = win.gt_valid.to(loss.dtype)
    return (loss * mask).sum() / mask.sum().clamp_min(1.0)


def nll_loss(out: Rollout) -> Tensor:
    """Innovation negative log-likelihood per used measurement, over all frames and windows (needs no ground
    truth)."""
    return out.nll.sum() / out.n_used.sum().clamp_min(1)


def _charbonnier(e: Tensor, eps: float) -> Tensor:
    return torch.sqrt(e * e + eps * eps) - eps
