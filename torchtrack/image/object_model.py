"""Object model: selection of the object by depth, its coloured point-cloud model (PCM), Table I's spread.

Paper §III: the object is the set of pixels whose depth lies in [near, far] (optionally only the
largest connected region), or the whole frame for scene tracking; its back-projected coloured points
are the PCM, and the mask is the region of interest handed to the feature selector (eq. 9).

Automatic [near, far] (:func:`depth_range`): the object is taken to be the nearest *depth layer*
holding a noticeable share of the valid pixels. Valid depths are binned (``bin_size``); a bin is
occupied when it holds more than ``min_bin_fraction`` of the valid pixels (which ignores stray
flying pixels at silhouettes); layers are runs of occupied bins separated by a gap of at least
``gap`` metres; the nearest layer with at least ``min_fraction`` of the valid pixels is the object
and its extent is [near, far]. An object in front of a distant background is thus cut out, while a
scene without such a gap (a room, an object on a table) is kept whole: give near/far explicitly
there.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.geometry import backproject_depth, project


def _check_depth(depth: Tensor, where: str) -> None:
    if depth.dim() != 4 or depth.shape[1] != 1:
        raise ValueError(f"{where}: depth must be (B, 1, H, W), got {tuple(depth.shape)}")


def depth_range(
    depth: Tensor,
    *,
    bin_size: float = 0.01,
    gap: float = 0.1,
    min_fraction: float = 0.05,
    min_bin_fraction: float = 1e-4,
) -> tuple[Tensor, Tensor]:
    """Automatic [near, far] (metres, each (B,)) of the nearest depth layer (module docstring).

    Sequences without valid depth get near = far = 0 (an empty object).
    """
    _check_depth(depth, "depth_range")
    B = depth.shape[0]
    z = depth.reshape(B, -1)
    has = z > 0
    n_valid = has.sum(1)  # B
    n_bins = max(1, math.ceil(float(z.max()) / bin_size) + 1)
    idx = torch.where(has, (z / bin_size).long().clamp_max(n_bins - 1), torch.zeros_like(z, dtype=torch.long))
    counts = torch.zeros(B, n_bins, dtype=torch.float32, device=depth.device)
    counts.scatter_add_(1, idx, has.float())
    occupied = counts > min_bin_fraction * n_valid[:, None]
    g = max(1, round(gap / bin_size))
    # Close gaps shorter than g bins: dilate then erode by g // 2 (a morphological closing, 1-D).
    occ = occupied.float()[:, None]
    closed = F.max_pool1d(F.pad(occ, (g // 2, g // 2)), g // 2 * 2 + 1, stride=1)
    closed = -F.max_pool1d(F.pad(-closed, (g // 2, g // 2), value=-1.0), g // 2 * 2 + 1, stride=1)
    closed = (closed[:, 0] > 0) | occupied
    starts = closed & ~F.pad(closed[:, :-1], (1, 0), value=False)
    layer = torch.cumsum(starts.long(), dim=1) * closed  # 1, 2, ... per layer, 0 between layers
    layer_counts = torch.zeros(B, n_bins + 1, device=depth.device).scatter_add_(1, layer, counts)
    layer_counts[:, 0] = 0
    big = layer_counts >= min_fraction * n_valid[:, None].clamp_min(1)
    first = torch.where(big.any(1), big.float().argmax(1), torch.zeros_like(n_valid))  # B; 0 = none
    in_layer = (layer == first[:, None]) & (first[:, None] > 0) & occupied
    bins = torch.arange(n_bins, device=depth.device).expand(B, -1)
    lo = torch.where(in_layer, bins, torch.full_like(bins, n_bins)).amin(1)
    hi = torch.where(in_layer, bins, torch.full_like(bins, -1)).amax(1)
    found = hi >= 0
    zero = depth.new_zeros(B)
    near = torch.where(found, lo.to(depth.dtype) * bin_size, zero)
    far = torch.where(found, (hi + 1).to(depth.dtype) * bin_size, zero)
    return near, far


def keep_largest_component(mask: Tensor) -> Tensor:
    """Largest 8-connected region of each mask (B, 1, H, W) bool (kornia's union-find labelling)."""
    B = mask.shape[0]
    labels = kornia.contrib.connected_components_union_find(mask).reshape(B, -1)  # distinct across the batch
    flat = labels.reshape(-1)
    counts = torch.bincount(flat, minlength=int(flat.max()) + 1)
    counts[0] = 0
    per_pixel = counts[labels]  # size of each pixel's component
    best = per_pixel.amax(1, keepdim=True)
    # Ties between equal-size components: keep the one with the smallest label.
    best_label = torch.where(per_pixel == best, labels, torch.full_like(labels, flat.max() + 1)).amin(1, keepdim=True)
    return ((labels == best_label) & (best > 0)).reshape(mask.shape)


def object_mask(
    depth: Tensor,
    *,
    near: float | Tensor | None = None,
    far: float | Tensor | None = None,
    largest_component: bool = False,
    whole_frame: bool = False,
    erode_px: int = 0,
    **range_kwargs,
) -> Tensor:
    """The object's pixels by depth thresholding: (B, 1, H, W) bool.

    Args:
        depth: (B, 1, H, W) metres, 0 = none.
        near, far: the depth interval in metres (floats or (B,) tensors); either one missing is taken
            from :func:`depth_range` (``range_kwargs`` passed on).
        largest_component: keep only the largest 8-connected region (kornia).
        whole_frame: the object is every pixel with depth (scene tracking); near/far are ignored.
        erode_px: keep only pixels whose whole (2 erode_px + 1)^2 window is in the mask (after the largest
            component): a feature's LK window then lies on the object, not across its silhouette, where the
            background does not follow the object's motion and biases the track.
    """
    _check_depth(depth, "object_mask")
    B = depth.shape[0]
    has = depth > 0
    if whole_frame:
        mask = has
    else:
        if near is None or far is None:
            auto_near, auto_far = depth_range(depth, **range_kwargs)
            near = auto_near if near is None else near
            far = auto_far if far is None else far
        near = torch.as_tensor(near, dtype=depth.dtype, device=depth.device).expand(B).view(B, 1, 1, 1)
        far = torch.as_tensor(far, dtype=depth.dtype, device=depth.device).expand(B).view(B, 1, 1, 1)
        mask = has & (depth >= near) & (depth <= far)
    mask = keep_largest_component(mask) if largest_component else mask
    return erode(mask, erode_px) if erode_px > 0 else mask


def erode(mask: Tensor, radius: int) -> Tensor:
    """(B, 1, H, W) bool: pixels whose whole (2 radius + 1)^2 window (clipped at the image border) is in mask."""
    size = 2 * radius + 1
    return -F.max_pool2d(-mask.float(), size, stride=1, padding=radius) > 0.5


class ObjectRegion:
    """Holds the object-selection parameters; ``__call__(depth) -> (B, 1, H, W) bool`` (the tracker's region)."""

    def __init__(
        self,
        near: float | None = None,
        far: float | None = None,
        largest_component: bool = False,
        whole_frame: bool = False,
        erode_px: int = 0,
        **range_kwargs,
    ) -> None:
        if erode_px < 0:
            raise ValueError(f"ObjectRegion: erode_px must be >= 0, got {erode_px}")
        self.kwargs = dict(
            near=near, far=far, largest_component=largest_component, whole_frame=whole_frame, erode_px=erode_px,
            **range_kwargs,
        )  # fmt: skip

    def __call__(self, depth: Tensor) -> Tensor:
        return object_mask(depth, **self.kwargs)

    @property
    def all_depth(self) -> bool:
        """Whether the region is every pixel with depth (the scene, not eroded, every component): then a depth image's
        zeros say it already."""
        k = self.kwargs
        return bool(k["whole_frame"] and not k["erode_px"] and not k["largest_component"])


class PCM(NamedTuple):
    """Coloured point-cloud model, padded.

    Attributes:
        points_colors: (B, P, 6) x, y, z in the depth camera (metres) and r, g, b in [0, 1].
        valid: (B, P) bool; invalid rows are zeros.
    """

    points_colors: Tensor
    valid: Tensor


def point_cloud_model(
    rgb: Tensor,
    depth: Tensor,
    K: Tensor,
    mask: Tensor | None = None,
    max_points: int | None = None,
    *,
    K_color: Tensor | None = None,
    T_color_depth: Tensor | None = None,
) -> PCM:
    """Back-projected coloured points of the masked pixels with depth.

    Args:
        rgb: (B, 3, H', W') colour in [0, 1].
        depth: (B, 1, H, W) metres; K: (B, 3, 3) depth intrinsics.
        mask: (B, 1, H, W) bool object pixels (None = every pixel with depth).
        max_points: keep at most this many per sequence, evenly spread over the masked pixels in
            raster order (deterministic); None = all.
        K_color, T_color_depth: (B, 3, 3), (B, 4, 4) for unregistered depth: colours are then read
            (bilinearly) where each point projects in the colour image. None = registered (same grid).

    Returns:
        PCM with P = the largest point count over the batch (or ``max_points``).
    """
    _check_depth(depth, "point_cloud_model")
    B, _, H, W = depth.shape
    keep = depth[:, 0] > 0
    if mask is not None:
        keep = keep & mask[:, 0]
    pts = backproject_depth(K.to(depth), depth).reshape(B, H * W, 3)
    keep = keep.reshape(B, H * W)
    count = keep.sum(1)  # B
    P = int(count.max()) if max_points is None else min(int(max_points), int(count.max()))
    P = max(P, 1)
    order = torch.argsort((~keep).to(torch.uint8), dim=1, stable=True)  # kept pixels first, raster order
    n = count.clamp_max(P)  # points per sequence
    j = torch.arange(P, device=depth.device).expand(B, P)
    pos = (j * count[:, None]) // n.clamp_min(1)[:, None]  # evenly spread ranks
    valid = j < n[:, None]
    idx = order.gather(1, pos.clamp_max(H * W - 1))
    points = pts.gather(1, idx[..., None].expand(-1, -1, 3))
    if T_color_depth is None:
        if rgb.shape[-2:] != (H, W):
            raise ValueError(f"point_cloud_model: registered rgb must be {(H, W)}, got {tuple(rgb.shape[-2:])}")
        colors = rgb.reshape(B, 3, H * W).gather(2, idx[:, None].expand(-1, 3, -1)).transpose(1, 2)
    else:
        colors = _sample_colors(rgb, points, K_color if K_color is not None else K, T_color_depth)
    out = torch.cat([points, colors.to(points)], dim=-1) * valid[..., None]
    return PCM(points_colors=out, valid=valid)


def _sample_colors(rgb: Tensor, points: Tensor, K_color: Tensor, T_color_depth: Tensor) -> Tensor:
    """Bilinear colours (B, P, 3) where depth-camera points (B, P, 3) project in the colour image."""
    Hc, Wc = rgb.shape[-2:]
    p = points @ T_color_depth[:, :3, :3].transpose(1, 2).to(points) + T_color_depth[:, None, :3, 3].to(points)
    uv = project(K_color.to(points), p)
    grid = torch.stack([(uv[..., 0] + 0.5) / Wc * 2 - 1, (uv[..., 1] + 0.5) / Hc * 2 - 1], dim=-1)[:, None]
    return F.grid_sample(rgb.to(points), grid, mode="bilinear", align_corners=False)[:, :, 0].transpose(1, 2)


def feature_spread(points: Tensor, valid: Tensor | None = None) -> Tensor:
    """Paper Table I statistic: the norm of the per-axis standard deviation of a point set, (B,) metres.

    Args:
        points: (B, N, 3); valid: (B, N) bool (None = all). The standard deviation is the sample one
            (N - 1, as MATLAB's ``std``); sets of fewer than 2 points give 0.
    """
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError(f"feature_spread: points must be (B, N, 3), got {tuple(points.shape)}")
    w = torch.ones_like(points[..., 0]) if valid is None else valid.to(points.dtype)
    n = w.sum(1, keepdim=True)  # B,1
    mean = (points * w[..., None]).sum(1) / n.clamp_min(1)
    var = (((points - mean[:, None]) ** 2) * w[..., None]).sum(1) / (n - 1).clamp_min(1)
    return torch.where(n[:, 0] >= 2, var.sum(-1).sqrt(), torch.zeros_like(var[:, 0]))
