"""Pose-warped templates for landmark re-acquisition: the keyframe's window seen from the predicted viewpoint.

LK (eq. 10) tracks a translation of the template window; a landmark's window seen from a keyframe several frames
(or degrees) away is rotated, scaled and sheared, and the translation that best explains it is biased. The plane
through the landmark with the surface normal ``n`` (from the keyframe's depth) induces the homography

    H_cur_kf = K (R + t n^T / d) K^-1,    d = n^T X_kf,                            (Hartley & Zisserman, eq. 13.2)

with ``(R, t) = T_cur_kf`` between the colour cameras: a pixel of the plane in the keyframe maps to ``H x`` in the
current frame. :func:`track_warped` takes a square crop of current-frame pixels around the predicted position, one per
landmark: the template is the keyframe sampled through ``H^-1`` there, the target the current image there, and the
same pyramidal LK with the forward-backward (TIM) check runs between the two; the end point, plus the crop origin, is
the re-acquired pixel. The crops' pyramids are not built: :func:`crop_pyramids` gathers each level from the whole
images' pyramids (the frames' own, built once), the target by integer crops, the template by one bilinear gather
through the level's homography, for all landmarks of all keyframes in one call (``sample_through`` and ``crop_at`` are
level 0's references). With ``H`` the translation that takes the keyframe pixel to the prediction, the same code is
the unwarped template (the baseline the warp is measured against: experiments/warp_reacquire.py).

References: Hartley & Zisserman, "Multiple View Geometry", §13.1; Molton, Davison & Reid, "Locally Planar Patch
Features for Real-Time Structure from Motion", BMVC 2004 (patches warped by their normal).
Frames: ``kf`` and ``cur`` are colour cameras; pixels are colour pixels, centres at integers.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.config import FlowConfig, LandmarkConfig
from torchtrack.geometry import T_inv, backproject
from torchtrack.image.lk import forward_backward
from torchtrack.image.pyramid import Pyramid, build_pyramid, layout


def depth_normals(depth: Tensor, K: Tensor, pixels: Tensor, image: Tensor | None = None,
                  step: int = 3) -> tuple[Tensor, Tensor]:  # fmt: skip
    """Unit surface normals (B, C, 3) in the camera K (B, 3, 3) at ``pixels`` (B, C, 2), from the depth maps
    (I, 1, H, W) metres (pixel (b, c) in map ``image[b, c]``, default b): the cross product of central differences of
    the back-projected points ``step`` px apart (at the nearest pixel), turned towards the camera. Returns (normals,
    valid (B, C)): the four neighbours and the centre have depth and the differences are not parallel."""
    B, C = pixels.shape[:2]
    H, W = depth.shape[-2:]
    image = torch.arange(B, device=pixels.device)[:, None].expand(B, C) if image is None else image
    centre = pixels.round().long()
    offsets = torch.tensor([[step, 0], [-step, 0], [0, step], [0, -step]], device=pixels.device)
    nb = (centre[:, :, None] + offsets).clamp_min(0)  # B,C,4,2
    nb = torch.stack([nb[..., 0].clamp_max(W - 1), nb[..., 1].clamp_max(H - 1)], -1)
    z = depth.reshape(-1)[(image[..., None] * H + nb[..., 1]) * W + nb[..., 0]].to(K.dtype)  # B,C,4
    P = backproject(K, nb.reshape(B, C * 4, 2).to(K.dtype), z.reshape(B, C * 4)).reshape(B, C, 4, 3)
    n = torch.linalg.cross(P[:, :, 0] - P[:, :, 1], P[:, :, 2] - P[:, :, 3])
    norm = n.norm(dim=-1, keepdim=True)
    n = n / norm.clamp_min(1e-12)
    ray = backproject(K, centre.to(K.dtype), torch.ones(B, C, dtype=K.dtype, device=K.device))
    n = torch.where((n * ray).sum(-1, keepdim=True) > 0, -n, n)  # facing the camera
    return n, (z > 0).all(-1) & (norm[..., 0] > 1e-12)


def plane_homography(K: Tensor, T_cur_kf: Tensor, points_kf: Tensor, normals_kf: Tensor) -> Tensor:
    """(B, C, 3, 3) homographies ``K (R + t n^T / d) K^-1`` taking keyframe pixels to current pixels for the planes
    through ``points_kf`` (B, C, 3) with normals ``normals_kf`` (B, C, 3), both in the keyframe's colour camera;
    K (B, 3, 3); T_cur_kf (B, 4, 4) or, per landmark, (B, C, 4, 4) keyframe -> current colour camera."""
    T = T_cur_kf if T_cur_kf.dim() == 4 else T_cur_kf[:, None]
    R, t = T[..., :3, :3], T[..., :3, 3:]
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


def _pixel_index(pyr: Pyramid, level: int, image: Tensor, x: Tensor, y: Tensor) -> Tensor:
    """int32 flat indices into ``pyr.flat`` of the integer pixels (x, y) (int32) of the images ``image`` at ``level``
    (broadcast shapes), clamped into each image's padded block (so that (x + 1, y + 1) stays inside it too)."""
    h, w = pyr.size(level)
    p = pyr.pad
    first = ((pyr.row_start[level].to(image.device)[image] + p) * pyr.stride + p).int()
    return first + y.clamp(-p, h + p - 2) * pyr.stride + x.clamp(-p, w + p - 2)


