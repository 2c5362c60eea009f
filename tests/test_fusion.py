"""FusionEKF: convergence on an exact synthetic moving rigid body, masks, resets, forms, batching."""

import math

import pytest
import torch

from torchtrack.filter import FusionEKF, fuse
from torchtrack.filter.models import pose_to_state
from torchtrack.geometry import (
    T_inv,
    intrinsics_matrix,
    make_T,
    project,
    rotation_angle,
    so3_exp,
    transform_points,
)

F64 = torch.float64


DT = 1 / 30


def body(B=2, N=60, seed=0):
    """Centred model points, colour K, a depth->colour extrinsic (not identity)."""
    g = torch.Generator().manual_seed(seed)
    X = 0.15 * torch.randn(B, N, 3, generator=g, dtype=F64)
    X = X - X.mean(1, keepdim=True)  # object frame at the model centroid
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=F64).expand(B, 3, 3)
    T_cd = make_T(so3_exp(torch.tensor([0.0, 0.01, 0.0], dtype=F64)), torch.tensor([-0.025, 0.0, 0.0], dtype=F64))
    return X, K, T_cd.expand(B, 4, 4)


def true_pose(t):
    """Constant linear velocity and constant angular velocity in SO(3) (NOT constant Euler rates)."""
    omega = torch.tensor([[0.3, -0.5, 0.4], [-0.2, 0.3, 0.6]], dtype=F64)
    R0 = so3_exp(torch.tensor([[0.1, 0.2, -0.1], [0.0, -0.3, 0.2]], dtype=F64))
    t0 = torch.tensor([[0.05, -0.02, 1.2], [-0.1, 0.05, 1.8]], dtype=F64)
    v = torch.tensor([[0.2, 0.1, -0.15], [-0.1, 0.05, 0.2]], dtype=F64)
    return make_T(so3_exp(omega * t) @ R0, t0 + v * t)


def measurements(T_cam_obj, X, K, T_cd):
    points_d = transform_points(T_cam_obj, X)  # eq. (6), noise-free
    pixels = project(K, transform_points(T_cd, points_d))  # eq. (7)
    return points_d, pixels


def pose_errors(T_est, T_true):
    E = T_inv(T_true) @ T_est
    return E[:, :3, 3].norm(dim=-1), torch.rad2deg(rotation_angle(E[:, :3, :3]))


def run(filt, steps, X, K, T_cd, valid=None, start=None):
    B, N = X.shape[:2]
    valid = torch.ones(B, N, dtype=torch.bool) if valid is None else valid
    start = true_pose(0.0) if start is None else start
    filt.reset(start)
    errs = []
    for k in range(1, steps + 1):
        filt.predict(torch.full((B,), DT, dtype=F64))
        T = true_pose(k * DT)
        est = filt.update(X, *measurements(T, X, K, T_cd), valid, K=K, T_color_depth=T_cd)
        errs.append(pose_errors(est.T_cam_obj, T))
    return est, errs


@pytest.mark.parametrize("jacobian", ["forward", "analytic"])
def test_converges_to_true_pose_on_noise_free_synthetic_motion(jacobian):
    """Start 2 cm / 2 deg off; noise-free 2D+3D measurements (small variances): < 1e-4 m and < 0.01 deg."""
    X, K, T_cd = body()
    start = true_pose(0.0) @ make_T(
        so3_exp(torch.tensor([0.0, 0.0, math.radians(2)], dtype=F64)), torch.tensor([0.02, 0.0, 0.0], dtype=F64)
    )
    filt = FusionEKF(sigma2_pix=1e-4, sigma2_xyz=1e-8, init_sigma_angle=0.05, init_sigma_trans=0.05, jacobian=jacobian)
    est, errs = run(filt, 30, X, K, T_cd, start=start)
    t_err, r_err = errs[-1]
    assert (t_err < 1e-4).all() and (r_err < 0.01).all(), (t_err, r_err)
    assert est.updated.all() and est.num_valid.tolist() == [60, 60]
    assert est.covariance.shape == (2, 12, 12) and est.innovation.shape == (2, 60, 5)


