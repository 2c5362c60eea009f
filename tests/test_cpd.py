"""Rigid CPD: exact SE(3) recovery, pycpd on the same inputs (iterate for iterate), outliers, masks, batching."""

import numpy as np
import pytest
import torch
from pointsets import eye, ones, random_cloud, random_T, registration_args

from torchtrack.estimators import CPDEstimator, CPDResult
from torchtrack.estimators.cpd import cpd_rigid
from torchtrack.estimators.horn import horn
from torchtrack.geometry import rotation_angle, transform_points


def pose_errors(T_est, T_true):
    dR = T_est[..., :3, :3].transpose(-1, -2) @ T_true[..., :3, :3]
    return rotation_angle(dR), (T_est[..., :3, 3] - T_true[..., :3, 3]).norm(dim=-1)


def run_pycpd(src, dst, w, max_iters, tol, fixed_scale=False):
    """pycpd's RigidRegistration(X=dst, Y=src): rows, TY = s Y @ R + t -> column-vector T with s R.T.
    ``fixed_scale``: the same EM with s = 1 (Myronenko & Song Fig. 2 with the scale update removed), as a subclass
    that overrides only the two lines pycpd has no switch for."""
    from pycpd import RigidRegistration

    class FixedScale(RigidRegistration):
        def update_transform(self):
            super().update_transform()
            mu_x, mu_y = self.Pt1 @ self.X / self.Np, self.P1 @ self.Y / self.Np
            self.s, self.t = 1.0, mu_x - mu_y @ self.R

        def update_variance(self):
            super().update_variance()
            trAR = np.trace(self.A @ self.R)
            xPx = self.Pt1 @ np.sum(self.X_hat * self.X_hat, axis=1)
            self.sigma2 = (xPx - 2 * trAR + self.YPY) / (self.Np * self.D)

    cls = FixedScale if fixed_scale else RigidRegistration
    reg = cls(X=dst.numpy(), Y=src.numpy(), w=w, max_iterations=max_iters, tolerance=tol)
    _, (s, R, t) = reg.register()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = s * R.T, t
    return torch.from_numpy(T), s, reg.sigma2, reg.iteration


def noisy_partial_problem(B=3, N=60, M=70, seed=30):
    T = random_T(B, seed=seed, max_angle=0.3)
    src = random_cloud(B, N, seed=seed + 1)
    dst = random_cloud(B, M, seed=seed + 2)
    g = torch.Generator().manual_seed(seed + 3)
    dst[:, :N] = transform_points(T, src) + 0.003 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    return src, dst, T


def test_smoke_shapes_and_type():
    src = random_cloud(2, 20)
    res = cpd_rigid(src, src, ones(2, 20), ones(2, 20), eye(2))
    assert isinstance(res, CPDResult)
    assert res.T.shape == (2, 4, 4) and res.sigma2.shape == (2,) and res.iterations.dtype == torch.long
    torch.testing.assert_close(res.T, eye(2), atol=1e-12, rtol=0)
    assert res.converged.all() and (res.scale == 1).all()


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(src=torch.zeros(2, 5)),
        dict(dst=torch.zeros(3, 7, 3)),
        dict(valid_src=torch.ones(2, 5)),  # not bool
        dict(T_init=torch.eye(4)),
        dict(w=1.0),
        dict(max_iters=-1),
    ],
)
def test_bad_input_raises(kwargs):
    args = registration_args()
    args.update(kwargs)
    kw = {k: args.pop(k) for k in ["w", "max_iters"] if k in args}
    with pytest.raises(ValueError, match="cpd_rigid"):
        cpd_rigid(**args, **kw)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_recovery_of_known_se3(dtype):
    """Same point set, shuffled, moved by a known motion, started from a nearby T_init: exact recovery."""
    B, N = 8, 60
    T = random_T(B, dtype, seed=2)
    src = random_cloud(B, N, dtype, seed=3)
    dst = transform_points(T, src)[:, torch.randperm(N, generator=torch.Generator().manual_seed(4))]
    T_init = random_T(B, dtype, seed=5, max_angle=0.05, max_trans=0.01)
    res = cpd_rigid(src, dst, ones(B, N), ones(B, N), T_init, max_iters=200)
    assert res.valid.all() and res.converged.all()
    if dtype == torch.float64:
        assert (res.T - T).abs().max() <= 1e-9
    else:
        torch.testing.assert_close(res.T, T, atol=1e-5, rtol=0)


@pytest.mark.parametrize("w", [0.0, 0.2])
def test_matches_pycpd_iterate_for_iterate(w):
    """Partial overlap and noise, scale estimated (pycpd always estimates it): after 15 EM iterations without
    a convergence test, and at convergence, the same s R, t, sigma² as pycpd."""
    src, dst, _ = noisy_partial_problem()
    B, N, M = src.shape[0], src.shape[1], dst.shape[1]
    for iters, tol, tol_pycpd, atol in [(15, 0.0, 0.0, 1e-10), (500, 1e-12, 1e-8, 1e-8)]:
        res = cpd_rigid(src, dst, ones(B, N), ones(B, M), eye(B), w=w, max_iters=iters, tol=tol, scale=True)
        assert tol == 0 or res.converged.all()
        for b in range(B):
            T_ref, s_ref, sigma2_ref, _ = run_pycpd(src[b], dst[b], w, iters, tol_pycpd)
            torch.testing.assert_close(res.T[b], T_ref, atol=atol, rtol=0)
            assert abs(res.scale[b].item() - s_ref) < atol
            assert abs(res.sigma2[b].item() / sigma2_ref - 1) < 1e3 * atol


