"""Dense pose correction against recent keyframes, batched over B sequences (issue 12, drift).

After each frame's EKF update the current colour camera is aligned to the nearest of the last few model (key)
frames by Gauss-Newton on a coarse pyramid: a photometric term (grey value of the current pixel against the
keyframe's grey at its projection) plus a point-to-plane term (the current point against the keyframe's surface
at the same projection, projective association), each with Huber weights. The aligned pose then replaces (or is
blended into) the filter's pose: the EKF's mean pose is reset and its velocity and covariance kept.

Frames: ``T_ref_cur`` maps current-camera points into the keyframe camera, ``p_ref = R p_cur + t``; both are colour
cameras. Twists are (v, omega) with the left update ``T <- exp(xi) T``.

References:
    C. Kerl, J. Sturm, D. Cremers, "Robust Odometry Estimation for RGB-D Cameras", ICRA 2013 (photometric term).
    T. Whelan et al., "Real-time large scale dense RGB-D SLAM with volumetric fusion", IJRR 2015 (joint ICP + RGB).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.geometry import T_inv, backproject_depth, point_jacobian, rotation_angle, se3_exp, se3_log


class AlignResult(NamedTuple):
    """T_ref_cur (B, 4, 4) float64; n_used (B,) residuals in the last iteration; valid (B,) enough of them."""

    T_ref_cur: Tensor
    n_used: Tensor
    valid: Tensor


def downsample(gray: Tensor, depth: Tensor, K: Tensor, factor: int, max_rel_step: float = 0.05):
    """Block-average ``gray`` (B,1,H,W) and ``depth`` (B,1,H,W, 0 = none) by ``factor``; a depth block counts only
    when all its pixels have depth within ``max_rel_step`` of each other (no mixing across occlusions).
    Returns (gray, depth, K (B,3,3) of the coarse grid, pixel centres kept: u' = (u + 0.5) / f - 0.5)."""
    if gray.dim() != 4 or gray.shape != depth.shape or K.shape != (gray.shape[0], 3, 3):
        raise ValueError(
            f"downsample: need gray, depth (B,1,H,W) and K (B,3,3), got {gray.shape}, {depth.shape}, {K.shape}"
        )
    if factor == 1:
        return gray, depth, K
    g = F.avg_pool2d(gray, factor)
    d_max = F.max_pool2d(depth, factor)
    d_min = -F.max_pool2d(-torch.where(depth > 0, depth, torch.full_like(depth, float("inf"))), factor)
    ok = (d_min > 0) & torch.isfinite(d_min) & (d_max - d_min <= max_rel_step * d_min)
    d = torch.where(ok, F.avg_pool2d(depth, factor), torch.zeros_like(d_max))
    Kc = K.clone()
    Kc[:, :2, :2] = K[:, :2, :2] / factor
    Kc[:, :2, 2] = (K[:, :2, 2] + 0.5) / factor - 0.5
    return g, d, Kc


def _sample(img: Tensor, pix: Tensor) -> Tensor:
    """Bilinear samples (B, P, C) of ``img`` (B, C, H, W) at pixels ``pix`` (B, P, 2); zeros outside."""
    H, W = img.shape[-2:]
    grid = torch.stack([2 * pix[..., 0] / (W - 1) - 1, 2 * pix[..., 1] / (H - 1) - 1], -1)[:, :, None]
    return F.grid_sample(img, grid.to(img.dtype), align_corners=True)[..., 0].transpose(1, 2)


def _normals(points: Tensor, valid: Tensor, max_rel_step: float = 0.05) -> tuple[Tensor, Tensor]:
    """Normals (B, 3, H, W) of a point map ``points`` (B, 3, H, W) by central differences, facing the camera;
    valid (B, 1, H, W) where the point and its four neighbours are, with depth steps to them below
    ``max_rel_step`` of the depth (no normals, and no interpolated points, across occlusion boundaries)."""
    dx = F.pad(points[..., :, 2:] - points[..., :, :-2], (1, 1, 0, 0))
    dy = F.pad(points[..., 2:, :] - points[..., :-2, :], (0, 0, 1, 1))
    n = torch.linalg.cross(dx, dy, dim=1)
    n = n / torch.linalg.vector_norm(n, dim=1, keepdim=True).clamp_min(1e-12)
    n = torch.where((n * points).sum(1, keepdim=True) > 0, -n, n)
    v = valid.float()
    nb = F.pad(v[..., :, 2:] * v[..., :, :-2], (1, 1, 0, 0)) * F.pad(v[..., 2:, :] * v[..., :-2, :], (0, 0, 1, 1))
    z = points[:, 2:3]
    smooth = (dx[:, 2:3].abs() <= 2 * max_rel_step * z) & (dy[:, 2:3].abs() <= 2 * max_rel_step * z)
    return n, ((nb * v) > 0.5) & smooth


def _huber(r: Tensor, k: float) -> Tensor:
    """Huber weights of normalised residuals r: 1 inside k, k/|r| outside."""
    a = r.abs()
    return torch.where(a <= k, torch.ones_like(a), k / a.clamp_min(1e-12))


def align_to_keyframe(
    gray_cur: Tensor,
    depth_cur: Tensor,
    gray_ref: Tensor,
    depth_ref: Tensor,
    K: Tensor,
    T_init: Tensor,
    *,
    iters: int = 6,
    sigma_gray: float = 0.03,
    sigma_m: float = 0.01,
    huber: float = 1.345,
    max_dist_m: float = 0.1,
    min_residuals: int = 200,
    use_photometric: bool = True,
    use_geometric: bool = True,
) -> AlignResult:
    """Gauss-Newton alignment of the current frame to a keyframe on one pyramid level, batched over B.

    Args:
        gray_cur, depth_cur: (B, 1, H, W) current grey (any range) and depth in metres (0 = none).
        gray_ref, depth_ref: (B, 1, H, W) the keyframe's, same grid and intrinsics.
        K: (B, 3, 3) intrinsics of that grid. T_init: (B, 4, 4) the initial T_ref_cur.
        sigma_gray, sigma_m: residual scales of the photometric and point-to-plane terms (their relative weight).
        max_dist_m: point pairs farther apart than this along the normal are dropped (not the same surface).
    Residuals per current pixel with depth: r_I = I_ref(pi(K p_ref)) - I_cur(u), r_G = n_ref . (p_ref - q_ref),
    p_ref = T p_cur, q_ref the keyframe's point at the projection. Linearised at the current iterate.
    """
    B, _, H, W = gray_cur.shape
    for name, x in (("depth_cur", depth_cur), ("gray_ref", gray_ref), ("depth_ref", depth_ref)):
        if x.shape != gray_cur.shape:
            raise ValueError(f"align_to_keyframe: {name} must be {tuple(gray_cur.shape)}, got {tuple(x.shape)}")
    if K.shape != (B, 3, 3) or T_init.shape != (B, 4, 4):
        raise ValueError(
            f"align_to_keyframe: need K (B,3,3), T_init (B,4,4), got {tuple(K.shape)}, {tuple(T_init.shape)}"
        )
    f64 = torch.float64
    K = K.to(f64)
    p_cur = backproject_depth(K, depth_cur.to(f64)).reshape(B, -1, 3)  # B,P,3
    ok_cur = (depth_cur > 0).reshape(B, -1)
    i_cur = gray_cur.to(f64).reshape(B, -1)
    q_map = backproject_depth(K, depth_ref.to(f64)).permute(0, 3, 1, 2)  # B,3,H,W
    n_map, ok_n = _normals(q_map, depth_ref > 0)
    g_ref = gray_ref.to(f64)
    gx = F.pad(g_ref[..., :, 2:] - g_ref[..., :, :-2], (1, 1, 0, 0)) / 2
    gy = F.pad(g_ref[..., 2:, :] - g_ref[..., :-2, :], (0, 0, 1, 1)) / 2
    ref = torch.cat([g_ref, gx, gy, q_map, n_map, ok_n.to(f64)], 1)  # B,10,H,W: one sampling per iteration
    T = T_init.to(f64).clone()
    fx, fy = K[:, 0, 0, None], K[:, 1, 1, None]
    n_used = torch.zeros(B, dtype=torch.long)
    for _ in range(iters):
        p = p_cur @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
        z = p[..., 2].clamp_min(1e-6)
        u = torch.stack([fx * p[..., 0] / z + K[:, 0, 2, None], fy * p[..., 1] / z + K[:, 1, 2, None]], -1)
        inside = ok_cur & (p[..., 2] > 1e-3) & (u[..., 0] >= 1) & (u[..., 0] <= W - 2) & (u[..., 1] >= 1)
        inside &= u[..., 1] <= H - 2
        s = _sample(ref, u)  # B,P,10
        J_proj = torch.zeros(*p.shape[:-1], 2, 3, dtype=f64)  # d pi / d p
        J_proj[..., 0, 0], J_proj[..., 0, 2] = fx / z, -fx * p[..., 0] / z**2
        J_proj[..., 1, 1], J_proj[..., 1, 2] = fy / z, -fy * p[..., 1] / z**2
        dp = point_jacobian(p)  # B,P,3,6
        Js, rs, ws = [], [], []
        if use_photometric:
            r = (s[..., 0] - i_cur) / sigma_gray
            J = (s[..., None, 1:3] @ J_proj @ dp)[..., 0, :] / sigma_gray  # B,P,6
            Js.append(J), rs.append(r), ws.append(inside.to(f64) * _huber(r, huber))
        if use_geometric:
            n, q = s[..., 6:9], s[..., 3:6]
            r_m = (n * (p - q)).sum(-1)
            ok = inside & (s[..., 9] > 0.999) & (r_m.abs() < max_dist_m)
            r = r_m / sigma_m
            J = (n[..., None, :] @ dp)[..., 0, :] / sigma_m
            Js.append(J), rs.append(r), ws.append(ok.to(f64) * _huber(r, huber))
        J, r, w = torch.cat(Js, 1), torch.cat(rs, 1), torch.cat(ws, 1)
        w = torch.where(w > 0, w, 0.0)
        r, J = torch.where(w > 0, r, 0.0), torch.where(w[..., None] > 0, J, 0.0)
        Hm = (J * w[..., None]).transpose(1, 2) @ J  # B,6,6 normal equations
        g = ((J * w[..., None]) * r[..., None]).sum(1)
        n_used = (w > 0).sum(1)
        good = n_used >= min_residuals
        damp = 1e-6 * Hm.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(1e-12)
        eye = torch.eye(6, dtype=f64)
        xi = -torch.linalg.solve(Hm + damp[:, None, None] * eye + (~good)[:, None, None] * eye, g)
        T = torch.where(good[:, None, None], se3_exp(torch.where(good[:, None], xi, 0.0)) @ T, T)
    return AlignResult(T, n_used, n_used >= min_residuals)


def align_coarse_to_fine(gray_cur, depth_cur, gray_ref, depth_ref, K, T_init, *, levels=(2, 1), **kw) -> AlignResult:
    """:func:`align_to_keyframe` over the pyramid levels ``levels`` (downsampling factors of the inputs, coarsest
    first), each starting from the previous level's pose. Inputs as there, at the finest grid."""
    T = T_init
    for f in levels:
        gc, dc, Kc = downsample(gray_cur, depth_cur, K, f)
        gr, dr, _ = downsample(gray_ref, depth_ref, K, f)
        res = align_to_keyframe(gc, dc, gr, dr, Kc, T, **kw)
        T = res.T_ref_cur
    return res


def pose_distance(T_a: Tensor, T_b: Tensor, m_per_rad: float = 0.3) -> Tensor:
    """(...) translation distance + m_per_rad x rotation angle between camera poses (..., 4, 4)."""
    ang = rotation_angle(T_b[..., :3, :3].mT @ T_a[..., :3, :3])
    return torch.linalg.vector_norm(T_a[..., :3, 3] - T_b[..., :3, 3], dim=-1) + m_per_rad * ang


class Correction(NamedTuple):
    """T_world_color (B, 4, 4) float64 corrected poses; used (B,) applied; latest (B,) against the newest keyframe."""

    T_world_color: Tensor
    used: Tensor
    latest: Tensor


class KeyframeAligner:
    """The last ``count`` keyframes of each of B sequences (grey, depth, K on a coarse grid, colour camera pose in
    the tracker's world) and the correction of a current pose against the nearest of them.

    Args:
        count: keyframes kept per sequence (a ring buffer). factor: the stored grid is the input downsampled by it
            (640x480 -> 160x120 at 4); ``levels``: alignment pyramid factors on top of it, coarsest first.
        blend: 1 replaces the pose with the aligned one; in (0, 1) moves that fraction along the geodesic.
        max_step_m, max_step_deg: a correction larger than this is not applied (a failed alignment).
        align: keyword arguments of :func:`align_to_keyframe`.
    """

    def __init__(
        self, *, count: int = 5, factor: int = 4, levels: tuple[int, ...] = (2, 1), blend: float = 1.0,
        max_step_m: float = 0.05, max_step_deg: float = 5.0, **align,
    ) -> None:  # fmt: skip
        if count < 1 or factor < 1 or not 0.0 < blend <= 1.0:
            raise ValueError(
                f"KeyframeAligner: need count >= 1, factor >= 1, 0 < blend <= 1; got {count}, {factor}, {blend}"
            )
        self.count, self.factor, self.levels, self.blend = count, factor, tuple(levels), blend
        self.max_step_m, self.max_step_rad = max_step_m, max_step_deg * torch.pi / 180
        self.align = align
        self.reset()

    def reset(self) -> None:
        """Forget every keyframe (a new run)."""
        self.gray = self.depth = self.K = self.T_world_color = self.valid = self.n_added = None

    def add(self, gray: Tensor, depth: Tensor, K: Tensor, T_world_color: Tensor, mask: Tensor) -> None:
        """Store the frames of the sequences in ``mask`` (B,): gray, depth (B,1,H,W), K (B,3,3), T_world_color
        (B,4,4) camera-to-world of the colour camera. The first call must cover every sequence."""
        g, d, Kc = downsample(gray.float(), depth.float(), K.float(), self.factor)
        B = g.shape[0]
        if self.gray is None or self.gray.shape[0] != B:
            if not bool(mask.all()):
                raise ValueError("KeyframeAligner.add: the first call (or a new batch size) must cover every sequence")
            self.gray = g[:, None].repeat(1, self.count, 1, 1, 1)
            self.depth, self.K = d[:, None].repeat(1, self.count, 1, 1, 1), Kc[:, None].repeat(1, self.count, 1, 1)
            self.T_world_color = T_world_color.double()[:, None].repeat(1, self.count, 1, 1)
            self.valid = torch.zeros(B, self.count, dtype=torch.bool)
            self.n_added = torch.zeros(B, dtype=torch.long)
        rows = torch.nonzero(mask).flatten()
        slot = self.n_added[rows] % self.count
        self.gray[rows, slot], self.depth[rows, slot], self.K[rows, slot] = g[rows], d[rows], Kc[rows]
        self.T_world_color[rows, slot] = T_world_color.double()[rows]
        self.valid[rows, slot] = True
        self.n_added[rows] += 1

    def correct(self, gray: Tensor, depth: Tensor, T_world_color: Tensor, active: Tensor) -> Correction:
        """The corrected colour camera poses (B, 4, 4) float64 of the current frames (gray, depth (B,1,H,W) on the
        grid ``add`` saw) estimated at ``T_world_color``; ``used`` (B,) where a correction was applied (``active``
        sequences whose alignment to their nearest keyframe succeeded within the step limits); ``latest`` (B,)
        where that keyframe is the one added last (the tracker's current model frame)."""
        B = gray.shape[0]
        if self.gray is None or self.gray.shape[0] != B:
            raise ValueError(f"KeyframeAligner.correct: no keyframes stored for a batch of {B}")
        T_est = T_world_color.double()
        dist = pose_distance(T_est[:, None], self.T_world_color).masked_fill(~self.valid, float("inf"))
        k = dist.argmin(1)
        rows = torch.arange(B)
        T_kf = self.T_world_color[rows, k]
        g, d, _ = downsample(gray.float(), depth.float(), self.K[rows, k], self.factor)  # only the images are used
        res = align_coarse_to_fine(
            g, d, self.gray[rows, k], self.depth[rows, k], self.K[rows, k], T_inv(T_kf) @ T_est, levels=self.levels,
            **self.align,
        )  # fmt: skip
        T_new = T_kf @ res.T_ref_cur
        step = se3_log(T_new @ T_inv(T_est)) * self.blend  # B,6 left increment on the estimate
        small = (torch.linalg.vector_norm(T_new[:, :3, 3] - T_est[:, :3, 3], dim=-1) <= self.max_step_m) & (
            torch.linalg.vector_norm(step[:, 3:], dim=-1) <= self.max_step_rad * self.blend
        )
        use = active & res.valid & small & torch.isfinite(step).all(-1)
        T_out = se3_exp(torch.where(use[:, None], step, 0.0)) @ T_est
        latest = k == (self.n_added - 1) % self.count
        return Correction(torch.where(use[:, None, None], T_out, T_est), use, latest)


def set_backend_pose(backend, T_cam_obj: Tensor, mask: Tensor) -> None:
    """Move the pose of ``backend`` to ``T_cam_obj`` (B, 4, 4) for the sequences in ``mask`` (B,): an EKF's pose is
    replaced and its velocity and covariance kept (:meth:`~torchtrack.estimators.backends.EKFBackend.set_pose`); a
    registration back end's previous pose is replaced."""
    if hasattr(backend, "set_pose"):
        backend.set_pose(T_cam_obj, mask)
    elif getattr(backend, "T_prev", None) is not None:
        backend.T_prev = torch.where(mask[:, None, None], T_cam_obj.to(backend.T_prev.dtype), backend.T_prev)
