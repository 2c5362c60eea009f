"""Paper models: constant velocity (eqs. 3-4), measurement model (eqs. 6-7), Jacobians vs finite differences; the same
for the SE(3) error state (motion, measurement, reset)."""

import math

import pytest
import torch

from torchtrack.filter import ekf, error_state
from torchtrack.filter.fusion import linearize
from torchtrack.filter.models import (
    constant_velocity,
    euler_velocity,
    measure_analytic,
    measure_single,
    pose_to_state,
    state_to_pose,
)
from torchtrack.geometry import euler_to_matrix, intrinsics_matrix, make_T, project, so3_exp, so3_log, transform_points

F64 = torch.float64


def scene(B=2, N=6, seed=0, skew=0.0):
    g = torch.Generator().manual_seed(seed)
    x = torch.cat([0.4 * torch.randn(B, 3, generator=g, dtype=F64), 0.1 * torch.randn(B, 3, generator=g, dtype=F64), torch.randn(B, 6, generator=g, dtype=F64)], -1)  # fmt: skip
    x[:, 5] += 1.2
    X = 0.15 * torch.randn(B, N, 3, generator=g, dtype=F64)
    K = intrinsics_matrix(525.0, 530.0, 319.5, 239.5, dtype=F64).repeat(B, 1, 1)
    K[:, 0, 1] = skew
    T = make_T(
        so3_exp(0.05 * torch.randn(B, 3, generator=g, dtype=F64)), 0.03 * torch.randn(B, 3, generator=g, dtype=F64)
    )
    return x, X, K, T


def finite_difference_jacobian(x, X, K, T, eps=1e-6):
    """Central differences of the batched analytic value: (B, N, 5, 12)."""
    cols = []
    for k in range(12):
        d = torch.zeros_like(x)
        d[:, k] = eps
        cols.append((measure_analytic(x + d, X, K, T).h - measure_analytic(x - d, X, K, T).h) / (2 * eps))
    return torch.stack(cols, -1)


def test_constant_velocity_matrices():
    dt = torch.tensor([0.0, 0.033, 0.5], dtype=F64)
    F, Q = constant_velocity(dt, sigma_ang_acc=2.0, sigma_lin_acc=3.0)
    assert F.shape == (3, 12, 12) and Q.shape == (3, 12, 12)
    torch.testing.assert_close(F[0], torch.eye(12, dtype=F64))
    assert torch.equal(Q[0], torch.zeros(12, 12, dtype=F64))
    x = torch.arange(12, dtype=F64)
    torch.testing.assert_close(F[2] @ x, torch.cat([x[:6] + 0.5 * x[6:], x[6:]]))  # eq. (3)-(4)
    # piecewise-constant white acceleration per axis: sigma^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]
    t, s2 = 0.5, 9.0
    axis = Q[2][[4, 10]][:, [4, 10]]
    torch.testing.assert_close(axis, s2 * torch.tensor([[t**4 / 4, t**3 / 2], [t**3 / 2, t**2]], dtype=F64))
    assert Q[2, 0, 0] == 4.0 * t**4 / 4 and Q[2, 0, 1] == 0 and Q[2, 0, 4] == 0
    assert torch.linalg.eigvalsh(Q).min() > -1e-12


def test_constant_velocity_bad_input():
    with pytest.raises(ValueError, match="dt must be >= 0"):
        constant_velocity(torch.tensor([-0.1]), 1.0, 1.0)
    with pytest.raises(ValueError, match="dt must be"):
        constant_velocity(torch.tensor(0.1), 1.0, 1.0)


def test_measure_single_against_geometry():
    """Eqs. (6)-(7) against torchtrack.geometry's transform_points and project on the same input."""
    x, X, K, T = scene()
    h, _ = ekf.linearize(measure_single, x, (X,), (K, T))
    assert h.shape == (2, 6, 5)
    X_d = transform_points(state_to_pose(x), X)
    pix = project(K, transform_points(T, X_d))
    torch.testing.assert_close(h, torch.cat([X_d, pix], -1))
    torch.testing.assert_close(measure_analytic(x, X, K, T).h, h)


