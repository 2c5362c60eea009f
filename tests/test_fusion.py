"""The fusion EKF (FusionEKF's pure steps, EKFBackend the one stateful filter), both pose states: convergence on an
exact synthetic moving rigid body, masks, resets, forms, batching."""

import copy
import math

import pytest
import torch

from torchtrack.filter import FusionEKF, Variances, fuse
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.frame import Observation
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


STATES = ["se3", "euler"]


def observation(T, X, K, T_cd, valid=None):
    B, N = X.shape[:2]
    valid = torch.ones(B, N, dtype=torch.bool) if valid is None else valid
    return Observation(torch.full((B,), DT, dtype=F64), X, *measurements(T, X, K, T_cd), valid, K, T_cd)


def constant(B, N, var_pix=1.0, var_xyz=1e-4):
    return Variances(torch.full((B, N), var_pix, dtype=F64), torch.full((B, N), var_xyz, dtype=F64))


def ungated(ekf: FusionEKF) -> FusionEKF:
    """A copy of ``ekf`` without the innovation gate and the refit: the paper's update of every measurement."""
    out = copy.copy(ekf)
    out.gate = out.refit = None
    return out


def run(ekf, steps, X, K, T_cd, valid=None, start=None, var=(1.0, 1e-4)):
    """EKFBackend (no gate, no refit) over ``steps`` frames of the true motion; the last frame's result and the
    pose errors of every frame."""
    B, N = X.shape[:2]
    backend = EKFBackend(ungated(ekf))
    backend.reset(true_pose(0.0) if start is None else start, torch.ones(B, dtype=torch.bool))
    errs = []
    for k in range(1, steps + 1):
        T = true_pose(k * DT)
        out = backend.step(observation(T, X, K, T_cd, valid), constant(B, N, *var))
        errs.append(pose_errors(out.T_cam_obj, T))
    return out, errs


def one_update(ekf, state, X, pd, px, valid, var=(1.0, 1e-4), **kw):
    """Prediction-free update of ``state`` and its posterior."""
    B, N = valid.shape
    v = constant(B, N, *var)
    upd = ekf.updated(state, X, pd, px, kw.pop("valid_xyz", valid), valid, v.var_xyz, v.var_pix, kw.pop("K"),
                      kw.pop("T_cd"))  # fmt: skip
    return upd, ekf.injected(state, upd)


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize("jacobian", ["forward", "analytic"])
def test_converges_to_true_pose_on_noise_free_synthetic_motion(jacobian, state):
    """Start 2 cm / 2 deg off; noise-free 2D+3D measurements (small variances): < 1e-4 m and < 0.01 deg."""
    X, K, T_cd = body()
    start = true_pose(0.0) @ make_T(
        so3_exp(torch.tensor([0.0, 0.0, math.radians(2)], dtype=F64)), torch.tensor([0.02, 0.0, 0.0], dtype=F64)
    )
    ekf = FusionEKF(init_sigma_angle=0.05, init_sigma_trans=0.05, jacobian=jacobian, state=state)
    out, errs = run(ekf, 30, X, K, T_cd, start=start, var=(1e-4, 1e-8))
    t_err, r_err = errs[-1]
    assert (t_err < 1e-4).all() and (r_err < 0.01).all(), (t_err, r_err)
    assert out.updated.all() and out.used_xyz.sum(-1).tolist() == [60, 60]
    assert out.cov.shape == (2, 12, 12) and out.innovation.shape == (2, 60, 5)


@pytest.mark.parametrize("state", STATES)
def test_iterated_update_beats_single_step_on_large_initial_error(state):
    """A single EKF step from a 10 deg wrong pose keeps a linearisation error; 3 Gauss-Newton steps remove it."""
    X, K, T_cd = body()
    start = true_pose(DT) @ make_T(
        so3_exp(torch.tensor([0.0, math.radians(10), 0.0], dtype=F64)), torch.zeros(3, dtype=F64)
    )
    errors = {}
    for it in (1, 3):
        ekf = FusionEKF(init_sigma_angle=0.5, init_sigma_trans=0.1, iterations=it, state=state)
        valid = torch.ones(2, 60, dtype=torch.bool)
        _, post = one_update(ekf, ekf.initial_state(start), X, *measurements(true_pose(DT), X, K, T_cd), valid,
                             var=(1e-4, 1e-8), K=K, T_cd=T_cd)  # fmt: skip
        errors[it] = pose_errors(post.T_cam_obj, true_pose(DT))[1]
    assert (errors[3] < 1e-3).all() and (errors[1] > 10 * errors[3]).all(), errors


