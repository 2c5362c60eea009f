"""Object model: depth thresholding (explicit and automatic), largest component, PCM, Table I spread."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchtrack.geometry import backproject_depth, make_T, project, transform_points
from torchtrack.image.object_model import (
    PCM,
    ObjectRegion,
    depth_range,
    feature_spread,
    keep_largest_component,
    object_mask,
    point_cloud_model,
)

H, W = 120, 160


def K_of(f=150.0, cx=79.5, cy=59.5) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])[None]


def layered_depth(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(1,1,H,W) depth: an object (two boxes, 0.60-0.75 m, noisy) before a wall at 1.5-1.7 m, a few holes
    and flying pixels; and the object's true mask."""
    g = torch.Generator().manual_seed(seed)
    z = 1.5 + 0.2 * torch.linspace(0, 1, W).expand(H, W)  # slanted wall
    obj = torch.zeros(H, W, dtype=torch.bool)
    obj[30:90, 20:70] = True
    obj[40:80, 100:140] = True
    z = torch.where(obj, 0.6 + 0.15 * torch.rand(H, W, generator=g), z)
    z[torch.rand(H, W, generator=g) < 0.05] = 0.0  # holes
    flying = torch.zeros(H, W, dtype=torch.bool)
    flying[::17, ::23] = True  # 1 pixel in ~400: stray depths between the layers
    z = torch.where(flying & ~obj & (z > 0), torch.full_like(z, 1.1), z)
    return z[None, None], obj & (z > 0)


# ---------------------------------------------------------------------------------------------- object mask
def test_explicit_near_far_is_thresholding():
    depth, _ = layered_depth()
    m = object_mask(depth, near=0.65, far=1.55)
    assert m.shape == depth.shape and m.dtype == torch.bool
    assert torch.equal(m, (depth >= 0.65) & (depth <= 1.55) & (depth > 0))
    per_seq = object_mask(depth.expand(2, -1, -1, -1), near=torch.tensor([0.5, 1.0]), far=torch.tensor([0.8, 2.0]))
    assert torch.equal(per_seq[0], (depth[0] >= 0.5) & (depth[0] <= 0.8))
    assert torch.equal(per_seq[1], (depth[0] >= 1.0) & (depth[0] <= 2.0))


def test_automatic_range_cuts_the_nearest_layer():
    depth, obj = layered_depth()
    near, far = depth_range(depth)
    assert 0.59 <= float(near) <= 0.6 and 0.75 <= float(far) <= 0.76  # bin edges around [0.6, 0.75]
    assert torch.equal(object_mask(depth)[0, 0], obj)


def test_automatic_range_keeps_a_scene_without_gap_whole():
    z = torch.linspace(0.8, 3.0, W).expand(1, 1, H, W).clone()  # a floor receding continuously
    near, far = depth_range(z)
    assert float(near) <= 0.8 and float(far) >= 3.0
    assert object_mask(z).all()


def test_automatic_range_ignores_a_small_near_speck():
    depth, obj = layered_depth()
    depth[..., 5:8, 5:8] = 0.3  # 9 pixels much nearer than the object: under min_fraction
    assert torch.equal(object_mask(depth)[0, 0], obj)


@pytest.mark.equivalence
def test_batched_range_equals_looped():
    a, _ = layered_depth(0)
    b = torch.linspace(0.8, 3.0, W).expand(1, 1, H, W).clone()
    c = torch.zeros(1, 1, H, W)  # no depth at all: empty object
    near, far = depth_range(torch.cat([a, b, c]))
    for i, d in enumerate((a, b, c)):
        n1, f1 = depth_range(d)
        assert torch.allclose(near[i], n1[0]) and torch.allclose(far[i], f1[0])
    assert not object_mask(c).any()


def test_whole_frame():
    depth, _ = layered_depth()
    assert torch.equal(object_mask(depth, whole_frame=True, near=0.1, far=0.2), depth > 0)


def test_largest_component_against_opencv():
    depth, obj = layered_depth()
    m = object_mask(depth, largest_component=True)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(obj.numpy().astype(np.uint8), connectivity=8)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    assert np.array_equal(m[0, 0].numpy(), labels == biggest)


@pytest.mark.equivalence
def test_largest_component_batched_equals_looped():
    g = torch.Generator().manual_seed(3)
    masks = torch.rand(3, 1, 40, 50, generator=g) > 0.55
    batched = keep_largest_component(masks)
    for b in range(3):
        assert torch.equal(batched[b], keep_largest_component(masks[b : b + 1])[0])
        n, labels, stats, _ = cv2.connectedComponentsWithStats(masks[b, 0].numpy().astype(np.uint8), connectivity=8)
        assert batched[b].sum() == stats[1:, cv2.CC_STAT_AREA].max()


def test_bad_input_raises():
    with pytest.raises(ValueError, match="depth must be"):
        object_mask(torch.rand(H, W))
    with pytest.raises(ValueError, match="depth must be"):
        depth_range(torch.rand(1, 2, H, W))
    with pytest.raises(ValueError, match="points must be"):
        feature_spread(torch.rand(2, 5, 2))


def test_module_equals_function():
    depth, _ = layered_depth()
    assert torch.equal(ObjectRegion(largest_component=True)(depth), object_mask(depth, largest_component=True))


