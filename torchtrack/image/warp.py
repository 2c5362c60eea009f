"""Pose-warped templates for landmark re-acquisition: the keyframe's window seen from the predicted viewpoint.

LK (eq. 10) tracks a translation of the template window; a landmark's window seen from a keyframe several frames
(or degrees) away is rotated, scaled and sheared, and the translation that best explains it is biased. The plane
through the landmark with the surface normal ``n`` (from the keyframe's depth) induces the homography

    H_cur_kf = K (R + t n^T / d) K^-1,    d = n^T X_kf,                            (Hartley & Zisserman, eq. 13.2)

with ``(R, t) = T_cur_kf`` between the colour cameras: a pixel of the plane in the keyframe maps to ``H x`` in the
current frame. :func:`track_warped` samples the keyframe image through ``H^-1`` on a square crop of current-frame
pixels around the predicted position (the template), crops the current image at the same integer origin, and runs
the same pyramidal LK with the forward-backward (TIM) check between the two; the end point, plus the crop origin, is
the re-acquired pixel. With ``H`` the translation that takes the keyframe pixel to the prediction, the same code is the
unwarped template (the baseline the warp is measured against: experiments/warp_reacquire.py).

References: Hartley & Zisserman, "Multiple View Geometry", §13.1; Molton, Davison & Reid, "Locally Planar Patch
Features for Real-Time Structure from Motion", BMVC 2004 (patches warped by their normal).
Frames: ``kf`` and ``cur`` are colour cameras; pixels are colour pixels, centres at integers.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.config import FlowConfig
from torchtrack.geometry import T_inv, backproject, transform_points
from torchtrack.image.lk import forward_backward


def depth_normals(depth: Tensor, K: Tensor, pixels: Tensor, step: int = 3) -> tuple[Tensor, Tensor]:
    """Unit surface normals (B, C, 3) in the camera at ``pixels`` (B, C, 2), from the depth map (B, 1, H, W) metres:
    the cross product of central differences of the back-projected points ``step`` px apart (at the nearest pixel),
    turned towards the camera. Returns (normals, valid (B, C)): the four neighbours and the centre have depth and
    the differences are not parallel."""
    B, C = pixels.shape[:2]
    H, W = depth.shape[-2:]
    centre = pixels.round().long()
    offsets = torch.tensor([[step, 0], [-step, 0], [0, step], [0, -step]], device=pixels.device)
    nb = (centre[:, :, None] + offsets).clamp_min(0)  # B,C,4,2
    nb = torch.stack([nb[..., 0].clamp_max(W - 1), nb[..., 1].clamp_max(H - 1)], -1)
    flat = depth.reshape(B, H * W)
    z = flat.gather(1, (nb[..., 1] * W + nb[..., 0]).reshape(B, C * 4)).reshape(B, C, 4)
    P = backproject(K, nb.reshape(B, C * 4, 2).to(depth.dtype), z.reshape(B, C * 4)).reshape(B, C, 4, 3)
    n = torch.linalg.cross(P[:, :, 0] - P[:, :, 1], P[:, :, 2] - P[:, :, 3])
    norm = n.norm(dim=-1, keepdim=True)
    n = n / norm.clamp_min(1e-12)
    ray = backproject(K, centre.to(depth.dtype), torch.ones(B, C, dtype=depth.dtype, device=depth.device))
    n = torch.where((n * ray).sum(-1, keepdim=True) > 0, -n, n)  # facing the camera
    return n, (z > 0).all(-1) & (norm[..., 0] > 1e-12)


def plane_homography(K: Tensor, T_cur_kf: Tensor, points_kf: Tensor, normals_kf: Tensor) -> Tensor:
    """(B, C, 3, 3) homographies ``K (R + t n^T / d) K^-1`` taking keyframe pixels to current pixels for the planes
    through ``points_kf`` (B, C, 3) with normals ``normals_kf`` (B, C, 3), both in the keyframe's colour camera;
    K (B, 3, 3); T_cur_kf (B, 4, 4) keyframe -> current colour camera."""
    R, t = T_cur_kf[:, None, :3, :3], T_cur_kf[:, None, :3, 3:]
    d = (normals_kf * points_kf).sum(-1)[..., None, None]  # B,C,1,1
    Hm = R + t @ normals_kf[..., None, :] / d
    return K[:, None] @ Hm @ torch.linalg.inv(K)[:, None]


def translation_homography(kf_pixels: Tensor, predicted: Tensor) -> Tensor:
    """(B, C, 3, 3) the translations taking ``kf_pixels`` (B, C, 2) to ``predicted`` (B, C, 2): the unwarped
    template."""
    Hm = torch.eye(3, dtype=predicted.dtype, device=predicted.device).repeat(*predicted.shape[:2], 1, 1)
    Hm[..., :2, 2] = predicted - kf_pixels
    return Hm


def sample_through(image: Tensor, M: Tensor, size: int) -> Tensor:
    """(B, C, ch, size, size) windows: pixel u of window c is ``image[b]`` (B, ch, H, W) bilinearly sampled at
    ``M[b, c] (u, 1)`` (M (B, C, 3, 3), projective; zeros outside the image). Coordinates in float32 (1e-4 px at
    1000 px), sampled in the image's dtype."""
    B, C = M.shape[:2]
    H, W = image.shape[-2:]
    M = M.float()
    r = torch.arange(size, dtype=torch.float32, device=M.device)
    u, v = r.view(1, 1, 1, size), r.view(1, 1, size, 1)
    p = [M[:, :, i, 0, None, None] * u + M[:, :, i, 1, None, None] * v + M[:, :, i, 2, None, None] for i in range(3)]
    gx = p[0] / p[2] * (2.0 / (W - 1)) - 1
    gy = p[1] / p[2] * (2.0 / (H - 1)) - 1
    grid = torch.stack([gx, gy], -1).reshape(B, C * size, size, 2).to(image.dtype)
    out = F.grid_sample(image, grid, align_corners=True, padding_mode="zeros")
    return out.reshape(B, image.shape[1], C, size, size).transpose(1, 2)