@pytest.mark.parametrize("skew", [0.0, 2.0])
def test_autograd_and_analytic_jacobians_equal_finite_differences(skew):
    x, X, K, T = scene(skew=skew)
    fd = finite_difference_jacobian(x, X, K, T)
    _, H_fwd = ekf.linearize(measure_single, x, (X,), (K, T), mode="forward")
    _, H_rev = ekf.linearize(measure_single, x, (X,), (K, T), mode="reverse")
    lin = measure_analytic(x, X, K, T)
    assert lin.H.shape == (2, 6, 5, 12)
    scale = fd.abs().amax((-1, -2), keepdim=True)  # pixel rows ~1e3, metric rows ~1
    for H in (H_fwd, H_rev, lin.H):
        assert ((H - fd).abs() / scale).max() < 1e-7
    torch.testing.assert_close(lin.H, H_fwd, atol=1e-10, rtol=1e-10)
    assert torch.equal(lin.H[..., 6:], torch.zeros_like(lin.H[..., 6:]))  # velocities do not enter h


@pytest.mark.equivalence
def test_analytic_batched_equals_looped():
    x, X, K, T = scene(B=3)
    lin = measure_analytic(x, X, K, T)
    for b in range(3):
        one = measure_analytic(x[b : b + 1], X[b : b + 1], K[b : b + 1], T[b : b + 1])
        torch.testing.assert_close(one.h[0], lin.h[b])
        torch.testing.assert_close(one.H[0], lin.H[b])


def test_pose_state_round_trip_and_euler_velocity():
    x, *_ = scene(B=4)
    T = state_to_pose(x)
    torch.testing.assert_close(T[:, :3, :3], euler_to_matrix(x[:, :3]))
    torch.testing.assert_close(state_to_pose(pose_to_state(T)), T)
    assert torch.equal(pose_to_state(T)[:, 6:], torch.zeros(4, 6, dtype=F64))
    dt = torch.full((4,), 0.1, dtype=F64)
    v = torch.tensor([0.3, -0.2, 0.5, 0.1, 0.0, -0.3], dtype=F64).expand(4, 6)
    x0 = pose_to_state(T)
    x1 = x0.clone()
    x1[:, :6] += v * dt[:, None]
    torch.testing.assert_close(euler_velocity(T, state_to_pose(x1), dt), v)
    # wrapping: phi from pi - 0.01 to -pi + 0.01 is +0.02 rad, not -2 pi + 0.02
    a = torch.tensor([[0.0, 0.0, math.pi - 0.01, 0, 0, 1]], dtype=F64)
    b = torch.tensor([[0.0, 0.0, -math.pi + 0.01, 0, 0, 1]], dtype=F64)
    w = euler_velocity(state_to_pose(a), state_to_pose(b), torch.tensor([1.0], dtype=F64))
    torch.testing.assert_close(w, torch.tensor([[0.0, 0.0, 0.02, 0, 0, 0]], dtype=F64))


# --- the SE(3) error state (torchtrack.filter.error_state) -----------------------------------------------------------


def error_scene(seed=0, dx_scale=0.0):
    """A nominal pose from :func:`scene`'s state and an error state dx (pose part ``dx_scale`` rad / m, random)."""
    x, X, K, T_cd = scene(seed=seed)
    g = torch.Generator().manual_seed(seed + 1)
    dx = torch.cat(
        [dx_scale * torch.randn(2, 6, generator=g, dtype=F64), torch.randn(2, 6, generator=g, dtype=F64)], -1
    )
    return dx, state_to_pose(x), X, K, T_cd


