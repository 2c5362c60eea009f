"""The RGB-D rig: a colour camera and a depth camera one rigid extrinsic ``T_color_depth`` apart.

The tracker estimates the DEPTH camera's pose (its 3D measurements live there, eq. (6)); its world is its first depth
camera. Ground truth and written trajectories are the COLOUR camera's (TUM convention). These helpers are the one
place that converts between the two; every writer (run outputs, panorama, observation cache) goes through them. The
extrinsic is rigid, so the lever arm between the cameras rotates with the rig: a trajectory of the wrong camera is
off by a pose-dependent offset that an aligned ATE partly hides.

For registered depth (``T_color_depth`` = I, every TUM sequence) the two cameras coincide.

:func:`register_depth` resamples the depth camera's image into the colour camera's pixel grid.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry.camera import backproject, backproject_depth, project, sample_depth_bilinear
from torchtrack.geometry.se3 import T_inv


def T_world_color_from_depth(T_world_depth: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) colour-camera poses from depth-camera poses (..., 4, 4) of the same rig, in float64."""
    return T_world_depth.double() @ T_inv(T_color_depth.double())


def T_world_depth_from_color(T_world_color: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) depth-camera poses from colour-camera poses (..., 4, 4) of the same rig, in float64."""
    return T_world_color.double() @ T_color_depth.double()


def tracker_world(T_world_color_gt: Tensor, gt_valid: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) float64 ``T_world_tracker``: the tracker's world (its first depth camera) in ground truth's world,
    from the first frame's ground-truth colour pose ``T_world_color_gt`` (..., 4, 4) where ``gt_valid`` (...,); where
    there is none, the first colour camera is the world. Then ``T_world_depth = T_world_tracker @ T_tracker_depth``
    and the written pose is :func:`T_world_color_from_depth` of it, comparable with ground truth unaligned."""
    eye = torch.eye(4, dtype=torch.float64, device=T_world_color_gt.device).expand_as(T_world_color_gt)
    T_world_color0 = torch.where(gt_valid[..., None, None], T_world_color_gt.double(), eye)
    return T_world_depth_from_color(T_world_color0, T_color_depth)


