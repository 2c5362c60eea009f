"""Kinect v1-like sensor noise for rendered RGB-D frames (parameters and references: :class:`KinectNoise`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.data.synthetic.config import KinectNoise
from torchtrack.data.synthetic.render import RGBD


def depth_sigma(z: Tensor, k: KinectNoise) -> Tensor:
    """Axial standard deviation (metres) of a depth measurement at z metres: sigma_scale (a + b (z - z0)^2)."""
    return k.sigma_scale * (k.sigma_a_m + k.sigma_b_per_m * (z - k.sigma_z0_m) ** 2)


def quantise_disparity(z: Tensor, k: KinectNoise) -> Tensor:
    """Snap depths z > 0 to the Kinect's disparity grid: d = f b / z rounded to ``disparity_subpixel`` pixels.

    Depth steps grow as z^2 / (f b) * subpixel (2.9 mm at 1 m with the defaults). 0 stays 0.
    """
    if k.disparity_subpixel <= 0:
        return z
    fb = k.disparity_focal_px * k.disparity_baseline_m
    steps = torch.round(fb / (z * k.disparity_subpixel))
    zq = fb / (steps.clamp_min(1) * k.disparity_subpixel)
    return torch.where(z > 0, zq, z)


def edge_holes(depth: Tensor, jump_m: float, dilate_px: int) -> Tensor:
    """Bool (B, 1, H, W): pixels next to a depth jump larger than jump_m (4-neighbours), dilated by dilate_px.

    A missing neighbour (depth 0) counts as a jump, as at silhouettes against empty background.
    """
    jx = (depth[..., :, 1:] - depth[..., :, :-1]).abs() > jump_m
    jy = (depth[..., 1:, :] - depth[..., :-1, :]).abs() > jump_m
    hole = torch.zeros_like(depth, dtype=torch.bool)
    hole[..., :, 1:] |= jx
    hole[..., :, :-1] |= jx
    hole[..., 1:, :] |= jy
    hole[..., :-1, :] |= jy
    if dilate_px > 0:
        size = 2 * dilate_px + 1
        hole = F.max_pool2d(hole.float(), size, stride=1, padding=dilate_px) > 0
    return hole


def apply_kinect_noise(rgbd: RGBD, k: KinectNoise, generator: torch.Generator) -> RGBD:
    """Noisy copy of a clean frame: rgb (3, H, W) or (B, 3, H, W), depth (1, H, W) or (B, 1, H, W).

    Depth: z + sigma(z) N(0, 1), snapped to the disparity grid, then removed at depth edges, at random
    dropouts and outside [min_depth_m, max_depth_m]. Colour: + rgb_sigma N(0, 1), clamped to [0, 1].
    Deterministic given the generator's state.
    """
    rgb, depth = rgbd
    if depth.shape[-3] != 1 or rgb.shape[-3] != 3 or rgb.shape[-2:] != depth.shape[-2:]:
        raise ValueError(
            f"apply_kinect_noise: need rgb (..., 3, H, W) and depth (..., 1, H, W), got {tuple(rgb.shape)}, {tuple(depth.shape)}"
        )
    z = depth + depth_sigma(depth, k) * torch.randn(depth.shape, generator=generator)
    z = quantise_disparity(z.clamp_min(0), k)
    holes = edge_holes(depth.reshape(-1, 1, *depth.shape[-2:]), k.edge_jump_m, k.edge_dilate_px).reshape(depth.shape)
    holes |= torch.rand(depth.shape, generator=generator) < k.dropout_prob
    holes |= (depth <= 0) | (z < k.min_depth_m) | (z > k.max_depth_m)
    noisy_rgb = (rgb + k.rgb_sigma * torch.randn(rgb.shape, generator=generator)).clamp(0, 1)
    return RGBD(noisy_rgb, torch.where(holes, torch.zeros_like(z), z))
