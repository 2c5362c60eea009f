"""Windowed refinement (torchtrack/estimators/window.py): oracles on synthetic windows with exact ground truth."""

from __future__ import annotations

import math

import pytest
import torch
from tolerances import F64_UNIT

from torchtrack.estimators.window import WindowRefiner, refine_window, window_measure
from torchtrack.filter.ekf import chi2_quantile
from torchtrack.geometry import T_inv, make_T, se3_exp, se3_log, so3_exp

F64 = torch.float64
SIG_PIX, SIG_XYZ = 1.0, 0.01  # px, m: the filter's nominal variances' scale


def _window(B: int, K: int, P: int, seed: int):
    """B windows of K depth-camera poses (world -> camera, about 5 cm and 3 degrees apart) and P landmarks at 1.5-3 m;
    exact measurements (3D in the depth camera, colour pixels) and a colour camera 2.5 cm beside the depth camera."""
    g = torch.Generator().manual_seed(seed)
    xi = torch.cat([0.05 * torch.randn(B, K, 3, generator=g, dtype=F64),
                    math.radians(3) * torch.randn(B, K, 3, generator=g, dtype=F64)], -1)  # fmt: skip
    T = se3_exp(xi)
    X = torch.cat([torch.rand(B, P, 2, generator=g, dtype=F64) * 1.6 - 0.8,
                   1.5 + 1.5 * torch.rand(B, P, 1, generator=g, dtype=F64)], -1)  # fmt: skip
    Kc = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], dtype=F64).expand(B, 3, 3)
    T_cd = make_T(so3_exp(torch.tensor([0.0, 0.01, 0.0], dtype=F64)), torch.tensor([0.025, 0.0, 0.0], dtype=F64))
    T_cd = T_cd.expand(B, 4, 4)
    h = window_measure(T, X, Kc, T_cd).h
    return T, X, h[..., :3], h[..., 3:], Kc, T_cd


def _perturbed(T, X, seed, rot=0.01, trans=0.01, pt=0.01):
    g = torch.Generator().manual_seed(seed)
    B, K = T.shape[:2]
    d = torch.cat(
        [trans * torch.randn(B, K, 3, generator=g, dtype=F64), rot * torch.randn(B, K, 3, generator=g, dtype=F64)], -1
    )
    d[:, 0] = 0  # the gauge pose starts (and stays) at the truth
    return se3_exp(d) @ T, X + pt * torch.randn(X.shape, generator=g, dtype=F64)


def _ones(shape, value):
    return torch.full(shape, value, dtype=F64)


def _refine(T0, X0, xyz, pix, Kc, T_cd, **kw):
    B, K, P = xyz.shape[:3]
    valid = torch.ones(B, K, P, dtype=torch.bool)
    return refine_window(T0, X0, xyz, pix, _ones((B, K, P), SIG_XYZ**2), _ones((B, K, P), SIG_PIX**2), valid, valid,
                         Kc, T_cd, **kw)  # fmt: skip


def _pose_error(T_est, T_true):
    return se3_log(T_est @ T_inv(T_true))  # left perturbation, as the covariance


def test_closed_form_jacobians_equal_autograd():
    T, X, _, _, Kc, T_cd = _window(2, 3, 5, seed=0)

    def h(xi, dX, b):
        return window_measure((se3_exp(xi) @ T[b])[None], (X[b] + dX)[None], Kc[b : b + 1], T_cd[b : b + 1]).h[0]

    lin = window_measure(T, X, Kc, T_cd)
    for b in range(2):
        J_xi, J_X = torch.func.jacfwd(h, argnums=(0, 1))(torch.zeros(3, 6, dtype=F64), torch.zeros(5, 3, dtype=F64), b)
        for k in range(3):  # J_xi: (K, P, 5, K, 6): measurement of keyframe k depends on pose k only
            torch.testing.assert_close(J_xi[k, :, :, k], lin.J_pose[b, k], rtol=1e-9, atol=1e-9)
            for p in range(5):
                torch.testing.assert_close(J_X[k, p, :, p], lin.J_point[b, k, p], rtol=1e-9, atol=1e-9)


def test_exact_observations_give_the_exact_window():
    T, X, xyz, pix, Kc, T_cd = _window(3, 4, 25, seed=1)
    T0, X0 = _perturbed(T, X, seed=2)
    out = _refine(T0, X0, xyz, pix, Kc, T_cd)
    assert (T0 - T).abs().max() > 1e-3  # it had something to do
    assert _pose_error(out.T_cam_world, T).abs().max() < 1e-9
    assert (out.points_world - X).abs().max() < 1e-9
    assert bool(out.inlier_xyz.all() and out.inlier_pix.all())
    assert (out.cov_poses[:, 0].abs().max() == 0) and (out.cov_poses[:, :, 0].abs().max() == 0)  # the gauge