@pytest.mark.parametrize("state", STATES)
def test_forms_and_jacobians_agree(state):
    X, K, T_cd = body(N=20)
    outs = []
    for form, jac in (
        ("information", "forward"),
        ("gain", "forward"),
        ("information", "analytic"),
        ("information", "reverse"),
    ):
        outs.append(run(FusionEKF(form=form, jacobian=jac, state=state), 3, X, K, T_cd)[0])
    for o in outs[1:]:
        torch.testing.assert_close(o.T_cam_obj, outs[0].T_cam_obj, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(o.mean, outs[0].mean, atol=1e-9, rtol=1e-9)
        torch.testing.assert_close(o.cov, outs[0].cov, atol=1e-12, rtol=1e-7)


@pytest.mark.parametrize("state", STATES)
def test_sequence_without_features_keeps_prediction_and_masked_garbage_is_ignored(state):
    X, K, T_cd = body(N=30)
    ekf = FusionEKF(state=state)
    pred = ekf.predicted(ekf.initial_state(true_pose(0.0), velocity=torch.ones(2, 6, dtype=F64) * 0.1),
                         torch.full((2,), DT, dtype=F64))  # fmt: skip
    pd, px = measurements(true_pose(DT), X, K, T_cd)
    valid = torch.ones(2, 30, dtype=torch.bool)
    valid[1] = False
    garbage = lambda t: torch.where(valid[..., None], t, torch.full_like(t, float("nan")))  # noqa: E731
    upd, post = one_update(ekf, pred, garbage(X), garbage(pd), garbage(px), valid, K=K, T_cd=T_cd)
    assert upd.num_valid.tolist() == [150, 0]
    torch.testing.assert_close(post.T_cam_obj[1], pred.T_cam_obj[1], atol=0, rtol=0)
    assert all(torch.isfinite(t).all() for t in post)
    ref = ekf.predicted(ekf.initial_state(true_pose(0.0)[:1], velocity=torch.ones(1, 6, dtype=F64) * 0.1),
                        torch.full((1,), DT, dtype=F64))  # fmt: skip
    _, ref_post = one_update(ekf, ref, X[:1], pd[:1], px[:1], valid[:1], K=K[:1], T_cd=T_cd[:1])
    for a, b in zip(post, ref_post, strict=True):
        torch.testing.assert_close(a[:1], b, atol=1e-12, rtol=1e-12)


def test_valid_xyz_masks_only_the_3d_part():
    X, K, T_cd = body(N=10)
    ekf = FusionEKF()
    pd, px = measurements(true_pose(DT), X, K, T_cd)
    valid_xyz = torch.ones(2, 10, dtype=torch.bool)
    valid_xyz[:, ::2] = False
    pd = torch.where(valid_xyz[..., None], pd, torch.full_like(pd, float("nan")))
    upd, post = one_update(ekf, ekf.initial_state(true_pose(0.0)), X, pd, px, torch.ones(2, 10, dtype=torch.bool),
                           valid_xyz=valid_xyz, K=K, T_cd=T_cd)  # fmt: skip
    assert all(torch.isfinite(t).all() for t in post)
    assert (upd.innovation[:, ::2, :3] == 0).all() and (upd.innovation[:, ::2, 3:] != 0).any()


@pytest.mark.parametrize("state", STATES)
def test_reset_and_set_pose_with_mask_touch_only_masked_sequences(state):
    X, K, T_cd = body(N=10)
    backend = EKFBackend(FusionEKF(init_sigma_angle=0.01, state=state, gate=None, refit=None))
    backend.reset(true_pose(0.0), torch.ones(2, dtype=torch.bool))
    backend.step(observation(true_pose(DT), X, K, T_cd), constant(2, 10))
    before = backend.state
    new = torch.eye(4, dtype=F64).expand(2, 4, 4).clone()
    new[:, 2, 3] = 0.7
    backend.reset(new, torch.tensor([False, True]))
    after = backend.state
    assert all(torch.equal(a[0], b[0]) for a, b in zip(after, before, strict=True))
    torch.testing.assert_close(after.T_cam_obj[1], new[1])
    expected_mean = pose_to_state(new[1:])[0] if state == "euler" else torch.zeros(12, dtype=F64)
    torch.testing.assert_close(after.mean[1], expected_mean)
    torch.testing.assert_close(after.cov[1], torch.diag(backend.ekf.init_var))
    backend.set_pose(true_pose(0.0), torch.tensor([True, False]))  # the pose moves; velocity and covariance stay
    torch.testing.assert_close(backend.state.T_cam_obj[0], true_pose(0.0)[0], atol=1e-12, rtol=0)
    assert torch.equal(backend.state.cov[0], after.cov[0]) and torch.equal(backend.state.mean[0, 6:], after.mean[0, 6:])
    assert all(torch.equal(a[1], b[1]) for a, b in zip(backend.state, after, strict=True))


@pytest.mark.equivalence
@pytest.mark.parametrize("state", STATES)
def test_batched_equals_looped(state):
    X, K, T_cd = body(N=25)
    both, _ = run(FusionEKF(state=state), 4, X, K, T_cd)
    for b in range(2):
        one, _ = run_one(FusionEKF(state=state), 4, X[b : b + 1], K[:1], T_cd[:1], b)
        torch.testing.assert_close(one.T_cam_obj[0], both.T_cam_obj[b], atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(one.mean[0], both.mean[b], atol=1e-12, rtol=1e-10)
        torch.testing.assert_close(one.cov[0], both.cov[b], atol=1e-15, rtol=1e-9)


def run_one(ekf, steps, X, K, T_cd, b):
    backend = EKFBackend(ungated(ekf))
    backend.reset(true_pose(0.0)[b : b + 1], torch.ones(1, dtype=torch.bool))
    for k in range(1, steps + 1):
        out = backend.step(observation(true_pose(k * DT)[b : b + 1], X, K, T_cd), constant(1, X.shape[1]))
    return out, None


@pytest.mark.parametrize("state", STATES)
def test_filter_step_equals_function(state):
    X, K, T_cd = body(N=12)
    ekf = FusionEKF(iterations=2, jacobian="analytic", state=state)
    prior = ekf.initial_state(true_pose(0.0))
    pd, px = measurements(true_pose(0.0), X, K, T_cd)
    var_xyz, var_pix = torch.full((2, 12), 1e-4, dtype=F64), torch.full((2, 12), 1.0, dtype=F64)
    valid = torch.ones(2, 12, dtype=torch.bool)
    nominal = None if state == "euler" else prior.T_cam_obj
    ref = fuse(prior.mean, prior.cov, X, pd, px, valid, var_xyz, var_pix, K, T_cd, iterations=2, nominal=nominal)
    est = ekf.updated(prior, X, pd, px, valid, valid, var_xyz, var_pix, K, T_cd)
    assert torch.equal(est.mean, ref.mean) and torch.equal(est.cov, ref.cov)


def test_bad_input_raises():
    X, K, T_cd = body(N=5)
    ekf = FusionEKF()
    backend = EKFBackend(ekf)
    with pytest.raises(ValueError, match="call reset"):
        backend.step(observation(true_pose(DT), X, K, T_cd), constant(2, 5))
    with pytest.raises(ValueError, match="first reset"):
        backend.reset(true_pose(0.0), torch.tensor([True, False]))
    with pytest.raises(ValueError, match="dt must be"):
        ekf.predicted(ekf.initial_state(true_pose(0.0)), torch.full((3,), DT, dtype=F64))
    with pytest.raises(ValueError, match="fuse: expected"):
        v = constant(2, 5)
        ekf.updated(ekf.initial_state(true_pose(0.0)), X, X[:, :3], X[..., :2], v.var_xyz > 0, v.var_xyz > 0,
                    v.var_xyz, v.var_pix, K, T_cd)  # fmt: skip
    with pytest.raises(ValueError, match="bad form"):
        FusionEKF(form="joseph")
    with pytest.raises(ValueError, match="state must be"):
        FusionEKF(state="quaternion")


@pytest.mark.parametrize(("overrides", "state"), [((), "se3"), (("+experiment=paper",), "euler")])
def test_the_paper_selects_the_euler_state(overrides, state):
    """The default filter is the SE(3) error state; ``+experiment=paper`` composes the paper's Euler state (eq. 2)."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from torchtrack.config import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides))
    assert cfg.filter.state == state and instantiate(cfg.filter).state == state
