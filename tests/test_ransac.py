"""RANSAC with Horn's minimal solver: exact recovery of a known SE(3) under gross outliers (synthetic oracle)."""

from __future__ import annotations

import pytest
import torch

from torchtrack.estimators.ransac import ransac_rigid
from torchtrack.geometry import make_T, so3_exp, transform_points


def problem(B=3, N=60, outliers=0.4, seed=0):
    """Well-posed scenes (depth >= 0.5 m), a rotation from axis-angle, a fraction of pairs replaced by junk."""
    g = torch.Generator().manual_seed(seed)
    src = torch.rand(B, N, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.5, 2.0]) + torch.tensor(
        [-1.0, -0.75, 0.5], dtype=torch.float64
    )
    T = make_T(
        so3_exp(0.3 * torch.randn(B, 3, generator=g, dtype=torch.float64)),
        0.2 * torch.randn(B, 3, generator=g, dtype=torch.float64),
    )
    dst = transform_points(T, src)
    bad = torch.rand(B, N, generator=g) < outliers
    dst = torch.where(bad[..., None], dst + 0.3 + torch.rand(B, N, 3, generator=g, dtype=torch.float64), dst)
    return src, dst, T, ~bad


def test_recovers_the_transform_and_the_inliers_exactly():
    src, dst, T, inlier = problem()
    valid = torch.ones_like(inlier)
    fit = ransac_rigid(src, dst, valid, 0.01)
    assert fit.valid.all()
    torch.testing.assert_close(fit.T, T, atol=1e-9, rtol=0)
    assert torch.equal(fit.inliers, inlier)


@pytest.mark.equivalence
def test_batched_equals_looped_and_invalid_pairs_are_ignored():
    src, dst, T, inlier = problem(B=2, seed=1)
    valid = torch.rand(src.shape[:2], generator=torch.Generator().manual_seed(2)) < 0.8
    batched = ransac_rigid(src, dst, valid, 0.01, seed=3)
    assert not (batched.inliers & ~valid).any()
    assert torch.equal(batched.inliers, inlier & valid)
    for b in range(2):
        one = ransac_rigid(src[b : b + 1], dst[b : b + 1], valid[b : b + 1], 0.01, seed=3)
        torch.testing.assert_close(one.T[0], batched.T[b], atol=1e-9, rtol=0)


def test_per_pair_threshold_and_too_few_pairs():
    src, dst, T, inlier = problem(B=1)
    thr = torch.full(src.shape[:2], 0.01, dtype=torch.float64)
    assert torch.equal(ransac_rigid(src, dst, torch.ones_like(inlier), thr).inliers, inlier)
    two = torch.zeros_like(inlier)
    two[0, :2] = True
    fit = ransac_rigid(src, dst, two, 0.01)
    assert not fit.valid.any() and torch.equal(fit.inliers, two)
    torch.testing.assert_close(fit.T[0], torch.eye(4, dtype=torch.float64))


def test_bad_input_raises():
    src, dst, _, inlier = problem(B=1)
    with pytest.raises(ValueError, match="ransac_rigid"):
        ransac_rigid(src, dst[..., :2], inlier, 0.01)