def _take(flat: Tensor, index: Tensor) -> Tensor:
    return flat.index_select(0, index.reshape(-1)).view(index.shape)  # index_select: ~3x faster than flat[index]


def _sample_level(pyr: Pyramid, level: int, image: Tensor, M: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """(N, R, Cc) level ``level`` of the images ``image`` (N,) of ``pyr`` sampled bilinearly at ``M[n] (u, v, 1)``
    (M (N, 3, 3) float32, projective; u (Cc,), v (R,) the pixel grid); beyond the padded border its last pixels."""
    N = M.shape[0]
    along_u = (M[:, :, 0, None] * u.to(M.dtype))[:, :, None, :]  # N,3,1,Cc
    along_v = (M[:, :, 1, None] * v.to(M.dtype) + M[:, :, 2, None])[..., None]  # N,3,R,1
    P = along_u + along_v  # N,3,R,Cc homogeneous keyframe pixels
    h, w = pyr.size(level)
    p = pyr.pad
    big = float(max(h, w) + p)  # behind the camera or not finite: far outside, clamped
    xy = torch.nan_to_num(P[:, :2] / P[:, 2:], nan=-big, posinf=big, neginf=-big)  # N,2,R,Cc
    lo = torch.tensor([-p, -p], dtype=xy.dtype, device=xy.device).view(1, 2, 1, 1)
    hi = torch.tensor([w + p - 2, h + p - 2], dtype=xy.dtype, device=xy.device).view(1, 2, 1, 1)
    fl = torch.clamp(xy.floor(), lo, hi)
    frac = (xy - fl).clamp_(0, 1)
    fl = fl.int()
    i00 = _pixel_index(pyr, level, image[:, None, None], fl[:, 0], fl[:, 1]).reshape(-1)
    pairs = pyr.flat.as_strided((pyr.flat.numel() - 1, 2), (1, 1))  # (x, x + 1) in one gather
    top, bottom = pairs.index_select(0, i00), pairs.index_select(0, i00 + pyr.stride)
    fx, fy = frac[:, 0].reshape(-1), frac[:, 1].reshape(-1)
    out = torch.lerp(torch.lerp(top[:, 0], top[:, 1], fx), torch.lerp(bottom[:, 0], bottom[:, 1], fx), fy)
    return out.view(N, len(v), len(u))


def crop_pyramids(kf: Pyramid, cur: Pyramid, M: Tensor, kf_image: Tensor, cur_image: Tensor, origin: Tensor, crop: int,
                  levels: int, window: int) -> tuple[Pyramid, Pyramid]:  # fmt: skip
    """The LK pyramids of N square crops (side ``crop``, ``levels`` levels, padded for ``window``), taken from the
    pyramids of whole images instead of built (no blur): level l of crop n is

    - target: level l of ``cur``'s image ``cur_image[n]`` from pixel ``origin[n] / 2^l`` on (integer: ``origin`` (N, 2)
      int64 must be a multiple of 2^(levels - 1)), padding included (image content, not a reflected border);
    - template: level l of ``kf``'s image ``kf_image[n]`` sampled bilinearly through ``M[n]`` (N, 3, 3), which takes
      the crop's level-0 pixels to the keyframe's: level-l pixel u of the crop is keyframe level-l pixel
      ``D^-1 M D u`` (D = diag(2^l, 2^l, 1)). At level 0 this is :func:`sample_through` of the keyframe image; the
      coarse levels are the warped keyframe pyramid rather than the pyramid of the warped level 0 (LK's coarse levels
      only bring the start into the finest level's basin).

    Where the keyframe's or the current image's padded border ends, its last pixels are repeated. Returns
    (template, target) pyramids of N images each, of equal geometry (:func:`~torchtrack.image.pyramid.layout`).
    """
    N, dev = origin.shape[0], origin.device
    if max(kf.flat.numel(), cur.flat.numel()) >= 2**31:
        raise ValueError("crop_pyramids: pyramid buffers must have fewer than 2^31 values (int32 indices)")
    pad, sizes, heights, starts, row_start = layout(N, crop, crop, levels, window)
    stride = crop + 2 * pad
    with torch.inference_mode():  # as build_pyramid: the buffers are inference tensors
        bufs = [kf.flat.new_empty(1, sum(heights) * N, stride, dtype=torch.float32) for _ in range(2)]
        for level, (hl, wl) in enumerate(sizes):
            s = 2**level
            v = torch.arange(-pad, hl + pad, device=dev)  # the level's padded rows and columns, crop pixels
            u = torch.arange(-pad, wl + pad, device=dev)
            o = torch.div(origin, s, rounding_mode="floor").int()
            at = _pixel_index(cur, level, cur_image[:, None, None], (o[:, 0, None] + u.int())[:, None, :],
                              (o[:, 1, None] + v.int())[:, :, None])  # fmt: skip  # N,R,Cc
            target = _take(cur.flat, at)
            D = torch.diag(torch.tensor([s, s, 1.0], dtype=M.dtype, device=dev))
            template = _sample_level(kf, level, kf_image, (torch.linalg.inv(D) @ M @ D).float(), u, v)
            for buf, img in zip(bufs, (template, target), strict=True):
                block = buf[0, int(starts[level]) : int(starts[level]) + N * heights[level]].view(
                    N, heights[level], stride
                )
                block[..., : wl + 2 * pad] = img
                block[..., wl + 2 * pad :] = 0.0  # past a coarse level's rows (as build_pyramid)
    out = []
    for buf in bufs:
        images = [buf[:, int(s0) : int(s0) + N * ht].view(1, N, ht, stride)[..., pad : pad + hl, pad : pad + wl].transpose(0, 1)
                  for s0, ht, (hl, wl) in zip(starts, heights, sizes, strict=True)]  # fmt: skip
        out.append(Pyramid(images, buf.view(-1), row_start.to(dev), stride=stride, plane=buf[0].numel(), pad=pad))
    return out[0], out[1]


class WarpedTrack(NamedTuple):
    """pixels (B, C, 2) re-acquired colour pixels; status (B, C) tracked both ways; d_tim (B, C) eq. (10), px;
    residual (B, C) LK's mean absolute intensity difference."""

    pixels: Tensor
    status: Tensor
    d_tim: Tensor
    residual: Tensor


def _as_pyramid(x: Tensor | Pyramid, levels: int) -> Pyramid:
    if isinstance(x, Pyramid):
        if x.levels < levels:
            raise ValueError(f"track_warped: a pyramid of {x.levels} levels, LK needs {levels}")
        return x
    if x.dim() != 4 or x.shape[1] != 1:
        raise ValueError(f"track_warped: images must be (B, 1, H, W), got {tuple(x.shape)}")
    return build_pyramid(x.float(), levels)


def track_warped(kf_image: Tensor | Pyramid, cur_image: Tensor | Pyramid, H_cur_kf: Tensor, kf_pixels: Tensor,
                 valid: Tensor, init: Tensor | None = None, *, kf_index: Tensor | None = None,
                 crop: int = LandmarkConfig.warp_crop, window: int = FlowConfig.window, levels: int = FlowConfig.levels,
                 iters: int = FlowConfig.iters, eps: float = FlowConfig.eps, min_eig: float = FlowConfig.min_eig,
                 ic_iters: int = FlowConfig.ic_iters) -> WarpedTrack:  # fmt: skip
    """Track landmarks from the keyframe's template warped by ``H_cur_kf`` into the current image (module docstring).

    Args:
        kf_image, cur_image: (I, 1, H, W) and (B, 1, H, W) LK images (intensity in [0, 1]), or their LK pyramids
            (:func:`~torchtrack.image.pyramid.build_pyramid`, at least ``levels`` levels; the current frame's first B
            images are sequence b's): pass pyramids to reuse them.
        H_cur_kf: (B, C, 3, 3) keyframe -> current pixels (:func:`plane_homography` or :func:`translation_homography`).
        kf_pixels: (B, C, 2) the landmarks in the keyframe: the template's point is ``H kf_pixels``.
        valid: (B, C) bool: only these are tracked (one crop each), where the template's point is in the current image.
            init: (B, C, 2) or (B, C, J, 2) LK's start(s) in the current image (default: the template's point);
            results are (B, C) or (B, C, J) accordingly; pixels are the starts where not tracked.
        kf_index: (B, C) int64 the keyframe image of each landmark (default: b, I = B).
        crop: the square crop's side (px): LK's end point stays within it (about ``crop / 2`` from the template's
            point); rounded up to a multiple of 2^(levels - 1).
    """
    B, C = kf_pixels.shape[:2]
    if H_cur_kf.shape != (B, C, 3, 3) or valid.shape != (B, C):
        raise ValueError(f"track_warped: H_cur_kf (B, C, 3, 3), kf_pixels (B, C, 2), valid (B, C); got "
                         f"{tuple(H_cur_kf.shape)}, {tuple(kf_pixels.shape)}, {tuple(valid.shape)}")  # fmt: skip
    kf, cur = _as_pyramid(kf_image, levels), _as_pyramid(cur_image, levels)
    q = apply_homography(H_cur_kf, kf_pixels)  # B,C,2 the template's point in the current image
    init = q if init is None else init
    J = 1 if init.dim() == 3 else init.shape[2]
    starts = init.reshape(B, C, J, 2)
    rows = torch.arange(B, device=valid.device)[:, None].expand(B, C)
    kf_index = rows if kf_index is None else kf_index
    h, w = cur.size(0)
    inside = (q >= 0).all(-1) & (q[..., 0] <= w - 1) & (q[..., 1] <= h - 1)  # False where not finite
    b, c = (valid & inside).nonzero(as_tuple=True)  # one crop per tracked landmark
    pixels = starts.clone()  # the start where not tracked
    status = torch.zeros(B, C, J, dtype=torch.bool, device=valid.device)
    d_tim = torch.full((B, C, J), float("inf"), device=valid.device)
    residual = torch.zeros(B, C, J, device=valid.device)
    if len(b):
        m = 2 ** (levels - 1)
        crop = -(-crop // m) * m
        origin = (((q[b, c] - (crop - 1) / 2) / m).round() * m).long()  # N,2, level-aligned
        shift = torch.eye(3, dtype=H_cur_kf.dtype, device=H_cur_kf.device).repeat(len(b), 1, 1)
        shift[:, :2, 2] = origin.to(H_cur_kf.dtype)
        M = torch.linalg.solve(H_cur_kf[b, c], shift)  # crop pixels -> keyframe pixels
        template, target = crop_pyramids(kf, cur, M, kf_index[b, c], b, origin, crop, levels, window)
        o = origin[:, None].to(starts.dtype)
        points = (q[b, c][:, None] - o).expand(-1, J, 2).float()
        fwd, _, tim = forward_backward(template, target, points, init=(starts[b, c] - o).float(), window=window,
                                       levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters)  # fmt: skip
        pixels[b, c] = fwd.points.to(starts.dtype) + o
        status[b, c], d_tim[b, c], residual[b, c] = fwd.status, tim, fwd.residual
    shape = (B, C) if init.dim() == 3 else (B, C, J)
    return WarpedTrack(pixels.reshape(*shape, 2), status.reshape(shape), d_tim.reshape(shape), residual.reshape(shape))


def apply_homography(Hm: Tensor, x: Tensor) -> Tensor:
    """(..., 2) pixels ``x`` (..., 2) through the homographies ``Hm`` (..., 3, 3)."""
    p = (Hm @ torch.cat([x.to(Hm.dtype), torch.ones_like(x[..., :1], dtype=Hm.dtype)], -1)[..., None])[..., 0]
    return p[..., :2] / p[..., 2:]


def warped_landmark_tracks(kf_gray: Tensor | Pyramid, kf_depth: Tensor, cur_gray: Tensor | Pyramid, K: Tensor,
                           T_color_depth: Tensor, T_world_kf: Tensor, T_world_depth: Tensor, world: Tensor,
                           kf_pixels: Tensor, starts: Tensor, valid: Tensor, *, kf_index: Tensor | None = None,
                           **lk) -> WarpedTrack:  # fmt: skip
    """Landmarks re-tracked from their keyframes with pose-warped templates: the plane homography of each landmark (its
    world position ``world`` (B, C, 3) seen from its keyframe camera ``T_world_kf`` ((B, 4, 4), or (B, C, 4, 4) per
    landmark), the normal from its keyframe's depth at ``kf_pixels`` (B, C, 2)) between the keyframe and the current
    camera ``T_world_depth`` (B, 4, 4), then :func:`track_warped` from the keyframe images ``kf_gray`` into
    ``cur_gray`` (B, 1, H, W) started at ``starts`` (B, C, J, 2). Keyframe images (I, 1, H, W) (or their pyramid) and
    depths ``kf_depth`` (I, 1, H, W) (registered to colour): landmark (b, c)'s is ``kf_index[b, c]`` (default b).
    Landmarks without a normal are not tracked. ``lk``: :func:`track_warped`'s settings."""
    B, C = kf_pixels.shape[:2]
    T_cd = T_color_depth.double()
    T_kf = T_world_kf.double() if T_world_kf.dim() == 4 else T_world_kf.double()[:, None].expand(B, C, 4, 4)
    T_kf_col = T_kf @ T_inv(T_cd)[:, None]  # B,C: keyframe colour camera -> world
    T_cur_kf = (T_cd @ T_inv(T_world_depth.double()))[:, None] @ T_kf_col  # keyframe colour -> current colour camera
    X_kf = ((world.double() - T_kf_col[..., :3, 3])[..., None, :] @ T_kf_col[..., :3, :3])[..., 0, :]  # R^T (X - t)
    normals, has_normal = depth_normals(kf_depth, K.double(), kf_pixels.double(), kf_index)  # in K's dtype
    Hm = plane_homography(K.double(), T_cur_kf, X_kf, normals)
    return track_warped(kf_gray, cur_gray, Hm, kf_pixels.double(), valid & has_normal, starts.double(),
                        kf_index=kf_index, **lk)  # fmt: skip
