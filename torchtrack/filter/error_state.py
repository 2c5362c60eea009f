"""The default pose state: a local error state on SE(3) (error-state, or multiplicative, EKF).

The paper's state (:mod:`torchtrack.filter.models`, eq. (2)) holds Euler angles, singular at ``|theta| = pi/2``:
an object turning past 90 degrees about the camera's y axis loses one rotational degree of freedom and the filter
diverges (tests/test_backends.py: ``test_tracks_through_90_degrees_about_each_axis``). Here the filter keeps

* a nominal pose ``T = (R, t)`` (``FilterState.T_cam_obj``, (B, 4, 4)), outside the Gaussian;
* the error state ``dx = [dtheta, dt, omega, v]`` (S = 12) with ``R_true = Exp(dtheta) R`` (a rotation vector in the
  depth camera's axes, about the object's centre), ``t_true = t + dt``, and the velocities ``omega`` (rad/s, camera
  axes) and ``v`` (m/s); its mean is ``[0, 0, omega, v]`` between frames (the pose error is reset after injection);
* the covariance of ``dx`` (B, 12, 12), in the tangent space.

The retraction ``T (+) dx = (Exp(dtheta) R, t + dt)`` rotates about the object's centre, like the paper's
Euler state, and does not couple rotation with translation through the lever arm |t| as ``Exp(xi) T`` with the
SE(3) exponential would; it is a retraction on SE(3) all the same, chart-free and regular at every attitude.

Motion (the counterpart of eqs. (3)-(4)): ``R- = Exp(omega dt) R``, ``t- = t + v dt``, velocities constant; the error
propagates with ``dtheta- = Exp(omega dt) dtheta + J_l(omega dt) dt domega`` (exact to first order), the rest as in
eqs. (3)-(4), and the same piecewise-constant white-acceleration Q. Measurements: eqs. (6)-(7) at ``T (+) dx``.

References: Sola, "Quaternion kinematics for the error-state Kalman filter" (2017), §6-7 (injection, reset);
Barfoot, "State Estimation for Robotics" (2017), §7.1 (left Jacobian).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.filter.models import Linearization, MotionModel, _linearization, constant_velocity
from torchtrack.geometry import make_T, so3_exp, so3_exp_and_left_jacobian, so3_left_jacobian


def transition(dt: Tensor, omega: Tensor, sigma_ang_acc: float, sigma_lin_acc: float) -> MotionModel:
    """Error-state transition of the constant-velocity motion over ``dt`` (B,) s at angular velocity ``omega`` (B, 3).

    ``F`` is eqs. (3)-(4)'s with the rotation rows made exact for the left error: ``F[dtheta, dtheta] = Exp(omega dt)``,
    ``F[dtheta, omega] = J_l(omega dt) dt`` (the two reduce to I and dt I as omega dt -> 0); ``Q`` is
    :func:`~torchtrack.filter.models.constant_velocity`'s. Returns :class:`MotionModel`, F and Q (B, 12, 12).
    """
    F, Q = constant_velocity(dt, sigma_ang_acc, sigma_lin_acc)
    phi = omega * dt[:, None]  # B,3
    turn, J = so3_exp_and_left_jacobian(phi)
    rot = torch.cat([turn, F[:, :3, 3:6], J * dt[:, None, None], F[:, :3, 9:]], -1)
    return MotionModel(torch.cat([rot, F[:, 3:]], -2), Q)


def predict_nominal(T_cam_obj: Tensor, velocity: Tensor, dt: Tensor, turn: Tensor | None = None) -> Tensor:
    """Nominal pose after ``dt`` (B,) s at velocity ``[omega, v]`` (B, 6): ``(Exp(omega dt) R, t + v dt)`` (B, 4, 4).
    ``turn``: ``Exp(omega dt)`` (B, 3, 3) when the caller has it (:func:`transition`'s ``F[:, :3, :3]``)."""
    d = dt[:, None]
    turn = so3_exp(velocity[:, :3] * d) if turn is None else turn
    return make_T(turn @ T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3] + velocity[:, 3:] * d)


