"""Point-to-point ICP: exact SE(3) recovery, Open3D's registration_icp on the same input, masks, batching."""

import math

import numpy as np
import pytest
import torch
from pointsets import eye, ones, random_cloud, random_T, registration_args
from tolerances import F64_UNIT

from torchtrack.estimators import ICPEstimator, ICPResult
from torchtrack.estimators.horn import horn
from torchtrack.estimators.icp import icp
from torchtrack.geometry import rotation_angle, transform_points


def open3d_icp(src, dst, T_init, max_corr_dist, max_iters, tight):
    o3d = pytest.importorskip("open3d")  # the reference only: skipped where Open3D is not installed

    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(
        relative_fitness=1e-14 if tight else 0.0, relative_rmse=1e-14 if tight else 0.0, max_iteration=max_iters
    )
    s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.numpy()))
    d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst.numpy()))
    res = reg.registration_icp(s, d, max_corr_dist, T_init.numpy(), reg.TransformationEstimationPointToPoint(), crit)
    return torch.from_numpy(np.asarray(res.transformation).copy()), res.inlier_rmse


def test_smoke_shapes_and_type():
    src = random_cloud(2, 20)
    res = icp(src, src, ones(2, 20), ones(2, 20), eye(2))
    assert isinstance(res, ICPResult)
    assert res.T.shape == (2, 4, 4) and res.rmse.shape == (2,) and res.iterations.dtype == torch.long
    torch.testing.assert_close(res.T, eye(2))
    assert res.converged.all() and (res.iterations == 0).all()


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(src=torch.zeros(2, 5)),
        dict(dst=torch.zeros(3, 7, 3)),
        dict(valid_dst=torch.ones(2, 5, dtype=torch.bool)),  # dst has M = 7
        dict(T_init=torch.eye(4)),
        dict(T_init=torch.eye(4, dtype=torch.float64).expand(2, 4, 4)),  # dtype mismatch
        dict(max_corr_dist=-1.0),
    ],
)
def test_bad_input_raises(kwargs):
    args = registration_args()
    args.update(kwargs)
    kw = {k: args.pop(k) for k in ["max_corr_dist"] if k in args}
    with pytest.raises(ValueError, match="icp"):
        icp(**args, **kw)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_recovery_of_known_se3(dtype):
    """Same point set, shuffled, moved by a known inter-frame motion: ICP from identity recovers it."""
    B, N = 16, 60
    T = random_T(B, dtype, seed=2)
    src = random_cloud(B, N, dtype, seed=3)
    perm = torch.randperm(N, generator=torch.Generator().manual_seed(4))
    dst = transform_points(T, src)[:, perm]
    res = icp(src, dst, ones(B, N), ones(B, N), eye(B, dtype), max_iters=100, tol=0.0)
    assert res.valid.all() and res.converged.all()
    atol = 1e-6 if dtype == torch.float64 else 1e-5
    assert (res.T - T).abs().max() <= (1e-10 if dtype == torch.float64 else atol)
    torch.testing.assert_close(res.T, T, atol=atol, rtol=0)


@pytest.mark.parametrize("tight", [False, True])
def test_matches_open3d_registration_icp(tight):
    """Partial overlap (extra dst points), noise, a max correspondence distance that matters and a non-identity
    init: the same T as Open3D after 5 iterations (no convergence test on either side) and at convergence."""
    B, N, M, d_max = 4, 80, 100, 0.03
    T = random_T(B, seed=5)
    src = random_cloud(B, N, seed=6)
    dst = random_cloud(B, M, seed=7)
    g = torch.Generator().manual_seed(8)
    dst[:, :N] = transform_points(T, src) + 0.002 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    T_init = random_T(B, seed=9, max_angle=0.03, max_trans=0.01)
    iters = 200 if tight else 5
    res = icp(
        src, dst, ones(B, N), ones(B, M), T_init, max_iters=iters, tol=1e-14 if tight else 0.0, max_corr_dist=d_max
    )
    for b in range(B):
        T_o3d, rmse_o3d = open3d_icp(src[b], dst[b], T_init[b], d_max, iters, tight)
        torch.testing.assert_close(res.T[b], T_o3d, atol=1e-9, rtol=0)
        assert abs(res.rmse[b].item() - rmse_o3d) < 1e-9


def test_max_corr_dist_rejects_outliers():
    """Source points without a counterpart, far (> max_corr_dist) from every dst point: exact recovery with
    the threshold; without it they pull the estimate away (dst-side extras never matter to src->dst matching)."""
    B, N = 4, 60
    T = random_T(B, seed=10)
    obj = random_cloud(B, N, seed=11)
    src = torch.cat([obj, random_cloud(B, 10, seed=12) + 0.5], 1)
    dst = transform_points(T, obj)
    valid_src = ones(B, N + 10)
    res = icp(src, dst, valid_src, ones(B, N), eye(B), max_iters=100, max_corr_dist=0.2)
    torch.testing.assert_close(res.T, T, atol=1e-9, rtol=0)
    biased = icp(src, dst, valid_src, ones(B, N), eye(B), max_iters=100)
    assert (biased.T - T).abs().amax((1, 2)).min() > 1e-2


def test_noisy_fixed_point_is_horn_with_true_correspondences():
    """Noise (2 mm) well below the point spacing: nearest neighbours are the true matches at convergence,
    so ICP's fixed point is exactly Horn's closed form with the known correspondences."""
    B, N = 8, 60
    T = random_T(B, seed=13)
    src = random_cloud(B, N, seed=14)
    g = torch.Generator().manual_seed(15)
    dst = transform_points(T, src) + 0.002 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    res = icp(src, dst, ones(B, N), ones(B, N), eye(B), max_iters=100, tol=0.0)
    torch.testing.assert_close(res.T, horn(src, dst, ones(B, N)).T, atol=1e-12, rtol=0)


