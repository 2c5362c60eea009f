"""The paper's motion and measurement models for the 12-state EKF (Gedik & Alatan 2013, §III-A).

State ``x`` (S = 12), as in the paper::

    x = [rho, theta, phi, tx, ty, tz, d(rho)/dt, d(theta)/dt, d(phi)/dt, d(tx)/dt, d(ty)/dt, d(tz)/dt]

``(rho, theta, phi)`` are the Euler angles of ``R_do`` (object -> depth camera) in the
:func:`torchtrack.geometry.euler_to_matrix` convention (``R = Rz(phi) @ Ry(theta) @ Rx(rho)``), ``t_do``
the translation in metres; velocities are per second (real time steps, not per frame). The object frame is centred
at the model's centroid with axes of the model camera, so angles start at 0 after each model (re-)selection. The
parameterisation is singular at ``|theta| = pi/2``: the default filter state is therefore the SE(3) error state of
:mod:`torchtrack.filter.error_state` (which reuses eqs. (3)-(7) from here); ``filter.state=euler`` selects this one.

Measurement of one feature (M = 5): ``[X_d (3), x_pix (2)]`` — the point in the depth camera (eq. 6)
and its pixel in the colour image (eq. 7).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.geometry import (
    T_inv,
    backproject,
    euler_to_matrix,
    hat,
    make_T,
    matrix_to_euler,
    sample_depth_bilinear,
    transform_points,
)

STATE_SIZE = 12
MEAS_SIZE = 5


class MotionModel(NamedTuple):
    """Linear transition ``x_t = F x_{t-1} + noise`` with noise covariance ``Q``.

    Attributes:
        F: (B, 12, 12) transition matrix.
        Q: (B, 12, 12) process-noise covariance (PSD).
    """

    F: Tensor
    Q: Tensor


def constant_velocity(dt: Tensor, sigma_ang_acc: float, sigma_lin_acc: float) -> MotionModel:
    """Constant-velocity model, eqs. (3)–(4), with real time steps.

    ``pose_t = pose_{t-1} + v_{t-1} dt`` (3), ``v_t = v_{t-1}`` (4), driven by white acceleration that is
    constant within a step (Bar-Shalom's piecewise-constant white-acceleration model): per axis with
    acceleration std ``sigma``, ``Q = sigma^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]`` on (pose, velocity).

    Args:
        dt: (B,) time steps in seconds (>= 0).
        sigma_ang_acc: std of the Euler-angle accelerations, rad/s^2.
        sigma_lin_acc: std of the linear accelerations, m/s^2.

    Returns:
        :class:`MotionModel` with F, Q of shape (B, 12, 12) in dt's dtype.
    """
    if dt.dim() != 1:
        raise ValueError(f"constant_velocity: dt must be (B,), got {tuple(dt.shape)}")
    if bool((dt < 0).any()):
        raise ValueError("constant_velocity: dt must be >= 0 (timestamps must increase)")
    B = dt.shape[0]
    eye6 = torch.eye(6, dtype=dt.dtype, device=dt.device)
    d = dt[:, None, None]
    F = torch.eye(STATE_SIZE, dtype=dt.dtype, device=dt.device).repeat(B, 1, 1)
    F[:, :6, 6:] = d * eye6  # eq. (3)
    sig2 = torch.tensor([sigma_ang_acc**2] * 3 + [sigma_lin_acc**2] * 3, dtype=dt.dtype, device=dt.device)
    s = torch.diag_embed(sig2.expand(B, 6))  # B,6,6
    Q = torch.cat([torch.cat([s * d**4 / 4, s * d**3 / 2], -1), torch.cat([s * d**3 / 2, s * d**2], -1)], -2)  # B,12,12
    return MotionModel(F, Q)


def measure_single(x: Tensor, point_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> Tensor:
    """Measurement model of ONE feature, eqs. (6)–(7): ``(12,), (3,), (3,3), (4,4) -> (5,)``.

    ``X_d = R_do X_o + t_do`` (6), ``alpha [x, 1] = K (R_dv X_d + t_dv)`` (7) with ``(R_dv, t_dv)`` from
    ``T_color_depth`` (depth -> colour). Written for one feature so that ``torch.func.vmap(jacfwd(...))``
    gives per-feature Jacobians (STYLE.md #4); kept to few ops because functorch's per-op cost dominates.
    """
    X_d = euler_to_matrix(x[:3]) @ point_obj + x[3:6]  # eq. (6)
    u = K @ (T_color_depth[:3, :3] @ X_d + T_color_depth[:3, 3])  # eq. (7), u = alpha [x, y, 1]
    return torch.cat([X_d, u[:2] / u[2]])


class Linearization(NamedTuple):
    """Measurement prediction and its Jacobian at a state.

    Attributes:
        h: (B, N, M) predicted measurements.
        H: (B, N, M, S) Jacobian dh/dx per feature.
    """

    h: Tensor
    H: Tensor


def measure_analytic(x: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> Linearization:
    """Batched eqs. (6)–(7) with the closed-form Jacobian (fast path and test oracle).

    With ``R = Rz Ry Rx``: ``dR/dphi = hat(e_z) R``, ``dR/dtheta = hat(Rz e_y) R``, ``dR/drho = hat(Rz Ry e_x) R``,
    so ``dX_d/d(angle_k) = u_k x (R X_o)``. Pixel part: ``u = K X_c``, ``pix = u[:2] / u[2]``,
    ``dpix/dX_c = (K[:2] - pix K[2]) / u[2]``, ``dX_c/dX_d = R_dv``.

    Args:
        x: (B, 12) state; points_obj: (B, N, 3) model points; K: (B, 3, 3) colour intrinsics;
        T_color_depth: (B, 4, 4) depth -> colour.

    Returns:
        :class:`Linearization` with h (B, N, 5), H (B, N, 5, 12); velocity columns are zero.
    """
    B = points_obj.shape[0]
    theta, phi = x[:, 1], x[:, 2]
    c_t, s_t, c_p, s_p = torch.cos(theta), torch.sin(theta), torch.cos(phi), torch.sin(phi)
    zero, one = torch.zeros_like(phi), torch.ones_like(phi)
    U = torch.stack([c_p * c_t, -s_p, zero, s_p * c_t, c_p, zero, -s_t, zero, one], -1).reshape(B, 3, 3)
    return _linearization(euler_to_matrix(x[:, :3]), x[:, 3:6], U, points_obj, K, T_color_depth)


def _linearization(R: Tensor, t: Tensor, U: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor):
    """h and H of eqs. (6)-(7) at ``X_d = R X_o + t`` (R (B, 3, 3), t (B, 3)), where the rotation's derivative with
    respect to the state's 3 angle coordinates is ``dX_d/da = -hat(R X_o) U`` (U (B, 3, 3)) and ``dX_d/dt = I``."""
    B, N, _ = points_obj.shape
    RX, X_d, A, u, pix = _project(R, t, points_obj, K, T_color_depth)
    dXd_da = -hat(RX) @ U[:, None]  # B,N,3,3: columns u_k x RX
    dpix_dXd = (A[:, None, :2, :] - pix[..., None] * A[:, None, 2:, :]) / u[..., 2:, None]  # B,N,2,3
    dpix_da = dpix_dXd @ dXd_da  # B,N,2,3
    pose_cols = torch.cat(
        [
            torch.cat([dXd_da, dpix_da], -2),
            torch.cat([torch.eye(3, dtype=R.dtype, device=R.device).expand(B, N, 3, 3), dpix_dXd], -2),
        ],
        -1,
    )  # B,N,5,6
    H = torch.cat([pose_cols, torch.zeros_like(pose_cols)], -1)  # velocities do not enter h
    return Linearization(torch.cat([X_d, pix], -1), H)


def _project(R: Tensor, t: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor):
    """Eqs. (6)-(7), batched, for ``R_do`` (B, 3, 3), ``t_do`` (B, 3): (R X_o (B,N,3), X_d (B,N,3), A = K R_dv (B,3,3),
    u = alpha [x, 1] (B,N,3), pixels (B,N,2))."""
    RX = points_obj @ R.transpose(-1, -2)  # B,N,3
    X_d = RX + t[:, None]  # eq. (6)
    A = K @ T_color_depth[:, :3, :3]  # B,3,3: u = A X_d + b
    u = X_d @ A.transpose(-1, -2) + (K @ T_color_depth[:, :3, 3:])[:, None, :, 0]  # B,N,3
    return RX, X_d, A, u, u[..., :2] / u[..., 2:]  # eq. (7)


def measure(x: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> Tensor:
    """Batched eqs. (6)-(7) without the Jacobian: h (B, N, 5) = [X_d, pixel] for states x (B, 12) and model points
    (B, N, 3); the same numbers as :func:`measure_analytic`'s h (same operations)."""
    return measure_pose(state_to_pose(x), points_obj, K, T_color_depth)


def measure_pose(T_cam_obj: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> Tensor:
    """Eqs. (6)-(7) at a pose ``T_cam_obj`` (B, 4, 4), whatever the state's parametrisation: h (B, N, 5)."""
    _, X_d, _, _, pix = _project(T_cam_obj[:, :3, :3], T_cam_obj[:, :3, 3], points_obj, K, T_color_depth)
    return torch.cat([X_d, pix], -1)


def measure_points(depth: Tensor, K: Tensor, T_color_depth: Tensor, pixels: Tensor) -> tuple[Tensor, Tensor]:
    """The 3D measurements X_d of eq. (6), read from depth at colour pixels (the prediction is :func:`measure`).

    Args:
        depth: (B, 1, H, W) depth registered to the colour camera (metres, 0 = none); K (B, 3, 3) colour intrinsics;
            T_color_depth (B, 4, 4) the depth-to-colour extrinsic (R_dv, t_dv); pixels (B, N, 2) colour pixels.

    Returns:
        (points (B, N, 3) in the depth camera, has_depth (B, N) bool). The depth is interpolated bilinearly on
        continuous surfaces and read at the nearest pixel across depth edges; the point is back-projected through
        the sub-pixel colour position and moved into the depth camera.
    """
    z = sample_depth_bilinear(depth, pixels)
    pts_color = backproject(K, pixels, z)
    pts_depth = transform_points(T_inv(T_color_depth), pts_color)
    return pts_depth, z > 0


def state_to_pose(x: Tensor) -> Tensor:
    """State (..., 12) -> ``T_cam_obj`` (..., 4, 4) (cam = depth camera)."""
    return make_T(euler_to_matrix(x[..., :3]), x[..., 3:6])


def pose_to_state(T_cam_obj: Tensor, velocity: Tensor | None = None) -> Tensor:
    """``T_cam_obj`` (..., 4, 4) and optional velocity (..., 6) -> state (..., 12); zero velocity by default."""
    pose = torch.cat([matrix_to_euler(T_cam_obj[..., :3, :3]), T_cam_obj[..., :3, 3]], -1)
    vel = torch.zeros_like(pose) if velocity is None else velocity
    return torch.cat([pose, vel], -1)


def euler_velocity(T_prev: Tensor, T_curr: Tensor, dt: Tensor) -> Tensor:
    """Finite-difference state velocity (B, 6) between two poses (B, 4, 4) ``dt`` (B,) seconds apart.

    Angle differences are wrapped to (-pi, pi]. Useful to carry motion over a model re-selection.
    """
    d = pose_to_state(T_curr)[..., :6] - pose_to_state(T_prev)[..., :6]
    ang = torch.remainder(d[..., :3] + torch.pi, 2 * torch.pi) - torch.pi
    return torch.cat([ang, d[..., 3:]], -1) / dt.clamp_min(1e-9)[..., None]