def crop_at(image: Tensor, origin: Tensor, size: int) -> Tensor:
    """(B, C, ch, size, size) crops of ``image`` (B, ch, H, W) whose pixel (0, 0) is at the integer ``origin`` (B, C, 2)
    (x, y); zeros outside the image (:func:`sample_through` of a translation, without interpolation)."""
    B, ch, H, W = image.shape
    C = origin.shape[1]
    r = torch.arange(size, device=image.device)
    x = origin[..., 0].long()[..., None] + r  # B,C,S
    y = origin[..., 1].long()[..., None] + r
    inside = ((x >= 0) & (x < W))[:, :, None, :] & ((y >= 0) & (y < H))[:, :, :, None]  # B,C,S,S
    flat = (y.clamp(0, H - 1)[:, :, :, None] * W + x.clamp(0, W - 1)[:, :, None, :]).reshape(B, 1, C * size * size)
    out = image.reshape(B, ch, H * W).gather(2, flat.expand(B, ch, -1)).reshape(B, ch, C, size, size)
    return (out * inside[:, None].to(out.dtype)).transpose(1, 2)


class WarpedTrack(NamedTuple):
    """pixels (B, C, 2) re-acquired colour pixels; status (B, C) tracked both ways; d_tim (B, C) eq. (10), px;
    residual (B, C) LK's mean absolute intensity difference."""

    pixels: Tensor
    status: Tensor
    d_tim: Tensor
    residual: Tensor


