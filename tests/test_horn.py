"""Horn's quaternion absolute orientation: exact SE(3) recovery, scipy's Kabsch, noise statistics, masks."""

import math
from functools import partial

import pointsets
import pytest
import torch
from scipy.spatial.transform import Rotation
from tolerances import F64_UNIT

from torchtrack.estimators import HornEstimator, RigidFit
from torchtrack.estimators.horn import horn
from torchtrack.geometry import rotation_angle, se3_exp, so3_log, transform_points

TOL = {torch.float32: 2e-5, torch.float64: 1e-10}


# Horn is global: any rotation and half a metre of translation (the shared defaults are inter-frame motions)
random_T = partial(pointsets.random_T, max_angle=math.pi - 1e-3, max_trans=0.5)
random_cloud = partial(pointsets.random_cloud, spread=0.15)


def pose_errors(T_est, T_true):
    """(B,) rotation angle (rad) and translation (m) of T_est^-1 T_true."""
    dR = T_est[..., :3, :3].transpose(-1, -2) @ T_true[..., :3, :3]
    return rotation_angle(dR), (T_est[..., :3, 3] - T_true[..., :3, 3]).norm(dim=-1)


def all_valid(B, N):
    return torch.ones(B, N, dtype=torch.bool)


def test_smoke_shapes_and_type():
    src = random_cloud(2, 10)
    est = horn(src, src, all_valid(2, 10))
    assert isinstance(est, RigidFit)
    assert est.T.shape == (2, 4, 4) and est.valid.shape == (2,) and est.valid.dtype == torch.bool
    torch.testing.assert_close(est.T, torch.eye(4, dtype=torch.float64).expand(2, 4, 4))


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(src=torch.zeros(2, 5, 2)),  # not 3D points
        dict(dst=torch.zeros(2, 6, 3)),  # N mismatch
        dict(dst=torch.zeros(3, 5, 3)),  # B mismatch
        dict(valid=torch.ones(2, 5)),  # not bool
        dict(weights=-torch.ones(2, 5)),  # negative weights
        dict(weights=torch.ones(2, 4)),  # wrong shape
    ],
)
def test_bad_input_raises(kwargs):
    args = dict(src=torch.zeros(2, 5, 3), dst=torch.zeros(2, 5, 3), valid=torch.ones(2, 5, dtype=torch.bool))
    args.update(kwargs)
    with pytest.raises(ValueError, match="horn"):
        horn(**args)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exact_recovery_of_known_se3(dtype):
    """Noise-free correspondences, rotations up to ~pi: the transform is recovered to rounding."""
    B, N = 64, 30
    T = random_T(B, dtype)
    src = random_cloud(B, N, dtype)
    est = horn(src, transform_points(T, src), all_valid(B, N))
    assert est.valid.all()
    torch.testing.assert_close(est.T, T, atol=TOL[dtype] * (10 if dtype == torch.float32 else 1), rtol=0)
    if dtype == torch.float64:
        assert (est.T - T).abs().max() <= 1e-6


def test_weighted_matches_scipy_kabsch():
    """Noisy weighted problem: same rotation as scipy's align_vectors on the weighted-centred sets."""
    B, N = 8, 40
    T = random_T(B, seed=3)
    src = random_cloud(B, N, seed=4)
    g = torch.Generator().manual_seed(5)
    dst = transform_points(T, src) + 0.01 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    w = torch.rand(B, N, generator=g, dtype=torch.float64) + 0.1
    est = horn(src, dst, all_valid(B, N), w)
    for b in range(B):
        wb = w[b, :, None]
        a = src[b] - (wb * src[b]).sum(0) / wb.sum()
        d = dst[b] - (wb * dst[b]).sum(0) / wb.sum()
        rot, _ = Rotation.align_vectors(d.numpy(), a.numpy(), weights=w[b].numpy())
        torch.testing.assert_close(est.T[b, :3, :3], torch.from_numpy(rot.as_matrix()), atol=1e-10, rtol=0)
        t = (wb * (dst[b] - src[b] @ est.T[b, :3, :3].T)).sum(0) / wb.sum()  # t = mu_d - R mu_s
        torch.testing.assert_close(est.T[b, :3, 3], t, atol=1e-12, rtol=0)


def test_noise_statistics_match_first_order_prediction():
    """Isotropic noise sigma on dst: the per-axis rotation error has covariance sigma^2 H^-1 with
    H = sum_i (|a_i|^2 I - a_i a_i^T) (a_i centred source), and the error at the centroid has per-axis
    std sigma / sqrt(N). Empirical RMS over 400 trials must match within 15 %."""
    B, N, sigma = 400, 100, 0.002
    T = random_T(B, seed=6)
    src = random_cloud(B, N, seed=7)
    g = torch.Generator().manual_seed(8)
    dst = transform_points(T, src) + sigma * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    est = horn(src, dst, all_valid(B, N))
    R_true = T[:, :3, :3]
    dtheta = so3_log(R_true.transpose(-1, -2) @ est.T[:, :3, :3])  # error in the source frame
    a = src - src.mean(1, keepdim=True)
    eye = torch.eye(3, dtype=torch.float64)
    H = (a.square().sum(-1)[..., None, None] * eye - a[..., :, None] * a[..., None, :]).sum(1)
    whitened = (torch.linalg.cholesky(H).transpose(-1, -2) @ dtheta[..., None])[..., 0] / sigma  # ~ N(0, I)
    assert abs(whitened.square().mean().sqrt().item() - 1) < 0.15
    centroid_err = transform_points(est.T, src.mean(1, keepdim=True)) - transform_points(T, src.mean(1, keepdim=True))
    assert abs(centroid_err.square().mean().sqrt().item() / (sigma / math.sqrt(N)) - 1) < 0.15