def test_rigid_matches_fixed_scale_pycpd_and_init_is_composed():
    """scale=False against pycpd with s fixed to 1, from a non-identity T_init (pycpd is handed T_init src)."""
    src, dst, _ = noisy_partial_problem(seed=40)
    B, N, M = src.shape[0], src.shape[1], dst.shape[1]
    T_init = random_T(B, seed=44, max_angle=0.05, max_trans=0.01)
    res = cpd_rigid(src, dst, ones(B, N), ones(B, M), T_init, w=0.1, max_iters=20, tol=0.0)
    for b in range(B):
        T_ref, _, sigma2_ref, _ = run_pycpd(transform_points(T_init[b], src[b]), dst[b], 0.1, 20, 0.0, fixed_scale=True)
        torch.testing.assert_close(res.T[b], T_ref @ T_init[b], atol=1e-9, rtol=0)
        assert abs(res.sigma2[b].item() / sigma2_ref - 1) < 1e-8
    torch.testing.assert_close(torch.linalg.det(res.T[:, :3, :3]), torch.ones(B, dtype=torch.float64))


def test_noise_matches_horn_level_and_outlier_weight_helps():
    """Noise 2 mm on all points: CPD's error is within 2x of Horn's with the true correspondences (whose
    sigma/sqrt(N) statistics test_horn checks). With 20 % of the measured points displaced 5-20 cm, w = 0.2
    keeps the error within 3x of the outlier-free Horn level while w = 0 is pulled off by more than 5x."""
    B, N, sigma = 6, 60, 0.002
    T = random_T(B, seed=50)
    src = random_cloud(B, N, seed=51)
    g = torch.Generator().manual_seed(52)
    dst = transform_points(T, src) + sigma * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    level_r, level_t = (e.mean() for e in pose_errors(horn(src, dst, ones(B, N)).T, T))
    r, t = pose_errors(cpd_rigid(src, dst, ones(B, N), ones(B, N), eye(B)).T, T)
    assert r.mean() < 2 * level_r and t.mean() < 2 * level_t
    n_out = N // 5
    d = torch.randn(B, n_out, 3, generator=g, dtype=torch.float64)
    dst[:, :n_out] += d / d.norm(dim=-1, keepdim=True) * (0.05 + 0.15 * torch.rand(B, n_out, 1, generator=g))
    r, t = pose_errors(cpd_rigid(src, dst, ones(B, N), ones(B, N), eye(B), w=0.2).T, T)
    assert r.mean() < 3 * level_r and t.mean() < 3 * level_t
    r0, t0 = pose_errors(cpd_rigid(src, dst, ones(B, N), ones(B, N), eye(B), w=0.0).T, T)
    assert r0.mean() > 5 * level_r and t0.mean() > 5 * level_t


@pytest.mark.equivalence
def test_masked_garbage_changes_nothing_and_batched_equals_looped():
    src, dst, _ = noisy_partial_problem(B=4, seed=60)
    B, N, M = 4, src.shape[1], dst.shape[1]
    n_src, n_dst = [60, 35, 2, 50], [70, 45, 70, 60]
    vs = torch.arange(N)[None] < torch.tensor(n_src)[:, None]
    vd = torch.arange(M)[None] < torch.tensor(n_dst)[:, None]
    src_g, dst_g = src.clone(), dst.clone()
    src_g[~vs], dst_g[~vd] = torch.nan, 1e6
    T_init = random_T(B, seed=61, max_angle=0.02, max_trans=0.005)
    res = cpd_rigid(src_g, dst_g, vs, vd, T_init, w=0.1)
    assert res.valid.tolist() == [True, True, False, True]
    torch.testing.assert_close(res.T[2], T_init[2])
    for b in range(B):
        if not res.valid[b]:
            continue
        one = cpd_rigid(src[b : b + 1, : n_src[b]], dst[b : b + 1, : n_dst[b]], ones(1, n_src[b]), ones(1, n_dst[b]),
                        T_init[b : b + 1], w=0.1)  # fmt: skip
        for field in CPDResult._fields:
            torch.testing.assert_close(getattr(res, field)[b], getattr(one, field)[0], atol=1e-12, rtol=1e-10)


def test_planar_and_mirrored_sets_give_proper_rotations():
    """Planar set: exact, det +1. Mirrored destination (best orthogonal map is a reflection): the SVD's
    reflection correction keeps det(R) = +1."""
    B, N = 4, 50
    T = random_T(B, seed=70)
    src = random_cloud(B, N, seed=71)
    src[..., 2] = 1.0
    res = cpd_rigid(src, transform_points(T, src), ones(B, N), ones(B, N), eye(B), max_iters=200)
    torch.testing.assert_close(res.T, T, atol=1e-9, rtol=0)
    mirrored = src * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    res = cpd_rigid(random_cloud(B, N, seed=72), mirrored, ones(B, N), ones(B, N), eye(B))
    torch.testing.assert_close(torch.linalg.det(res.T[:, :3, :3]), torch.ones(B, dtype=torch.float64))


def test_estimator_equals_function_and_keeps_T_prev():
    B, N = 3, 40
    T = random_T(B, seed=80)
    src = random_cloud(B, N, seed=81)
    dst = transform_points(T, src)
    valid = ones(B, N)
    valid[1, 2:] = False
    T_prev = random_T(B, seed=82, max_angle=0.05, max_trans=0.01)
    out = CPDEstimator(w=0.1, max_iters=50, tol=1e-6)(src, dst, valid, T_prev, torch.rand(B, N))
    ref = cpd_rigid(src, dst, valid, valid, T_prev, w=0.1, max_iters=50, tol=1e-6)
    torch.testing.assert_close(out, ref.T)
    torch.testing.assert_close(out[1], T_prev[1])