def track_warped(kf_image: Tensor, cur_image: Tensor, H_cur_kf: Tensor, kf_pixels: Tensor, valid: Tensor,
                 init: Tensor | None = None, *, crop: int = 96, window: int = FlowConfig.window,
                 levels: int = FlowConfig.levels, iters: int = FlowConfig.iters, eps: float = FlowConfig.eps,
                 min_eig: float = FlowConfig.min_eig, ic_iters: int = FlowConfig.ic_iters) -> WarpedTrack:  # fmt: skip
    """Track landmarks from the keyframe's template warped by ``H_cur_kf`` into the current image (module docstring).

    Args:
        kf_image, cur_image: (B, ch, H, W) the keyframe's and the current frame's LK images (intensity in [0, 1]).
        H_cur_kf: (B, C, 3, 3) keyframe -> current pixels (:func:`plane_homography` or :func:`translation_homography`).
        kf_pixels: (B, C, 2) the landmarks in the keyframe: the template's point is ``H kf_pixels``.
        valid: (B, C) bool. init: (B, C, 2) or (B, C, J, 2) LK's start(s) in the current image (default: the
            template's point); results are (B, C) or (B, C, J) accordingly.
        crop: the square crop's side (px): the window at the coarsest level plus the search range.
    """
    B, C = kf_pixels.shape[:2]
    q = apply_homography(H_cur_kf, kf_pixels)
    init = q if init is None else init
    J = 1 if init.dim() == 3 else init.shape[2]
    origin = q.round() - crop // 2  # B,C,2 integer
    shift = torch.eye(3, dtype=H_cur_kf.dtype, device=H_cur_kf.device).repeat(B, C, 1, 1)
    shift[..., :2, 2] = origin.to(H_cur_kf.dtype)
    template = sample_through(kf_image.float(), torch.linalg.solve(H_cur_kf, shift), crop)  # B,C,ch,S,S float32
    target = crop_at(cur_image.float(), origin, crop)  # LK's images are float32
    o = origin[:, :, None].to(init.dtype)
    points = (q[:, :, None] - o).expand(B, C, J, 2).reshape(B * C, J, 2).float()
    start = (init.reshape(B, C, J, 2) - o).reshape(B * C, J, 2).float()
    ok = valid[:, :, None].expand(B, C, J).reshape(B * C, J)
    fwd, _, d_tim = forward_backward(
        template.reshape(B * C, *template.shape[2:]).contiguous(), target.reshape(B * C, *target.shape[2:]).contiguous(),
        points, init=start, valid=ok, window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig,
        ic_iters=ic_iters,
    )  # fmt: skip
    shape = (B, C, 2) if init.dim() == 3 else (B, C, J, 2)
    pixels = (fwd.points.reshape(B, C, J, 2).to(init.dtype) + o).reshape(shape)
    status = (fwd.status & ok).reshape(shape[:-1])
    return WarpedTrack(pixels, status, d_tim.reshape(shape[:-1]), fwd.residual.reshape(shape[:-1]))


def apply_homography(Hm: Tensor, x: Tensor) -> Tensor:
    """(..., 2) pixels ``x`` (..., 2) through the homographies ``Hm`` (..., 3, 3)."""
    p = (Hm @ torch.cat([x.to(Hm.dtype), torch.ones_like(x[..., :1], dtype=Hm.dtype)], -1)[..., None])[..., 0]
    return p[..., :2] / p[..., 2:]


def warped_landmark_tracks(kf_gray: Tensor, kf_depth: Tensor, cur_gray: Tensor, K: Tensor, T_color_depth: Tensor,
                           T_world_kf: Tensor, T_world_depth: Tensor, world: Tensor, kf_pixels: Tensor, starts: Tensor,
                           valid: Tensor, **lk) -> WarpedTrack:  # fmt: skip
    """Landmarks re-tracked from one keyframe with pose-warped templates: the plane homography of each landmark (its
    world position ``world`` (B, C, 3) seen from the keyframe camera ``T_world_kf`` (B, 4, 4), the normal from the
    keyframe's depth ``kf_depth`` (B, 1, H, W, registered to colour) at ``kf_pixels`` (B, C, 2)) between the keyframe
    and the current camera ``T_world_depth`` (B, 4, 4), then :func:`track_warped` from ``kf_gray`` into ``cur_gray``
    (B, 1, H, W) started at ``starts`` (B, C, J, 2). Landmarks without a normal are not tracked. ``lk``: LK settings."""
    T_cd = T_color_depth.double()
    T_kf_col = T_world_kf.double() @ T_inv(T_cd)  # keyframe colour camera -> world
    T_cur_kf = T_cd @ T_inv(T_world_depth.double()) @ T_kf_col  # keyframe colour -> current colour camera
    X_kf = transform_points(T_inv(T_kf_col), world.double())
    normals, has_normal = depth_normals(kf_depth.double(), K.double(), kf_pixels.double())
    Hm = plane_homography(K.double(), T_cur_kf, X_kf, normals)
    return track_warped(kf_gray, cur_gray, Hm, kf_pixels.double(), valid & has_normal, starts.double(), **lk)
