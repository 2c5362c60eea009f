"""Model points as estimates (``reselect.point_mean``): the information-weighted mean of each feature's depth
samples against closed forms and Monte Carlo on a static scene with exact poses; the tracker's bookkeeping of the
estimates through a re-selection."""

from __future__ import annotations

import math

import pytest
import torch
from test_tracker import make_tracker, synth, track  # noqa: F401  (synth: the module's fixture)
from tolerances import F64_UNIT, TRAJ

from torchtrack.data import iterate_batched
from torchtrack.geometry import make_T, so3_exp, transform_points
from torchtrack.pipeline.reselect import PointEstimate, Reselection, fuse_points
from torchtrack.pipeline.state import Measure

F = 525.0  # px, the focal length of the scene


def _stage(**kw) -> Reselection:
    return Reselection(region=lambda d: d > 0, select=None, point_mean=True, **kw)


def _scene(B: int, N: int, k: int, seed: int = 0):
    """Static scene: model points (B, N, 3) 1-3 m in front of k exact cameras T_cam_obj (k, B, 4, 4), rotated up to
    ~20 deg and moved up to 0.2 m about the first."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(B, N, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.5, 2.0]) - torch.tensor(
        [1.0, 0.75, 0.0]
    )
    pts[..., 2] += 1.0
    R = so3_exp(0.35 * (torch.rand(k, B, 3, generator=g, dtype=torch.float64) - 0.5))
    t = 0.4 * (torch.rand(k, B, 3, generator=g, dtype=torch.float64) - 0.5)
    return pts, make_T(R, t), g


def _run(stage: Reselection, pts, T, g, sample_noise, var_xyz):
    """Birth sample at camera 0, then one fused sample per further camera; ``sample_noise(points_cam, g)`` (B, N, 3)."""
    B, N, _ = pts.shape
    valid = torch.ones(B, N, dtype=torch.bool)
    X0 = transform_points(T[0], pts) + sample_noise(transform_points(T[0], pts), g)
    est = PointEstimate(transform_points(torch.linalg.inv(T[0]), X0), torch.zeros(B, N, 3, 3, dtype=torch.float64))
    for T_k in T[1:]:
        X = transform_points(T_k, pts)
        est = stage.fused(est, T_k, X + sample_noise(X, g), var_xyz, valid)
    return est


def test_the_mean_of_k_samples_has_variance_sigma2_over_k():
    """Isotropic depth noise of sigma per coordinate, exact poses, k samples of equal weight: each coordinate's error
    variance is sigma^2 / k (Monte Carlo over 3 x 2000 points x 3 coordinates: relative std sqrt(2 / 18000) = 0.011,
    allowed 4x) and the information is exactly k / sigma^2 I."""
    B, N, k, sigma = 3, 2000, 6, 0.005
    pts, T, g = _scene(B, N, k)
    noise = lambda X, g: sigma * torch.randn(X.shape, generator=g, dtype=X.dtype)  # noqa: E731
    var = torch.full((B, N), sigma**2, dtype=torch.float64)
    est = _run(_stage(), pts, T, g, noise, var)
    err = est.mean - pts
    ratio = float(err.pow(2).mean() / (sigma**2 / k))
    assert abs(ratio - 1.0) < 4 * math.sqrt(2 / err.numel()), f"error variance / (sigma^2 / k) = {ratio:.3f}"
    eye = torch.eye(3, dtype=torch.float64).expand(B, N, 3, 3)
    torch.testing.assert_close(est.info * sigma**2 / k, eye, atol=F64_UNIT, rtol=0)


def test_exact_samples_give_the_exact_points():
    """Exact depth: the estimate is the true model point, to float64 precision, whatever the weights."""
    B, N, k = 2, 50, 4
    pts, T, g = _scene(B, N, k, seed=2)
    var = 1e-6 * (1 + torch.rand(B, N, generator=g, dtype=torch.float64))
    est = _run(_stage(), pts, T, g, lambda X, g: torch.zeros_like(X), var)
    torch.testing.assert_close(est.mean, pts, atol=F64_UNIT, rtol=0)


def test_the_birth_sample_weighs_as_the_first_and_the_mask():
    """Two samples of a point at its birth (zero information): the mean is (x0 + x1) / 2 and the information twice the
    sample's (closed form); a second fused sample of variance v after a prior of information I / v gives a third of
    the way; a feature not valid keeps its estimate bit for bit."""
    x0, x1 = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]]], dtype=torch.float64), torch.rand(1, 2, 3).double()
    var = torch.full((1, 2), 0.25, dtype=torch.float64)
    est0 = PointEstimate(x0, torch.zeros(1, 2, 3, 3, dtype=torch.float64))
    valid = torch.tensor([[True, False]])
    est = fuse_points(est0, x1, var, valid)
    torch.testing.assert_close(est.mean[0, 0], (x0[0, 0] + x1[0, 0]) / 2, atol=F64_UNIT, rtol=0)
    torch.testing.assert_close(est.info[0, 0], 8.0 * torch.eye(3, dtype=torch.float64), atol=F64_UNIT, rtol=0)
    assert torch.equal(est.mean[0, 1], x0[0, 1]) and torch.equal(est.info[0, 1], est0.info[0, 1])
    x2 = torch.rand(1, 2, 3).double()
    est2 = fuse_points(est, x2, var, valid)
    torch.testing.assert_close(est2.mean[0, 0], (2 * est.mean[0, 0] + x2[0, 0]) / 3, atol=F64_UNIT, rtol=0)


@pytest.mark.equivalence
def test_batched_equals_looped():
    """Three scenes of different sizes padded into one batch (invalid rows never fused), with points past their
    birth, vs each alone."""
    B, N, k = 3, 40, 4
    pts, T, g = _scene(B, N, k, seed=3)
    valid = torch.arange(N)[None] < torch.tensor([40, 25, 10])[:, None]
    noise = [0.003 * torch.randn(B, N, 3, generator=g, dtype=torch.float64) for _ in range(k)]
    var_xyz = 1e-5 * (1 + torch.rand(B, N, generator=g, dtype=torch.float64))

    weighed = torch.arange(N)[None] < torch.tensor([10, 20, 30])[:, None]  # points past their birth, per row
    prior = torch.where(weighed[..., None, None], 1e5 * torch.eye(3, dtype=torch.float64), 0.0)

    def run(rows):
        stage = _stage()
        m = valid[rows]
        est = PointEstimate(transform_points(torch.linalg.inv(T[0, rows]), transform_points(T[0, rows], pts[rows])
                                             + noise[0][rows]), prior[rows])  # fmt: skip
        for i in range(1, k):
            X = transform_points(T[i, rows], pts[rows]) + noise[i][rows]
            est = stage.fused(est, T[i, rows], X, var_xyz[rows], m)
        return est

    batched = run(list(range(B)))
    for b in range(B):
        alone = run([b])
        n = int(valid[b].sum())
        torch.testing.assert_close(batched.mean[b, :n], alone.mean[0, :n], atol=F64_UNIT, rtol=0)
        torch.testing.assert_close(batched.info[b, :n] * 1e-5, alone.info[0, :n] * 1e-5, atol=F64_UNIT, rtol=0)


def test_survivors_carry_their_estimates_into_the_new_model(synth):  # noqa: F811
    """``reselect``: between re-selections the filter's model points stay fixed while the estimates move; a
    re-selection puts each survivor's estimate into the new model at the same world position with the same world
    information (rigid re-expression), and the new features start at their birth sample with zero information."""
    seq = synth(seed=5, frames=5, noise="kinect")
    tracker = make_tracker("reselect.point_mean=true", "reselect.fraction=0.0", "landmarks=none")
    frames = list(iterate_batched([seq], prefetch=False))
    for frame in frames:
        tracker.step(frame)
    s = tracker.state
    keep = s.valid[0].clone()
    assert not torch.equal(s.points_mean[0][keep].float(), s.points_obj[0][keep])  # estimated, not the birth sample
    R = s.T_world_obj[0, :3, :3]
    world = transform_points(s.T_world_obj, s.points_mean)[0][keep]
    info_world = (R @ s.points_info[0] @ R.T)[keep]
    measure = Measure(s.prev.depth, frames[-1].K, frames[-1].T_color_depth)
    tracker.state, _ = tracker._new_model(s, frames[-1], s.prev, measure, torch.ones(1, dtype=torch.bool))
    s, k = tracker.state, len(world)
    R = s.T_world_obj[0, :3, :3]
    torch.testing.assert_close(transform_points(s.T_world_obj, s.points_obj.double())[0][:k], world, atol=1e-6, rtol=0)
    torch.testing.assert_close(transform_points(s.T_world_obj, s.points_mean)[0][:k], world, atol=1e-6, rtol=0)
    scale = 1 / float(info_world.abs().max())
    torch.testing.assert_close((R @ s.points_info[0] @ R.T)[:k] * scale, info_world * scale, atol=1e-9, rtol=0)
    torch.testing.assert_close(s.points_mean[0].float(), s.points_obj[0], atol=0, rtol=0)
    assert bool((s.points_info[0][k:] == 0).all()) and int(s.valid[0].sum()) > k


@pytest.mark.slow
@pytest.mark.equivalence
def test_tracker_batched_equals_looped(synth):  # noqa: F811
    """Two sequences of different lengths tracked together equal each alone (the estimates are per row)."""
    a, b = synth(seed=1, frames=8, noise="kinect"), synth(seed=2, frames=6, noise="kinect")
    over = ("reselect.point_mean=true", "reselect.fraction=0.6")
    batched, _ = track(make_tracker(*over), [a, b])
    alone_a, _ = track(make_tracker(*over), [a])
    alone_b, _ = track(make_tracker(*over), [b])
    torch.testing.assert_close(batched[0], alone_a[0], atol=TRAJ, rtol=0)
    torch.testing.assert_close(batched[1, :6], alone_b[0], atol=TRAJ, rtol=0)


@pytest.mark.parametrize("value", ["reselect", "off", 1])
def test_bad_settings_raise(value):
    with pytest.raises(ValueError, match="reselect.point_mean"):
        Reselection(region=None, select=None, point_mean=value)