def test_iterated_update_beats_single_step_on_large_initial_error():
    """A single EKF step from a 10 deg wrong pose keeps a linearisation error; 3 Gauss-Newton steps remove it."""
    X, K, T_cd = body()
    start = true_pose(DT) @ make_T(
        so3_exp(torch.tensor([0.0, math.radians(10), 0.0], dtype=F64)), torch.zeros(3, dtype=F64)
    )
    errors = {}
    for it in (1, 3):
        filt = FusionEKF(sigma2_pix=1e-4, sigma2_xyz=1e-8, init_sigma_angle=0.5, init_sigma_trans=0.1, iterations=it)
        filt.reset(start)
        est = filt.update(
            X, *measurements(true_pose(DT), X, K, T_cd), torch.ones(2, 60, dtype=torch.bool), K=K, T_color_depth=T_cd
        )
        errors[it] = pose_errors(est.T_cam_obj, true_pose(DT))[1]
    assert (errors[3] < 1e-3).all() and (errors[1] > 10 * errors[3]).all(), errors


def test_forms_and_jacobians_agree():
    X, K, T_cd = body(N=20)
    outs = []
    for form, jac in (
        ("information", "forward"),
        ("gain", "forward"),
        ("information", "analytic"),
        ("information", "reverse"),
    ):
        filt = FusionEKF(form=form, jacobian=jac)
        outs.append(run(filt, 3, X, K, T_cd)[0])
    for o in outs[1:]:
        torch.testing.assert_close(o.state, outs[0].state, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(o.covariance, outs[0].covariance, atol=1e-12, rtol=1e-7)


def test_sequence_without_features_keeps_prediction_and_masked_garbage_is_ignored():
    X, K, T_cd = body(N=30)
    filt = FusionEKF()
    filt.reset(true_pose(0.0), velocity=torch.ones(2, 6, dtype=F64) * 0.1)
    pred = filt.predict(torch.full((2,), DT, dtype=F64))
    pd, px = measurements(true_pose(DT), X, K, T_cd)
    valid = torch.ones(2, 30, dtype=torch.bool)
    valid[1] = False
    garbage = lambda t: torch.where(valid[..., None], t, torch.full_like(t, float("nan")))  # noqa: E731
    est = filt.update(garbage(X), garbage(pd), garbage(px), valid, K=K, T_color_depth=T_cd)
    assert est.updated.tolist() == [True, False] and est.num_valid.tolist() == [30, 0]
    assert torch.equal(est.T_cam_obj[1], pred[1])
    assert torch.isfinite(est.state).all() and torch.isfinite(est.covariance).all()
    ref = FusionEKF()
    ref.reset(true_pose(0.0)[:1], velocity=torch.ones(1, 6, dtype=F64) * 0.1)
    ref.predict(torch.full((1,), DT, dtype=F64))
    ref_est = ref.update(X[:1], pd[:1], px[:1], valid[:1], K=K[:1], T_color_depth=T_cd[:1])
    torch.testing.assert_close(est.state[:1], ref_est.state, atol=1e-12, rtol=1e-12)


def test_valid_xyz_masks_only_the_3d_part():
    X, K, T_cd = body(N=10)
    filt = FusionEKF()
    filt.reset(true_pose(0.0))
    pd, px = measurements(true_pose(DT), X, K, T_cd)
    valid_xyz = torch.ones(2, 10, dtype=torch.bool)
    valid_xyz[:, ::2] = False
    pd = torch.where(valid_xyz[..., None], pd, torch.full_like(pd, float("nan")))
    est = filt.update(X, pd, px, torch.ones(2, 10, dtype=torch.bool), K=K, T_color_depth=T_cd, valid_xyz=valid_xyz)
    assert torch.isfinite(est.state).all()
    assert (est.innovation[:, ::2, :3] == 0).all() and (est.innovation[:, ::2, 3:] != 0).any()


def test_reset_with_mask_touches_only_masked_sequences():
    X, K, T_cd = body(N=10)
    filt = FusionEKF(init_sigma_angle=0.01)
    filt.reset(true_pose(0.0))
    filt.predict(torch.full((2,), DT, dtype=F64))
    filt.update(
        X, *measurements(true_pose(DT), X, K, T_cd), torch.ones(2, 10, dtype=torch.bool), K=K, T_color_depth=T_cd
    )
    mean, cov = filt.mean.clone(), filt.cov.clone()
    new = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
    new[:, 2, 3] = 0.7
    filt.reset(new, mask=torch.tensor([False, True]))
    assert torch.equal(filt.mean[0], mean[0]) and torch.equal(filt.cov[0], cov[0])
    torch.testing.assert_close(filt.mean[1], pose_to_state(new[1]))
    torch.testing.assert_close(filt.cov[1], torch.diag(filt.init_var))
    torch.testing.assert_close(filt.T_cam_obj[1], new[1])


@pytest.mark.equivalence
def test_batched_equals_looped():
    X, K, T_cd = body(N=25)
    est, _ = run(FusionEKF(), 4, X, K, T_cd)
    for b in range(2):
        filt = FusionEKF()
        filt.reset(true_pose(0.0)[b : b + 1])
        for k in range(1, 5):
            filt.predict(torch.full((1,), DT, dtype=F64))
            pd, px = measurements(true_pose(k * DT)[b : b + 1], X[b : b + 1], K[:1], T_cd[:1])
            one = filt.update(
                X[b : b + 1], pd, px, torch.ones(1, 25, dtype=torch.bool), K=K[:1], T_color_depth=T_cd[:1]
            )
        torch.testing.assert_close(one.state[0], est.state[b], atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(one.covariance[0], est.covariance[b], atol=1e-15, rtol=1e-9)


def test_module_equals_function():
    X, K, T_cd = body(N=12)
    filt = FusionEKF(iterations=2, jacobian="analytic")  # fuse's default
    filt.reset(true_pose(0.0))
    mean, cov = filt.mean, filt.cov
    pd, px = measurements(true_pose(0.0), X, K, T_cd)
    var_xyz, var_pix = torch.full((2, 12), 1e-4, dtype=F64), torch.full((2, 12), 1.0, dtype=F64)
    valid = torch.ones(2, 12, dtype=torch.bool)
    ref = fuse(mean, cov, X, pd, px, valid, var_xyz, var_pix, K, T_cd, iterations=2)
    est = filt.update(X, pd, px, valid, var_xyz, var_pix, K, T_cd)
    assert torch.equal(est.state, ref.mean) and torch.equal(est.covariance, ref.cov)


def test_bad_input_raises():
    X, K, T_cd = body(N=5)
    filt = FusionEKF()
    with pytest.raises(ValueError, match="call reset"):
        filt.predict(torch.full((2,), DT, dtype=F64))
    with pytest.raises(ValueError, match="first reset"):
        filt.reset(true_pose(0.0), mask=torch.tensor([True, False]))
    filt.reset(true_pose(0.0))
    with pytest.raises(ValueError, match="dt must be"):
        filt.predict(torch.full((3,), DT, dtype=F64))
    with pytest.raises(ValueError, match="fuse: expected"):
        filt.update(X, X[:, :3], X[..., :2], torch.ones(2, 5, dtype=torch.bool), K=K)
    with pytest.raises(ValueError, match="K"):
        filt.update(X, X, X[..., :2], torch.ones(2, 5, dtype=torch.bool))
    with pytest.raises(ValueError, match="bad form"):
        FusionEKF(form="joseph")
