"""Pinhole projection and back-projection, batched.

Pixel convention (OpenCV's): x to the right, y down, the centre of pixel (u, v) is at integer
coordinates (u, v). Camera frame: z forward, x right, y down. ``K`` is (B, 3, 3).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry.se3 import T_inv


def intrinsics_matrix(
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Tensor:
    """(3, 3) pinhole matrix."""
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def project(K: Tensor, points: Tensor) -> Tensor:
    """Camera points (..., N, 3) -> pixels (..., N, 2) through K (..., 3, 3). No z check."""
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    z = points[..., 2]
    return torch.stack([fx * points[..., 0] / z + cx, fy * points[..., 1] / z + cy], dim=-1)


def backproject(K: Tensor, pixels: Tensor, depth: Tensor) -> Tensor:
    """Pixels (..., N, 2) with depth (..., N) in metres -> camera points (..., N, 3)."""
    fx, fy = K[..., 0, 0, None], K[..., 1, 1, None]
    cx, cy = K[..., 0, 2, None], K[..., 1, 2, None]
    x = (pixels[..., 0] - cx) / fx * depth
    y = (pixels[..., 1] - cy) / fy * depth
    return torch.stack([x, y, depth], dim=-1)


def pixel_grid(H: int, W: int, dtype=torch.float32, device=None) -> Tensor:
    """(H, W, 2) pixel coordinates (x, y)."""
    ys, xs = torch.meshgrid(
        torch.arange(H, dtype=dtype, device=device), torch.arange(W, dtype=dtype, device=device), indexing="ij"
    )
    return torch.stack([xs, ys], dim=-1)


def backproject_depth(K: Tensor, depth: Tensor) -> Tensor:
    """Depth image (B, 1, H, W) -> point image (B, H, W, 3) in the camera; 0 depth gives 0 points."""
    if depth.dim() != 4 or depth.shape[1] != 1:
        raise ValueError(f"depth must be (B, 1, H, W), got {tuple(depth.shape)}")
    B, _, H, W = depth.shape
    grid = pixel_grid(H, W, depth.dtype, depth.device).reshape(1, H * W, 2).expand(B, -1, -1)
    pts = backproject(K, grid, depth.reshape(B, H * W))
    return pts.reshape(B, H, W, 3)


def sample_depth(depth: Tensor, pixels: Tensor) -> Tensor:
    """Depth (B, 1, H, W) read at pixels (B, N, 2) by nearest neighbour -> (B, N); 0 outside.

    Nearest (not bilinear) so that no depth is invented across depth edges or holes.
    """
    B, _, H, W = depth.shape
    u = pixels[..., 0].round().long()
    v = pixels[..., 1].round().long()
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    idx = (v.clamp(0, H - 1) * W + u.clamp(0, W - 1)).reshape(B, -1)
    z = depth.reshape(B, H * W).gather(1, idx).reshape(pixels.shape[:-1])
    return torch.where(inside, z, torch.zeros_like(z))


def warp_depth(depth: Tensor, K_src: Tensor, K_dst: Tensor, T_dst_src: Tensor, out_hw: tuple[int, int]) -> Tensor:
    """Forward-warp a depth image into another camera with a z-buffer (nearest pixel).

    Used to register depth to the colour camera: ``depth`` (B, 1, H, W) in the source (depth) camera,
    ``T_dst_src`` (B, 4, 4) the depth-to-colour extrinsic -> depth (B, 1, H', W') in the destination
    camera, 0 where nothing lands. Where several source pixels land on one pixel the nearest wins.
    """
    B = depth.shape[0]
    H2, W2 = out_hw
    pts = backproject_depth(K_src, depth).reshape(B, -1, 3)
    src_valid = pts[..., 2] > 0
    p = pts @ T_dst_src[:, :3, :3].transpose(-1, -2) + T_dst_src[:, None, :3, 3]
    z = p[..., 2]
    uv = project(K_dst, p).round()
    ok = src_valid & (z > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W2) & (uv[..., 1] >= 0) & (uv[..., 1] < H2)
    idx = (uv[..., 1].clamp(0, H2 - 1) * W2 + uv[..., 0].clamp(0, W2 - 1)).long()
    idx = idx + torch.arange(B, device=depth.device)[:, None] * (H2 * W2)
    big = torch.finfo(depth.dtype).max
    out = torch.full((B * H2 * W2,), big, dtype=depth.dtype, device=depth.device)
    out.scatter_reduce_(0, idx[ok], z[ok], reduce="amin")
    out = torch.where(out == big, torch.zeros_like(out), out)
    return out.reshape(B, 1, H2, W2)


def sample_depth_bilinear(depth: Tensor, pixels: Tensor, max_rel_step: float = 0.02) -> Tensor:
    """Depth (B, 1, H, W) at sub-pixel pixels (B, N, 2) -> (B, N): bilinear where the four neighbours
    have depth and agree within ``max_rel_step`` (a continuous surface), nearest elsewhere (no depth is
    invented across edges or holes); 0 outside the image.
    """
    B, _, H, W = depth.shape
    x, y = pixels[..., 0], pixels[..., 1]
    x0 = x.floor().clamp(0, W - 2)
    y0 = y.floor().clamp(0, H - 2)
    fx, fy = (x - x0).clamp(0, 1), (y - y0).clamp(0, 1)
    flat = depth.reshape(B, H * W)
    i00 = (y0 * W + x0).long().reshape(B, -1)
    z = torch.stack([flat.gather(1, i00 + d) for d in (0, 1, W, W + 1)], -1).reshape(*pixels.shape[:-1], 4)
    w = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1)
    zmin, zmax = z.min(-1).values, z.max(-1).values
    smooth = (zmin > 0) & (zmax - zmin <= max_rel_step * zmin)
    nearest = sample_depth(depth, pixels)
    return torch.where(smooth & (nearest > 0), (w * z).sum(-1), nearest)


def depth_along_rays(depth: Tensor, K_depth: Tensor, K: Tensor, T_color_depth: Tensor, pixels: Tensor, z0: Tensor,
                     iterations: int = 4, tol: float = 1e-3) -> Tensor:  # fmt: skip
    """The colour camera's depth (B, N) where the rays of colour pixels (B, N, 2) meet the surface a separate depth
    camera sees, 0 where they do not settle on one.

    A forward warp (:func:`warp_depth`) gives each colour pixel the depth of the nearest depth sample that lands
    there: half a pixel off on a slope and the wrong surface beside an edge. Instead each ray is intersected with the
    depth image itself: from the warped depth ``z0`` (B, N), the ray's point at colour depth z is moved into the
    depth camera (``inv(T_color_depth)``), projected (``K_depth``), the depth image read there (bilinear on
    continuous surfaces, nearest across edges: :func:`sample_depth_bilinear`), and z moved to the ray's point with
    that depth-camera depth; ``iterations`` fixed-point steps, kept where the last one moved z by at most ``tol``
    of it (a ray that grazes an edge or meets a hole does not settle: no depth, the pixel is measured without it).
    depth: (B, 1, H_d, W_d) the depth camera's image (m, 0 = none); K_depth, K (B, 3, 3); T_color_depth (B, 4, 4).
    """
    dt = z0.dtype
    T_dc = T_inv(T_color_depth.to(dt))
    ray = backproject(K.to(dt), pixels.to(dt), torch.ones_like(z0))  # the colour ray at colour depth 1
    a = ray @ T_dc[:, :3, :3].transpose(-1, -2)  # B,N,3: the ray's direction in the depth camera
    t = T_dc[:, None, :3, 3]  # B,1,3: the colour centre there
    az = a[..., 2]
    z, settled = z0, torch.zeros_like(z0, dtype=torch.bool)
    for _ in range(iterations):
        X = z[..., None] * a + t
        front = X[..., 2] > 1e-3
        zd = sample_depth_bilinear(depth, project(K_depth.to(dt), torch.where(front[..., None], X, 1.0)))
        step = torch.where(front & (zd > 0) & (az.abs() > 1e-6), (zd - t[..., 2]) / az, torch.zeros_like(z))
        settled = (step > 0) & ((step - z).abs() <= tol * step)
        z = step
    return torch.where(settled, z, torch.zeros_like(z))
