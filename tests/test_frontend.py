"""Per-frame preparation helpers (torchtrack.frontend): the occlusion-boundary mask of the selection."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from torchtrack.frontend import _window_max, smooth_depth_mask


@pytest.mark.parametrize("shape", [(2, 1, 7, 9), (1, 1, 1, 5), (1, 1, 3, 3), (3, 1, 40, 33)])
@pytest.mark.parametrize("radius", [1, 2, 3])
def test_window_max_equals_max_pool(shape, radius):
    x = torch.randn(shape, generator=torch.Generator().manual_seed(0))
    assert torch.equal(_window_max(x, radius), F.max_pool2d(x, 2 * radius + 1, 1, radius))


def test_smooth_depth_mask_against_max_pool_oracle():
    """The definition: no hole in the 5x5 window and max - min of its depth within 3% of the pixel's depth."""
    g = torch.Generator().manual_seed(1)
    depth = 1.0 + 0.01 * torch.rand(2, 1, 48, 64, generator=g)
    depth[:, :, 20:30, 30:] += 0.5  # an occlusion boundary
    depth[torch.rand(depth.shape, generator=g) < 0.02] = 0.0  # holes
    hi = F.max_pool2d(depth, 5, 1, 2)
    lo = -F.max_pool2d(torch.where(depth > 0, -depth, -1e9), 5, 1, 2)
    holes = F.max_pool2d((depth <= 0).float(), 5, 1, 2) > 0
    expected = ~holes & (hi - lo <= 0.03 * depth)
    mask = smooth_depth_mask(depth, 0.03)
    assert mask.shape == depth.shape and mask.dtype == torch.bool
    assert torch.equal(mask, expected)
    assert not mask[:, :, 18:32, 28:32].any() and mask[:, :, 24, 40:].float().mean() > 0.5