def inject(T_cam_obj: Tensor, dx: Tensor) -> Tensor:
    """The retraction ``T (+) dx = (Exp(dtheta) R, t + dt)``: nominal pose (B, 4, 4), error state (B, 12) -> (B, 4, 4)."""
    return make_T(so3_exp(dx[:, :3]) @ T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3] + dx[:, 3:6])


def reset_jacobian(dx: Tensor) -> Tensor:
    """(B, 12, 12) Jacobian of the error reset after injecting ``dx`` (B, 12): the new rotation error is
    ``J_l(dtheta) eps`` to first order (``Exp(dtheta + eps) = Exp(J_l eps) Exp(dtheta)``), the others are unchanged;
    the covariance becomes ``G P G^T`` (Sola 2017, §7.2, for the left error)."""
    B = dx.shape[0]
    G = torch.eye(12, dtype=dx.dtype, device=dx.device).repeat(B, 1, 1)
    top = torch.cat([so3_left_jacobian(dx[:, :3]), G[:, :3, 3:]], -1)
    return torch.cat([top, G[:, 3:]], -2)


def reset_covariance(cov: Tensor, dx: Tensor) -> Tensor:
    """``G P G^T`` (B, 12, 12) with G = :func:`reset_jacobian` of ``dx`` (B, 12), by its one non-identity block."""
    J = so3_left_jacobian(dx[:, :3])  # B,3,3
    rows = torch.cat([J @ cov[:, :3], cov[:, 3:]], -2)
    out = torch.cat([rows[..., :3] @ J.transpose(-1, -2), rows[..., 3:]], -1)
    return 0.5 * (out + out.transpose(-1, -2))


def measure_single(dx: Tensor, point_obj: Tensor, R: Tensor, t: Tensor, K: Tensor, T_color_depth: Tensor) -> Tensor:
    """Eqs. (6)-(7) of ONE feature at ``T (+) dx``: ``(12,), (3,), R (3, 3), t (3,), (3, 3), (4, 4) -> (5,)``; written
    for ``torch.func.vmap(jacfwd(...))`` (the autograd path and the analytic Jacobian's oracle)."""
    X_d = so3_exp(dx[:3]) @ (R @ point_obj) + t + dx[3:6]  # eq. (6)
    u = K @ (T_color_depth[:3, :3] @ X_d + T_color_depth[:3, 3])  # eq. (7)
    return torch.cat([X_d, u[:2] / u[2]])


def measure_analytic(
    dx: Tensor, T_cam_obj: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor
) -> Linearization:
    """Batched eqs. (6)-(7) at ``T (+) dx`` and the closed-form Jacobian with respect to dx.

    ``d(Exp(dtheta) y)/d(dtheta) = -hat(Exp(dtheta) y) J_l(dtheta)`` (exact, at any dtheta: the iterated EKF
    re-linearises away from 0); the pixel part as in :func:`~torchtrack.filter.models.measure_analytic`.

    Args:
        dx: (B, 12) error state; T_cam_obj: (B, 4, 4) nominal pose; points_obj: (B, N, 3); K: (B, 3, 3);
        T_color_depth: (B, 4, 4).

    Returns:
        :class:`~torchtrack.filter.models.Linearization`, h (B, N, 5), H (B, N, 5, 12); velocity columns zero.
    """
    R = so3_exp(dx[:, :3]) @ T_cam_obj[:, :3, :3]
    t = T_cam_obj[:, :3, 3] + dx[:, 3:6]
    return _linearization(R, t, so3_left_jacobian(dx[:, :3]), points_obj, K, T_color_depth)


def measure_at_nominal(T_cam_obj: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> Linearization:
    """:func:`measure_analytic` at ``dx = 0`` (the EKF's linearisation point between frames): ``J_l(0) = I``."""
    U = torch.eye(3, dtype=T_cam_obj.dtype, device=T_cam_obj.device).expand(T_cam_obj.shape[0], 3, 3)
    return _linearization(T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3], U, points_obj, K, T_color_depth)
