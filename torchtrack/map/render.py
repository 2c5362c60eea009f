"""Pictures of a point map without a display or GPU: z-buffered square splats in torch.

Two views: a perspective view from a camera (the first one, with a wider field of view so that the panorama
beyond the first frame shows) and an orthographic top-down view looking along that camera's image "down" axis
(its +y: a hand-held sequence starts roughly level, so this is gravity's direction to a few degrees).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry import T_inv, transform_points


def splat(
    uv: Tensor, z: Tensor, rgb: Tensor, size: tuple[int, int], radius: Tensor | int = 0, background: float = 1.0
) -> tuple[Tensor, Tensor]:
    """Z-buffered splats: each point covers the (2r+1)^2 pixels about its pixel and the nearest point wins.

    Args:
        uv: (M, 2) pixel coordinates (x, y); z: (M,) depth along the view (smaller = nearer); rgb: (M, 3) in [0, 1].
        size: (H, W) of the image; radius: splat radius in pixels, (M,) int64 or one int.
    Returns:
        image (3, H, W) float32 (``background`` where nothing lands) and zbuf (H, W) (inf where nothing lands).
    """
    if uv.dim() != 2 or uv.shape[-1] != 2 or z.shape != uv.shape[:1] or rgb.shape != (len(uv), 3):
        raise ValueError(f"splat: need uv (M, 2), z (M,), rgb (M, 3); got {tuple(uv.shape)}, {tuple(z.shape)}, "
                         f"{tuple(rgb.shape)}")  # fmt: skip
    H, W = size
    radius = torch.as_tensor(radius, dtype=torch.int64, device=uv.device).expand(len(uv))
    r_max = int(radius.max()) if len(uv) else 0
    px = uv.round().long()
    z = z.float()
    zbuf = torch.full((H * W,), float("inf"), device=uv.device)
    image = torch.full((H * W, 3), float(background), device=uv.device)
    offsets = [(dx, dy) for dy in range(-r_max, r_max + 1) for dx in range(-r_max, r_max + 1)]

    def covered(dx: int, dy: int) -> tuple[Tensor, Tensor]:
        x, y = px[:, 0] + dx, px[:, 1] + dy
        ok = (x >= 0) & (x < W) & (y >= 0) & (y < H) & (radius >= max(abs(dx), abs(dy)))
        return ok, y * W + x

    for dx, dy in offsets:  # pass 1: the nearest depth per pixel
        ok, idx = covered(dx, dy)
        zbuf.scatter_reduce_(0, idx[ok], z[ok], reduce="amin")
    for dx, dy in offsets:  # pass 2: the colour of the point that holds it
        ok, idx = covered(dx, dy)
        ok &= z <= zbuf[idx.clamp(0, H * W - 1)]
        image[idx[ok]] = rgb[ok].float()
    return image.T.reshape(3, H, W), zbuf.reshape(H, W)


def perspective_view(
    xyz: Tensor, rgb: Tensor, T_world_cam: Tensor, K: Tensor, size: tuple[int, int], voxel_size: float,
    zoom: float = 0.5,
) -> Tensor:  # fmt: skip
    """(3, H, W) the points xyz (M, 3) world seen from T_world_cam (4, 4) through K (3, 3) with its focal lengths
    times ``zoom`` (0.5: twice the field of view); each point splatted to its voxel's projected size."""
    p = transform_points(T_inv(T_world_cam.double()), xyz.double())
    front = p[:, 2] > 0.05
    p, c = p[front], rgb[front]
    Kz = K.double().clone()
    Kz[:2, :2] *= zoom
    Kz[0, 2], Kz[1, 2] = size[1] / 2, size[0] / 2
    uv = torch.stack([Kz[0, 0] * p[:, 0] / p[:, 2] + Kz[0, 2], Kz[1, 1] * p[:, 1] / p[:, 2] + Kz[1, 2]], -1)
    radius = (Kz[0, 0] * voxel_size / p[:, 2] / 2).round().long().clamp(0, 3)
    return splat(uv, p[:, 2], c, size, radius)[0]


def top_down_view(
    xyz: Tensor, rgb: Tensor, T_world_cam: Tensor, size: tuple[int, int], voxel_size: float, margin: float = 0.03
) -> Tensor:
    """(3, H, W) orthographic view of xyz (M, 3) from above: image right = the camera's x, image up = its viewing
    direction projected on the ground, depth = the camera's +y ("down"); scaled to fit (1st-99th percentile box)."""
    if len(xyz) == 0:
        return torch.ones(3, *size, device=xyz.device)
    R = T_world_cam[:3, :3].double()
    down = R[:, 1]
    right = R[:, 0] - (R[:, 0] @ down) * down
    right = right / right.norm()
    ahead = torch.linalg.cross(down, right)  # right-handed (right, down, ahead): ahead ~ the viewing direction
    p = xyz.double()
    a, f, d = p @ right, p @ ahead, p @ down
    few = torch.stack([a, f], -1)[:: max(1, len(p) // 1_000_000)]  # torch.quantile takes at most 16M values
    lo, hi = torch.quantile(few, 0.01, dim=0), torch.quantile(few, 0.99, dim=0)
    H, W = size
    span = (hi - lo).clamp_min(1e-6)
    scale = float(min((W * (1 - 2 * margin)) / span[0], (H * (1 - 2 * margin)) / span[1]))  # pixels per metre
    centre = (lo + hi) / 2
    uv = torch.stack([(a - centre[0]) * scale + W / 2, -(f - centre[1]) * scale + H / 2], -1)
    radius = min(3, round(scale * voxel_size / 2))
    return splat(uv, d, rgb, size, radius)[0]  # d along "down": the highest point is the nearest