@pytest.mark.equivalence
def test_masked_garbage_changes_nothing_and_batched_equals_looped():
    B, N, M = 4, 50, 60
    T = random_T(B, seed=16)
    src = random_cloud(B, N, seed=17)
    dst = random_cloud(B, M, seed=18)
    dst[:, :N] = transform_points(T, src) + 0.001 * torch.randn(B, N, 3, dtype=torch.float64)
    n_src, n_dst = [50, 30, 2, 44], [60, 45, 60, 50]
    vs = torch.arange(N)[None] < torch.tensor(n_src)[:, None]
    vd = torch.arange(M)[None] < torch.tensor(n_dst)[:, None]
    src_g, dst_g = src.clone(), dst.clone()
    src_g[~vs], dst_g[~vd] = torch.nan, 0.0  # NaN padding on one side, zeros on the other
    T_init = random_T(B, seed=19, max_angle=0.02, max_trans=0.005)
    res = icp(src_g, dst_g, vs, vd, T_init, max_corr_dist=0.05)
    assert res.valid.tolist() == [True, True, False, True]
    torch.testing.assert_close(res.T[2], T_init[2])
    for b in range(B):
        one = icp(src[b : b + 1, : n_src[b]], dst[b : b + 1, : n_dst[b]], ones(1, n_src[b]), ones(1, n_dst[b]),
                  T_init[b : b + 1], max_corr_dist=0.05)  # fmt: skip
        for field in ICPResult._fields:
            torch.testing.assert_close(getattr(res, field)[b], getattr(one, field)[0], atol=F64_UNIT, rtol=0)


@pytest.mark.equivalence
def test_sequences_stop_independently():
    """A sequence started at its exact pose stops after one update; a distant one keeps iterating; each
    equals its own run alone within F64_UNIT (a batch of two runs other kernels; frozen sequences are not moved by
    the others' iterations: the iteration counts agree)."""
    B, N = 2, 60
    T = random_T(B, seed=27, max_angle=0.25, max_trans=0.03)
    src = random_cloud(B, N, seed=28)
    dst = transform_points(T, src)
    T_init = torch.stack([T[0], eye(1)[0]])
    res = icp(src, dst, ones(B, N), ones(B, N), T_init, max_iters=100, tol=0.0)
    assert res.iterations[0] <= 1 < res.iterations[1] and res.converged.all()
    for b in range(B):
        one = icp(src[b : b + 1], dst[b : b + 1], ones(1, N), ones(1, N), T_init[b : b + 1], max_iters=100, tol=0.0)
        torch.testing.assert_close(res.T[b], one.T[0], atol=F64_UNIT, rtol=0)
        assert res.iterations[b] == one.iterations[0]


def test_planar_set_exact():
    B, N = 4, 60
    T = random_T(B, seed=20)
    src = random_cloud(B, N, seed=21)
    src[..., 2] = 1.0
    res = icp(src, transform_points(T, src), ones(B, N), ones(B, N), eye(B), max_iters=100)
    torch.testing.assert_close(res.T, T, atol=1e-9, rtol=0)
    torch.testing.assert_close(torch.linalg.det(res.T[:, :3, :3]), torch.ones(B, dtype=torch.float64))


def test_collinear_or_too_small_sets_keep_T_init():
    line = torch.linspace(0, 0.3, 20, dtype=torch.float64)[:, None] * torch.tensor([1.0, 0.5, 0.2], dtype=torch.float64)
    src = torch.stack([line + torch.tensor([0, 0, 1.0], dtype=torch.float64), random_cloud(1, 20, seed=29)[0]])
    valid = ones(2, 20)
    valid[1, 2:] = False
    T_init = random_T(2, seed=30)
    res = icp(src, src + 0.01, valid, valid, T_init)
    assert res.valid.tolist() == [False, False] and not res.converged.any()
    torch.testing.assert_close(res.T, T_init, atol=0, rtol=0)


def test_max_iters_zero_returns_init_and_rmse_at_init():
    src = random_cloud(1, 20, seed=22)
    T_init = random_T(1, seed=23)
    res = icp(src, src, ones(1, 20), ones(1, 20), T_init, max_iters=0)
    torch.testing.assert_close(res.T, T_init)
    moved = transform_points(T_init, src)
    nn = torch.cdist(moved, src).min(-1).values
    torch.testing.assert_close(res.rmse, nn.square().mean(-1).sqrt())
    assert res.iterations.item() == 0 and not res.converged.item()


def test_estimator_equals_function_and_keeps_T_prev():
    B, N = 3, 40
    T = random_T(B, seed=24)
    src = random_cloud(B, N, seed=25)
    dst = transform_points(T, src)
    valid = ones(B, N)
    valid[1, 2:] = False
    T_prev = random_T(B, seed=26, max_angle=0.05, max_trans=0.01)
    out = ICPEstimator(max_iters=30, tol=1e-8, max_corr_dist=0.1)(src, dst, valid, T_prev, torch.rand(B, N))
    ref = icp(src, dst, valid, valid, T_prev, max_iters=30, tol=1e-8, max_corr_dist=0.1)
    torch.testing.assert_close(out, ref.T)
    torch.testing.assert_close(out[1], T_prev[1])
    errs = rotation_angle(out[[0, 2], :3, :3].transpose(-1, -2) @ T[[0, 2], :3, :3])
    assert errs.max() < 1e-6 * math.pi