@pytest.mark.parametrize("dx_scale", [0.0, 0.3])
def test_error_state_jacobians_equal_finite_differences(dx_scale):
    """Analytic, forward and reverse Jacobians of eqs. (6)-(7) at ``T (+) dx`` with respect to dx, against central
    differences of h (float64); at dx = 0 (the EKF) and away from it (the iterated EKF's re-linearisation). h itself
    against geometry's transform_points and project at the injected pose."""
    dx, T, X, K, T_cd = error_scene(dx_scale=dx_scale)
    lin = error_state.measure_analytic(dx, T, X, K, T_cd)
    X_d = transform_points(error_state.inject(T, dx), X)
    torch.testing.assert_close(lin.h, torch.cat([X_d, project(K, transform_points(T_cd, X_d))], -1))
    cols = []
    for k in range(12):
        d = torch.zeros_like(dx)
        d[:, k] = 1e-6
        cols.append((error_state.measure_analytic(dx + d, T, X, K, T_cd).h - error_state.measure_analytic(dx - d, T, X, K, T_cd).h) / 2e-6)  # fmt: skip
    fd = torch.stack(cols, -1)
    scale = fd.abs().amax((-1, -2), keepdim=True)  # pixel rows ~1e3, metric rows ~1
    H_fwd = linearize(dx, X, K, T_cd, jacobian="forward", nominal=T)[1]
    H_rev = linearize(dx, X, K, T_cd, jacobian="reverse", nominal=T)[1]
    for H in (H_fwd, H_rev, lin.H):
        assert ((H - fd).abs() / scale).max() < 1e-7
    torch.testing.assert_close(lin.H, H_fwd, atol=1e-10, rtol=1e-10)
    assert torch.equal(lin.H[..., 6:], torch.zeros_like(lin.H[..., 6:]))  # velocities do not enter h


def propagate_error(dx, R, omega, v, dt):
    """The true motion's error after dt: true state (Exp(dtheta) R, t + dt, omega + domega, v + dv) and the nominal
    (R, t, omega, v) each moved by the constant-velocity motion, the new error read off them (so3_log)."""
    R_true = so3_exp((omega + dx[6:9]) * dt) @ so3_exp(dx[:3]) @ R
    R_nom = so3_exp(omega * dt) @ R
    return torch.cat([so3_log(R_true @ R_nom.T), dx[3:6] + dx[9:] * dt, dx[6:]])


def test_error_state_transition_is_the_motions_jacobian():
    """F of the error state against central differences of the exact error propagation (:func:`propagate_error`)
    at a fast turn (omega dt = 0.6 rad, where Exp(omega dt) and J_l differ from eqs. (3)-(4)'s I and dt I by ~0.2)."""
    g = torch.Generator().manual_seed(3)
    R, omega, v, dt = so3_exp(torch.randn(3, generator=g, dtype=F64)), torch.tensor([1.0, -2.0, 2.0], dtype=F64), torch.randn(3, generator=g, dtype=F64), 0.2  # fmt: skip
    F, Q = error_state.transition(torch.tensor([dt], dtype=F64), omega[None], 2.0, 3.0)
    fd = torch.stack([(propagate_error(d, R, omega, v, dt) - propagate_error(-d, R, omega, v, dt)) / 2e-6
                      for d in 1e-6 * torch.eye(12, dtype=F64)], -1)  # fmt: skip
    torch.testing.assert_close(F[0], fd, atol=1e-8, rtol=0)
    F_paper, Q_paper = constant_velocity(torch.tensor([dt], dtype=F64), 2.0, 3.0)
    assert torch.equal(Q, Q_paper) and float((F - F_paper).abs().max()) > 0.1


def test_error_state_reset_jacobian():
    """After injecting dtheta, the error eps left in the old coordinates becomes Log(Exp(dtheta + eps) Exp(-dtheta))
    in the new ones: its Jacobian (central differences) is the reset Jacobian's rotation block."""
    dtheta = torch.tensor([0.3, -0.2, 0.5], dtype=F64)
    G = error_state.reset_jacobian(torch.cat([dtheta, torch.zeros(9, dtype=F64)])[None])[0]

    def new_error(eps):
        return so3_log(so3_exp(dtheta + eps) @ so3_exp(dtheta).T)

    fd = torch.stack([(new_error(d) - new_error(-d)) / 2e-6 for d in 1e-6 * torch.eye(3, dtype=F64)], -1)
    torch.testing.assert_close(G[:3, :3], fd, atol=1e-8, rtol=0)
    torch.testing.assert_close(G[3:, 3:], torch.eye(9, dtype=F64))
    assert torch.equal(G[:3, 3:], torch.zeros(3, 9, dtype=F64))
    A = torch.randn(12, 12, generator=torch.Generator().manual_seed(0), dtype=F64)
    P, dx = (A @ A.T)[None], torch.cat([dtheta, torch.ones(9, dtype=F64)])[None]
    torch.testing.assert_close(error_state.reset_covariance(P, dx)[0], G @ P[0] @ G.T, atol=1e-12, rtol=1e-12)
