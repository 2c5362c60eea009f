"""Model points as estimates (``reselect.point_mean``, issue 24): the information-weighted mean of each feature's depth
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

F = 525.0  # px, the focal length of the scene


def _stage(**kw) -> Reselection:
    return Reselection(region=lambda d: d > 0, select=None, point_mean="frame", **kw)


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


def _run(stage: Reselection, pts, T, g, sample_noise, var_xyz, var_pix):
    """Birth sample at camera 0, then one fused sample per further camera; ``sample_noise(points_cam, g)`` (B, N, 3)."""
    B, N, _ = pts.shape
    focal = torch.full((B,), F, dtype=torch.float64)
    valid = torch.ones(B, N, dtype=torch.bool)
    X0 = transform_points(T[0], pts) + sample_noise(transform_points(T[0], pts), g)
    est = PointEstimate(transform_points(torch.linalg.inv(T[0]), X0), torch.zeros(B, N, 3, 3, dtype=torch.float64))
    for T_k in T[1:]:
        X = transform_points(T_k, pts)
        est = stage.fused(est, T_k, X + sample_noise(X, g), var_xyz, var_pix, focal, valid)
    return est


def test_the_mean_of_k_samples_has_variance_sigma2_over_k():
    """Isotropic depth noise of sigma per coordinate, exact poses, k samples of equal weight: each coordinate's error
    variance is sigma^2 / k (Monte Carlo over 3 x 2000 points x 3 coordinates: relative std sqrt(2 / 18000) = 0.011,
    allowed 4x) and the information is exactly k / sigma^2 I."""
    B, N, k, sigma = 3, 2000, 6, 0.005
    pts, T, g = _scene(B, N, k)
    noise = lambda X, g: sigma * torch.randn(X.shape, generator=g, dtype=X.dtype)  # noqa: E731
    var = torch.full((B, N), sigma**2, dtype=torch.float64)
    est = _run(_stage(), pts, T, g, noise, var, var)
    err = est.mean - pts
    ratio = float(err.pow(2).mean() / (sigma**2 / k))
    assert abs(ratio - 1.0) < 4 * math.sqrt(2 / err.numel()), f"error variance / (sigma^2 / k) = {ratio:.3f}"
    eye = torch.eye(3, dtype=torch.float64).expand(B, N, 3, 3)
    torch.testing.assert_close(est.info * sigma**2 / k, eye, atol=F64_UNIT, rtol=0)


def test_the_ray_model_information_is_the_inverse_error_covariance():
    """Noise along each camera ray (sigma_z) and across it (z / f sigma_px), exact poses from several viewpoints: the
    fused point's error is normal with the inverse of the fused information as covariance, NEES e^T Lambda e has mean 3
    (dof 3, std sqrt(6 / n) of the mean over n points, allowed 4x)."""
    B, N, k, s_z, s_px = 2, 3000, 5, 0.006, 0.5

    def noise(X, g):
        ray = torch.nn.functional.normalize(X, dim=-1)
        lateral = torch.randn(X.shape, generator=g, dtype=X.dtype) * (X[..., 2:] / F * s_px)
        lateral = lateral - (lateral * ray).sum(-1, keepdim=True) * ray
        return lateral + ray * s_z * torch.randn(X.shape[:-1], generator=g, dtype=X.dtype)[..., None]

    pts, T, g = _scene(B, N, k, seed=1)
    T[1] = T[0]  # the birth sample weighs as the first tracked one: the same viewpoint (consecutive frames)
    var_xyz = torch.full((B, N), s_z**2, dtype=torch.float64)
    var_pix = torch.full((B, N), s_px**2, dtype=torch.float64)
    est = _run(_stage(point_noise="ray"), pts, T, g, noise, var_xyz, var_pix)
    err = est.mean - pts
    nees = (err[..., None, :] @ est.info @ err[..., :, None]).mean()
    assert abs(float(nees) - 3.0) < 4 * math.sqrt(6 / (B * N)), f"NEES {float(nees):.3f}"


def test_exact_samples_give_the_exact_points():
    """Exact depth: the estimate is the true model point, to float64 precision, whatever the weights."""
    B, N, k = 2, 50, 4
    pts, T, g = _scene(B, N, k, seed=2)
    var = 1e-6 * (1 + torch.rand(B, N, generator=g, dtype=torch.float64))
    for noise_model in ("isotropic", "ray"):
        est = _run(_stage(point_noise=noise_model), pts, T, g, lambda X, g: torch.zeros_like(X), var, var)
        torch.testing.assert_close(est.mean, pts, atol=F64_UNIT, rtol=0)


def test_the_birth_weight_and_the_mask():
    """Two samples: the mean is (w x0 + x1) / (w + 1) with the birth weight w (closed form); a feature not valid keeps
    its estimate bit for bit."""
    x0, x1 = torch.tensor([[[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]]], dtype=torch.float64), torch.rand(1, 2, 3).double()
    info = torch.eye(3, dtype=torch.float64).expand(1, 2, 3, 3) * 4.0
    est0 = PointEstimate(x0, torch.zeros(1, 2, 3, 3, dtype=torch.float64))
    valid = torch.tensor([[True, False]])
    for w in (0.25, 1.0, 3.0):
        est = fuse_points(est0, x1, info, valid, w)
        torch.testing.assert_close(est.mean[0, 0], (w * x0[0, 0] + x1[0, 0]) / (w + 1), atol=F64_UNIT, rtol=0)
        torch.testing.assert_close(est.info[0, 0], (1 + w) * info[0, 0], atol=F64_UNIT, rtol=0)
        assert torch.equal(est.mean[0, 1], x0[0, 1]) and torch.equal(est.info[0, 1], est0.info[0, 1])


@pytest.mark.equivalence
def test_batched_equals_looped():
    """Three scenes of different sizes padded into one batch (invalid rows never fused), with different focal lengths
    and points past their birth, vs each alone."""
    B, N, k = 3, 40, 4
    pts, T, g = _scene(B, N, k, seed=3)
    valid = torch.arange(N)[None] < torch.tensor([40, 25, 10])[:, None]
    noise = [0.003 * torch.randn(B, N, 3, generator=g, dtype=torch.float64) for _ in range(k)]
    var_xyz = 1e-5 * (1 + torch.rand(B, N, generator=g, dtype=torch.float64))
    focal = torch.tensor([F, 580.0, 610.0], dtype=torch.float64)

    weighed = torch.arange(N)[None] < torch.tensor([10, 20, 30])[:, None]  # points past their birth, per row
    prior = torch.where(weighed[..., None, None], 1e5 * torch.eye(3, dtype=torch.float64), 0.0)

    def run(rows):
        stage = _stage(point_noise="ray")
        m = valid[rows]
        est = PointEstimate(transform_points(torch.linalg.inv(T[0, rows]), transform_points(T[0, rows], pts[rows])
                                             + noise[0][rows]), prior[rows])  # fmt: skip
        for i in range(1, k):
            X = transform_points(T[i, rows], pts[rows]) + noise[i][rows]
            est = stage.fused(est, T[i, rows], X, var_xyz[rows], var_xyz[rows] * 1e5, focal[rows], m)
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
    tracker = make_tracker("reselect.point_mean=reselect", "reselect.point_noise=ray", "reselect.fraction=0.0",
                           "landmarks.enabled=false")  # fmt: skip
    frames = list(iterate_batched([seq], prefetch=False))
    for frame in frames:
        tracker.step(frame)
    s = tracker.state
    keep = s.valid[0].clone()
    assert not torch.equal(s.points_mean[0][keep].float(), s.points_obj[0][keep])  # estimated, not the birth sample
    R = s.T_world_obj[0, :3, :3]
    world = transform_points(s.T_world_obj, s.points_mean)[0][keep]
    info_world = (R @ s.points_info[0] @ R.T)[keep]
    tracker.state, _ = tracker._new_model(s, frames[-1], s.prev, torch.ones(1, dtype=torch.bool))
    s, k = tracker.state, len(world)
    R = s.T_world_obj[0, :3, :3]
    torch.testing.assert_close(transform_points(s.T_world_obj, s.points_obj.double())[0][:k], world, atol=1e-6, rtol=0)
    torch.testing.assert_close(transform_points(s.T_world_obj, s.points_mean)[0][:k], world, atol=1e-6, rtol=0)
    scale = 1 / float(info_world.abs().max())
    torch.testing.assert_close((R @ s.points_info[0] @ R.T)[:k] * scale, info_world * scale, atol=1e-9, rtol=0)
    torch.testing.assert_close(s.points_mean[0].float(), s.points_obj[0], atol=0, rtol=0)
    assert bool((s.points_info[0][k:] == 0).all()) and int(s.valid[0].sum()) > k


@pytest.mark.equivalence
def test_tracker_batched_equals_looped(synth):  # noqa: F811
    """``frame``: two sequences of different lengths tracked together equal each alone (the estimates are per row)."""
    a, b = synth(seed=1, frames=8, noise="kinect"), synth(seed=2, frames=6, noise="kinect")
    over = ("reselect.point_mean=frame", "reselect.point_noise=ray")
    batched, _ = track(make_tracker(*over), [a, b])
    alone_a, _ = track(make_tracker(*over), [a])
    alone_b, _ = track(make_tracker(*over), [b])
    torch.testing.assert_close(batched[0], alone_a[0], atol=TRAJ, rtol=0)
    torch.testing.assert_close(batched[1, :6], alone_b[0], atol=TRAJ, rtol=0)


def test_the_gate_rejects_planted_outliers():
    """Samples with noise of sigma, and in one frame 20 % of them moved 0.1-0.3 m (a depth edge): with the gate at the
    0.999 chi-square quantile (3 dof) no moved sample is fused: the estimate is that of the clean samples alone (the
    same computation: equal), within 6 sigma of the truth; without the gate the moved samples pull it centimetres off."""
    B, N, k, sigma = 1, 500, 6, 0.002
    pts, T, g = _scene(B, N, k, seed=4)
    noise = [sigma * torch.randn(B, N, 3, generator=g, dtype=torch.float64) for _ in range(k)]
    moved = torch.rand(B, N, generator=g) < 0.2
    jump = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g, dtype=torch.float64), dim=-1)
    jump = jump * (0.1 + 0.2 * torch.rand(B, N, 1, generator=g, dtype=torch.float64))
    var = torch.full((B, N), sigma**2, dtype=torch.float64)
    focal = torch.full((B,), F, dtype=torch.float64)

    def run(gate, outliers):
        stage = _stage(point_gate=gate)
        X0 = transform_points(T[0], pts) + noise[0]
        est = PointEstimate(transform_points(torch.linalg.inv(T[0]), X0), torch.zeros(B, N, 3, 3, dtype=torch.float64))
        for i in range(1, k):
            X = transform_points(T[i], pts) + noise[i] + (torch.where(moved[..., None], jump, 0.0) if i == 3 else 0)
            valid = ~moved if i == 3 and not outliers else torch.ones(B, N, dtype=torch.bool)
            est = stage.fused(est, T[i], X, var, var, focal, valid)
        return est

    clean = run(16.27, outliers=False)  # the moved samples left out by hand (the gate judges the rest alike)
    gated = run(16.27, outliers=True)
    torch.testing.assert_close(gated.mean, clean.mean, atol=0, rtol=0)
    assert float((gated.mean - pts).norm(dim=-1).max()) < 6 * sigma
    plain = run(None, outliers=True)
    assert float((plain.mean - pts)[moved].norm(dim=-1).median()) > 0.01


@pytest.mark.parametrize("kw", [dict(point_mean="always"), dict(point_noise="anisotropic"), dict(point_gate=0.0),
                                dict(point_birth_weight=-1.0)])  # fmt: skip
def test_bad_settings_raise(kw):
    with pytest.raises(ValueError, match="reselect.point_"):
        Reselection(region=None, select=None, **{"point_mean": "frame", **kw})