def test_covariance_matches_the_monte_carlo_spread():
    """B = 400 noisy copies of one window (Gaussian noise with the given sigmas), started at the truth: the normalised
    estimation error squared of the free poses (12 dof) averages 12 within 4 of its standard errors
    sqrt(2 * 12 / 400) = 0.245 (plus the small bias of a nonlinear estimator), and each landmark's (3 dof) averages 3
    within 0.25 (the 20 landmarks share pose errors, so their mean is less certain than independent ones')."""
    B, K, P = 400, 3, 20
    T, X, xyz, pix, Kc, T_cd = _window(1, K, P, seed=3)
    T, X, xyz, pix = T.expand(B, -1, -1, -1), X.expand(B, -1, -1), xyz.expand(B, -1, -1, -1), pix.expand(B, -1, -1, -1)
    g = torch.Generator().manual_seed(4)
    noisy_xyz = xyz + SIG_XYZ * torch.randn(xyz.shape, generator=g, dtype=F64)
    noisy_pix = pix + SIG_PIX * torch.randn(pix.shape, generator=g, dtype=F64)
    out = _refine(T.clone(), X.clone(), noisy_xyz, noisy_pix, Kc.expand(B, 3, 3), T_cd.expand(B, 4, 4))
    e = _pose_error(out.T_cam_world, T)[:, 1:].reshape(B, 12)
    cov = out.cov_poses[:, 1:, 1:].permute(0, 1, 3, 2, 4).reshape(B, 12, 12)
    nees = (e[:, None, :] @ torch.linalg.solve(cov, e[..., None]))[:, 0, 0]
    assert abs(nees.mean().item() - 12) < 4 * math.sqrt(2 * 12 / B), nees.mean()
    dX = out.points_world - X
    nees_p = (dX[..., None, :] @ torch.linalg.solve(out.cov_points, dX[..., None]))[..., 0, 0]
    assert abs(nees_p.mean().item() - 3) < 0.25, nees_p.mean()
    # the spread itself, per pose coordinate: sample variances within 4 standard errors (sqrt(2 / B) relative)
    ratio = e.var(0) / torch.diagonal(cov, dim1=-2, dim2=-1).mean(0)
    assert (ratio - 1).abs().max() < 4 * math.sqrt(2 / B), ratio


def test_planted_outliers_are_rejected():
    """20% of the 3D blocks and 20% of the pixel blocks are moved by 0.1-0.3 m / 15-40 px, the rest exact: the inlier
    masks are exactly the planted ones and the window is exact."""
    B, K, P = 2, 4, 30
    T, X, xyz, pix, Kc, T_cd = _window(B, K, P, seed=5)
    g = torch.Generator().manual_seed(6)
    bad_xyz = torch.rand(B, K, P, generator=g) < 0.2
    bad_pix = torch.rand(B, K, P, generator=g) < 0.2
    direction = torch.nn.functional.normalize(torch.randn(B, K, P, 3, generator=g, dtype=F64), dim=-1)
    xyz = xyz + bad_xyz[..., None] * direction * (0.1 + 0.2 * torch.rand(B, K, P, 1, generator=g, dtype=F64))
    angle = 2 * math.pi * torch.rand(B, K, P, generator=g, dtype=F64)
    shift = (15 + 25 * torch.rand(B, K, P, generator=g, dtype=F64))[..., None]
    pix = pix + bad_pix[..., None] * shift * torch.stack([angle.cos(), angle.sin()], -1)
    T0, X0 = _perturbed(T, X, seed=7)
    out = _refine(T0, X0, xyz, pix, Kc, T_cd)
    assert torch.equal(out.inlier_xyz, ~bad_xyz) and torch.equal(out.inlier_pix, ~bad_pix)
    assert _pose_error(out.T_cam_world, T).abs().max() < 1e-8
    assert (out.points_world - X).abs().max() < 1e-8


def _noisy(B, K, P, seed):
    T, X, xyz, pix, Kc, T_cd = _window(B, K, P, seed)
    g = torch.Generator().manual_seed(seed + 100)
    xyz = xyz + SIG_XYZ * torch.randn(xyz.shape, generator=g, dtype=F64)
    pix = pix + SIG_PIX * torch.randn(pix.shape, generator=g, dtype=F64)
    T0, X0 = _perturbed(T, X, seed + 200)
    return T0, X0, xyz, pix, Kc, T_cd