def color_poses(T_world_tracker: Tensor, T_tracker_depth: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) float64 ``T_world_color``: the tracker's depth-camera poses ``T_tracker_depth`` (..., 4, 4) as the
    colour camera's poses in ground truth's world (``T_world_tracker`` from :func:`tracker_world`)."""
    return T_world_color_from_depth(T_world_tracker.double() @ T_tracker_depth.double(), T_color_depth)


def register_depth(
    depth: Tensor,
    K_depth: Tensor,
    K_color: Tensor,
    T_color_depth: Tensor,
    out_hw: tuple[int, int],
    iterations: int = 3,
    max_rel_residual: float = 1e-3,
) -> Tensor:
    """Depth (B, 1, H', W') seen by the colour camera at its pixel centres, from the depth camera's image ``depth``
    (B, 1, H, W) (metres, 0 = none); ``K_depth``, ``K_color`` (B, 3, 3), ``T_color_depth`` (B, 4, 4) depth-to-colour.

    Each colour pixel's ray is intersected with the depth camera's surface. The z-buffered forward warp
    (:func:`splat_depth`) picks the surface a pixel sees (the nearest) and a start depth;
    a fixed-point iteration then moves along the ray: project the ray's point at depth z into the depth camera, read
    the depth d there (bilinear on continuous surfaces, nearest across edges), and take the z at which the ray's point
    has depth d in the depth camera. The forward warp alone assigns a depth camera sample to the colour pixel it
    lands nearest, up to half a pixel away: on slanted surfaces and, worse, beside depth edges, the depth read at a
    feature is then another point's. The iteration converges where the surface's depth changes along the epipolar
    line more slowly than the ray's; a pixel whose iteration has not settled to ``max_rel_residual`` of its depth
    (an occlusion edge, a hole beside it) gets no depth rather than a wrong one.
    """
    B = depth.shape[0]
    if depth.dim() != 4 or depth.shape[1] != 1 or K_depth.shape != (B, 3, 3) or T_color_depth.shape != (B, 4, 4):
        raise ValueError(
            "register_depth: expected depth (B, 1, H, W), K_depth (B, 3, 3), T_color_depth (B, 4, 4); got "
            f"{tuple(depth.shape)}, {tuple(K_depth.shape)}, {tuple(T_color_depth.shape)}"
        )
    H2, W2 = out_hw
    z_all = splat_depth(depth, K_depth, K_color, T_color_depth, out_hw).reshape(B, -1)
    # Only the pixels the splat reached can settle: iterate on those, padded to the batch's largest count.
    n = int((z_all > 0).sum(1).max())
    order = torch.sort((z_all <= 0).to(torch.uint8), dim=1, stable=True).indices[:, :n]  # B,n: reached pixels first
    z = z_all.gather(1, order)
    seen = z > 0
    grid = torch.stack([order % W2, order // W2], -1).to(depth.dtype)  # B,n,2 their colour pixels
    T_depth_color = T_inv(T_color_depth)
    # The ray's point at colour depth z, in the depth camera: z a + t (a: the unit-depth ray turned into it).
    a = backproject(K_color, grid, torch.ones_like(grid[..., 0])) @ T_depth_color[:, :3, :3].transpose(-1, -2)
    t = T_depth_color[:, None, :3, 3]

    def depth_at(z: Tensor) -> Tensor:  # the depth camera's depth where the ray's point at z projects; 0: none
        p = z[..., None] * a + t
        ok = seen & (p[..., 2] > 0)
        pix = torch.where(ok[..., None], project(K_depth, torch.where(ok[..., None], p, 1.0)), -2.0)  # -2: outside
        return sample_depth_bilinear(depth, pix)

    for _ in range(iterations):
        d = depth_at(z)
        z_new = (d - t[..., 2]) / a[..., 2]
        seen = seen & (d > 0) & (z_new > 0)
        z = torch.where(seen, z_new, torch.zeros_like(z))
    d = depth_at(z)
    settled = seen & ((d - (z * a[..., 2] + t[..., 2])).abs() <= max_rel_residual * d)
    out = torch.zeros_like(z_all).scatter_(1, order, torch.where(settled, z, torch.zeros_like(z)))
    return out.reshape(B, 1, H2, W2)


def splat_depth(depth: Tensor, K_src: Tensor, K_dst: Tensor, T_dst_src: Tensor, out_hw: tuple[int, int]) -> Tensor:
    """Forward warp of ``depth`` (B, 1, H, W) into another camera (B, 1, H', W'), z-buffered, each sample written to
    the 2 x 2 pixels around where it lands (0 where none lands). Nearest-pixel writing (one pixel per sample) leaves
    cracks wherever noise or a slanted surface spreads neighbouring samples more than a pixel apart: with 1 mm of
    depth noise 10 cm off the colour camera, about a third of an object's pixels. The 2 x 2 footprint closes them at the
    cost of up to a pixel of dilation at edges, which :func:`register_depth`'s iteration then corrects."""
    B = depth.shape[0]
    H2, W2 = out_hw
    pts = backproject_depth(K_src, depth).reshape(B, -1, 3)
    p = pts @ T_dst_src[:, :3, :3].transpose(-1, -2) + T_dst_src[:, None, :3, 3]
    z = p[..., 2]
    front = (pts[..., 2] > 0) & (z > 0)
    uv = project(K_dst, torch.where(front[..., None], p, 1.0)).floor()
    big = torch.finfo(depth.dtype).max
    out = torch.full((B * H2 * W2,), big, dtype=depth.dtype, device=depth.device)
    base = torch.arange(B, device=depth.device)[:, None] * (H2 * W2)
    for du, dv in ((0, 0), (1, 0), (0, 1), (1, 1)):
        u, v = uv[..., 0] + du, uv[..., 1] + dv
        ok = front & (u >= 0) & (u < W2) & (v >= 0) & (v < H2)
        idx = (v.clamp(0, H2 - 1) * W2 + u.clamp(0, W2 - 1)).long() + base
        out.scatter_reduce_(0, idx[ok], z[ok], reduce="amin")
    return torch.where(out == big, torch.zeros_like(out), out).reshape(B, 1, H2, W2)