def test_zero_weights_equal_masking_and_reject_outliers():
    B, N = 4, 30
    T = random_T(B, seed=9)
    src = random_cloud(B, N, seed=10)
    dst = transform_points(T, src)
    dst[:, :6] += 0.5  # gross outliers
    w = torch.ones(B, N, dtype=torch.float64)
    w[:, :6] = 0
    valid = w > 0
    by_weight = horn(src, dst, all_valid(B, N), w)
    by_mask = horn(src, dst, valid)
    torch.testing.assert_close(by_weight.T, by_mask.T, atol=1e-12, rtol=0)
    torch.testing.assert_close(by_mask.T, T, atol=1e-10, rtol=0)
    assert pose_errors(horn(src, dst, all_valid(B, N)).T, T)[0].min() > 1e-3  # unweighted is biased


@pytest.mark.equivalence
def test_masked_garbage_changes_nothing_and_batched_equals_looped():
    B, N = 5, 25
    T = random_T(B, seed=11)
    src = random_cloud(B, N, seed=12)
    dst = transform_points(T, src) + 0.003 * torch.randn(B, N, 3, dtype=torch.float64)
    counts = [25, 3, 10, 17, 2]
    valid = torch.arange(N)[None] < torch.tensor(counts)[:, None]
    src_g, dst_g = src.clone(), dst.clone()
    src_g[~valid] = torch.nan
    dst_g[~valid] = 1e6
    est = horn(src_g, dst_g, valid)
    assert est.valid.tolist() == [True, True, True, True, False]
    for b, n in enumerate(counts):
        one = horn(src[b : b + 1, :n], dst[b : b + 1, :n], all_valid(1, n))
        torch.testing.assert_close(est.T[b], one.T[0], atol=F64_UNIT, rtol=0)
        assert bool(one.valid) == est.valid[b]
    torch.testing.assert_close(est.T[4], torch.eye(4, dtype=torch.float64))  # identity where invalid


def test_planar_and_mirrored_sets_give_proper_rotations():
    """Planar source: exact recovery with det +1. Mirrored data (the best orthogonal map is a reflection):
    the result is still a rotation and equals the best proper rotation (scipy)."""
    B, N = 6, 20
    T = random_T(B, seed=13)
    src = random_cloud(B, N, seed=14)
    src[..., 2] = 1.0  # plane z = 1
    est = horn(src, transform_points(T, src), all_valid(B, N))
    assert est.valid.all()
    torch.testing.assert_close(est.T, T, atol=1e-10, rtol=0)
    src3 = random_cloud(B, N, seed=15)
    mirrored = src3 * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    est = horn(src3, mirrored, all_valid(B, N))
    torch.testing.assert_close(torch.linalg.det(est.T[:, :3, :3]), torch.ones(B, dtype=torch.float64))
    for b in range(B):
        a, d = src3[b] - src3[b].mean(0), mirrored[b] - mirrored[b].mean(0)
        rot, _ = Rotation.align_vectors(d.numpy(), a.numpy())
        torch.testing.assert_close(est.T[b, :3, :3], torch.from_numpy(rot.as_matrix()), atol=1e-8, rtol=0)


def test_degenerate_sets_are_invalid():
    line = torch.linspace(0, 1, 10, dtype=torch.float64)[:, None] * torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    src = torch.stack([line + torch.tensor([0, 0, 1.0], dtype=torch.float64), random_cloud(1, 10)[0]])
    valid = all_valid(2, 10)
    valid[1, 2:] = False  # only 2 points
    est = horn(src, src + 0.1, valid)
    assert est.valid.tolist() == [False, False]


def test_gradcheck_float64():
    src = random_cloud(1, 6, seed=16)
    dst = transform_points(random_T(1, seed=17, max_angle=1.0), src) + 0.01 * torch.randn(1, 6, 3, dtype=torch.float64)
    dst.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: horn(src, d, all_valid(1, 6)).T, (dst,))


def test_estimator_equals_function_and_keeps_T_prev():
    B, N = 3, 12
    T = random_T(B, seed=18)
    src = random_cloud(B, N, seed=19)
    dst = transform_points(T, src)
    w = torch.rand(B, N, dtype=torch.float64) + 0.5
    valid = all_valid(B, N)
    valid[2, 2:] = False
    T_prev = se3_exp(0.1 * torch.ones(B, 6, dtype=torch.float64))
    out = HornEstimator()(src, dst, valid, T_prev, w)
    ref = horn(src, dst, valid, w)
    torch.testing.assert_close(out[:2], ref.T[:2])
    torch.testing.assert_close(out[2], T_prev[2])
    noisy = dst + 0.01 * torch.randn(B, N, 3, generator=torch.Generator().manual_seed(20), dtype=torch.float64)
    unweighted = HornEstimator(use_weights=False)(src, noisy, valid, T_prev, w)
    torch.testing.assert_close(unweighted[:2], horn(src, noisy, valid).T[:2])
    assert (unweighted[:2] - horn(src, noisy, valid, w).T[:2]).abs().max() > 1e-6  # the weights were ignored


def test_estimator_classes_resolve_by_module_path():
    """conf/tracker/*.yaml name the classes by module path; the package must not shadow those submodules."""
    from hydra.utils import get_class

    from torchtrack.estimators import CPDEstimator, ICPEstimator

    for path, cls in [
        ("torchtrack.estimators.horn.HornEstimator", HornEstimator),
        ("torchtrack.estimators.icp.ICPEstimator", ICPEstimator),
        ("torchtrack.estimators.cpd.CPDEstimator", CPDEstimator),
    ]:
        assert get_class(path) is cls