# ---------------------------------------------------------------------------------------------- PCM
def test_pcm_is_the_backprojected_coloured_mask():
    depth, obj = layered_depth()
    K = K_of()
    rgb = torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(1))
    pcm = point_cloud_model(rgb, depth, K, obj[None, None])
    assert isinstance(pcm, PCM)
    P = int(obj.sum())
    assert pcm.points_colors.shape == (1, P, 6) and pcm.valid.all()
    pts = backproject_depth(K, depth)[0][obj]  # raster order
    assert torch.allclose(pcm.points_colors[0, :, :3], pts)
    assert torch.equal(pcm.points_colors[0, :, 3:], rgb[0].permute(1, 2, 0)[obj])


def test_pcm_padding_and_subsampling():
    depth, obj = layered_depth()
    other = torch.zeros_like(obj)
    other[50:60, 60:70] = True
    masks = torch.stack([obj, other])[:, None]
    rgb = torch.rand(2, 3, H, W)
    K = K_of().expand(2, 3, 3)
    pcm = point_cloud_model(rgb, depth.expand(2, -1, -1, -1), K, masks)
    n0, n1 = int(obj.sum()), int((other & (depth[0, 0] > 0)).sum())
    assert pcm.valid.shape == (2, n0) and pcm.valid.sum(1).tolist() == [n0, n1]
    assert torch.all(pcm.points_colors[1, n1:] == 0)
    sub = point_cloud_model(rgb, depth.expand(2, -1, -1, -1), K, masks, max_points=50)
    assert sub.valid.sum(1).tolist() == [50, min(50, n1)]
    full0 = pcm.points_colors[0]
    idx = torch.div(torch.arange(50) * n0, 50, rounding_mode="floor")  # evenly spread ranks
    assert torch.equal(sub.points_colors[0], full0[idx])


def test_pcm_unregistered_colours_are_read_where_points_project():
    depth, obj = layered_depth()
    K = K_of()
    T_color_depth = make_T(torch.eye(3)[None], torch.tensor([[0.02, 0.0, 0.0]]))
    rgb = torch.linspace(0, 1, W).expand(1, 3, H, W).clone()  # colour = a function of the column
    pcm = point_cloud_model(rgb, depth, K, obj[None, None], K_color=K, T_color_depth=T_color_depth)
    uv = project(K, transform_points(T_color_depth, pcm.points_colors[..., :3]))
    inside = (uv[..., 0] > 0) & (uv[..., 0] < W - 1)
    expected = uv[..., 0] / (W - 1)  # bilinear reading of a linear ramp is exact
    assert torch.allclose(pcm.points_colors[..., 3][inside], expected[inside], atol=1e-5)


# ---------------------------------------------------------------------------------------------- Table I
def test_feature_spread_is_norm_of_per_axis_std():
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(2, 30, 3, generator=g, dtype=torch.float64) * torch.tensor([0.05, 0.02, 0.1], dtype=torch.float64)
    valid = torch.ones(2, 30, dtype=torch.bool)
    valid[1, 20:] = False
    s = feature_spread(pts, valid)
    for b, n in ((0, 30), (1, 20)):
        ref = np.linalg.norm(np.std(pts[b, :n].numpy(), axis=0, ddof=1))
        assert abs(float(s[b]) - ref) < 1e-12
    assert torch.allclose(feature_spread(pts[:1]), s[:1])
    assert feature_spread(pts, torch.zeros(2, 30, dtype=torch.bool)).tolist() == [0.0, 0.0]


# ---------------------------------------------------------------------------------------------- erosion
@pytest.mark.parametrize("radius", [1, 3, 6])
def test_erode_px_against_opencv(radius):
    """region.erode_px: the mask eroded by a (2r+1)^2 square, as cv2.erode (whose default border never erodes)."""
    depth, _ = layered_depth(2)
    base = object_mask(depth, largest_component=True)
    m = object_mask(depth, largest_component=True, erode_px=radius)
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    ref = cv2.erode(base[0, 0].numpy().astype(np.uint8), kernel) > 0
    assert np.array_equal(m[0, 0].numpy(), ref) and 0 < int(m.sum()) < int(base.sum())
    assert torch.equal(ObjectRegion(largest_component=True, erode_px=radius)(depth), m)
    with pytest.raises(ValueError, match="erode_px must be >= 0"):
        ObjectRegion(erode_px=-1)


def test_all_depth_says_when_the_region_is_the_depths_own_mask():
    """The tracker skips the dense map's region where ``all_depth``: there the region is exactly the pixels with depth
    (so masking the depth with it changes nothing); an object, an eroded or a largest-component scene is not."""
    depth, _ = layered_depth()  # two boxes before a wall, holes, stray pixels between the layers
    depth[..., :6, :6] = 0.0
    depth[..., 1:4, 1:4] = 1.0  # and an island of depth (a component of its own)
    scene = ObjectRegion(whole_frame=True)
    assert scene.all_depth and torch.equal(scene(depth), depth > 0)
    assert torch.equal(torch.where(scene(depth), depth, torch.zeros_like(depth)), depth)
    for kw in (dict(whole_frame=True, erode_px=2), dict(whole_frame=True, largest_component=True), dict()):
        region = ObjectRegion(**kw)
        assert not region.all_depth and not torch.equal(region(depth), depth > 0), kw