@pytest.mark.equivalence
def test_batched_equals_looped():
    args = _noisy(3, 4, 12, seed=8)
    out = _refine(*args)
    for b in range(3):
        one = _refine(*(a[b : b + 1] for a in args))
        torch.testing.assert_close(one.T_cam_world[0], out.T_cam_world[b], rtol=0, atol=F64_UNIT)
        torch.testing.assert_close(one.points_world[0], out.points_world[b], rtol=0, atol=F64_UNIT)
        torch.testing.assert_close(one.cov_poses[0], out.cov_poses[b], rtol=F64_UNIT, atol=F64_UNIT * 1e-6)
        torch.testing.assert_close(one.cov_points[0], out.cov_points[b], rtol=F64_UNIT, atol=F64_UNIT * 1e-6)
        assert torch.equal(one.inlier_xyz[0], out.inlier_xyz[b]) and torch.equal(one.inlier_pix[0], out.inlier_pix[b])


@pytest.mark.equivalence
def test_padding_poses_and_landmarks_changes_nothing():
    """A window padded with a masked-out pose and landmarks without measurements equals the window alone."""
    T0, X0, xyz, pix, Kc, T_cd = _noisy(1, 3, 10, seed=9)
    B, K, P = 1, 3, 10
    out = _refine(T0, X0, xyz, pix, Kc, T_cd)
    Tp = torch.cat([T0, se3_exp(torch.full((1, 1, 6), 0.1, dtype=F64))], 1)
    Xp = torch.cat([X0, torch.ones(1, 4, 3, dtype=F64)], 1)
    pad = lambda t, v: torch.cat([torch.cat([t, torch.full((1, 1, P, *t.shape[3:]), v, dtype=t.dtype)], 1),  # noqa: E731
                                  torch.full((1, K + 1, 4, *t.shape[3:]), v, dtype=t.dtype)], 2)  # fmt: skip
    valid = pad(torch.ones(B, K, P, dtype=torch.bool), False)
    pose_valid = torch.tensor([[True, True, True, False]])
    padded = refine_window(Tp, Xp, pad(xyz, float("nan")), pad(pix, float("nan")), pad(_ones((B, K, P), SIG_XYZ**2), 0.0),
                           pad(_ones((B, K, P), SIG_PIX**2), 0.0), valid, valid, Kc, T_cd, pose_valid=pose_valid)  # fmt: skip
    torch.testing.assert_close(padded.T_cam_world[:, :K], out.T_cam_world, rtol=0, atol=F64_UNIT)
    assert torch.equal(padded.T_cam_world[:, K:], Tp[:, K:]) and torch.equal(padded.points_world[:, P:], Xp[:, P:])
    torch.testing.assert_close(padded.points_world[:, :P], out.points_world, rtol=0, atol=F64_UNIT)
    torch.testing.assert_close(padded.cov_poses[:, :K, :K], out.cov_poses, rtol=F64_UNIT, atol=F64_UNIT * 1e-6)
    assert padded.cov_points[:, P:].abs().max() == 0 and padded.cov_poses[:, K:].abs().max() == 0


def test_a_pose_prior_fixes_the_gauge_like_a_fixed_pose():
    """With the first pose's prior very strong (1e12) instead of fixing it, the window is the fixed-gauge answer."""
    T0, X0, xyz, pix, Kc, T_cd = _noisy(2, 3, 10, seed=10)
    fixed = _refine(T0, X0, xyz, pix, Kc, T_cd)
    info = torch.zeros(2, 3, 6, 6, dtype=F64)
    info[:, 0] = 1e12 * torch.eye(6, dtype=F64)
    prior = _refine(T0, X0, xyz, pix, Kc, T_cd, fix_first=False, pose_prior_info=info)
    torch.testing.assert_close(prior.T_cam_world, fixed.T_cam_world, rtol=0, atol=1e-9)
    torch.testing.assert_close(prior.cov_poses[:, 1:, 1:], fixed.cov_poses[:, 1:, 1:], rtol=1e-5, atol=1e-14)


def test_module_equals_function_and_bad_input_raises():
    args = _noisy(1, 3, 6, seed=11)
    a, b = _refine(*args, loss="cauchy"), WindowRefiner(loss="cauchy")(*args[:4], *(
        (_ones(args[2].shape[:3], SIG_XYZ**2), _ones(args[2].shape[:3], SIG_PIX**2),
         torch.ones(args[2].shape[:3], dtype=torch.bool), torch.ones(args[2].shape[:3], dtype=torch.bool))), *args[4:])  # fmt: skip
    assert torch.equal(a.T_cam_world, b.T_cam_world)
    with pytest.raises(ValueError, match="loss"):
        _refine(*args, loss="tukey")
    with pytest.raises(ValueError, match="gauge"):
        _refine(*args, fix_first=False)
    with pytest.raises(ValueError, match="points_world"):
        _refine(args[0], args[1][:, :3], *args[2:])
    assert chi2_quantile(0.999, 3) > 16  # the inlier gate of a 3D block is the filter's
