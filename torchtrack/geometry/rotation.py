"""SO(3): exponential and logarithm, Euler angles, quaternions.

Conventions (used everywhere in torchtrack):

* Rotation matrices act on column vectors: ``p_target = R @ p_source``.
* Euler angles are the paper's ``(rho, theta, phi)`` about the x, y and z axes, composed as
  ``R = Rz(phi) @ Ry(theta) @ Rx(rho)`` (rotate about x first, all about fixed axes). Inverse
  singular at ``|theta| = pi/2``.
* Quaternions are ``quat_xyzw`` only at file IO (TUM order); ``matrix_to_quat_xyzw`` returns the
  representative with ``w >= 0``.

All functions take any leading batch shape ``(...)``.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
from torch import Tensor

_EPS = {torch.float32: 1e-4, torch.float64: 1e-8}
_WXYZ, _XYZW = [3, 0, 1, 2], [1, 2, 3, 0]  # kornia's quaternions are w, x, y, z; torchtrack's (TUM's) x, y, z, w


def hat(v: Tensor) -> Tensor:
    """Skew-symmetric matrix: (..., 3) -> (..., 3, 3) with ``hat(a) @ b == cross(a, b)``."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def vee(m: Tensor) -> Tensor:
    """Inverse of :func:`hat`: (..., 3, 3) -> (..., 3)."""
    return torch.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], dim=-1)


def _so3(omega: Tensor, exp: bool, jacobian: bool) -> tuple[Tensor | None, Tensor | None]:
    """Rodrigues' rotation ``I + a W + b W^2`` (``exp``) and the left Jacobian ``I + b W + c W^2`` (``jacobian``) at
    axis-angle ``omega`` (..., 3), ``W = hat(omega)``, t = |omega|, ``a = sin(t)/t``, ``b = (1 - cos t)/t^2``,
    ``c = (t - sin t)/t^3``, with Taylor series near 0; the terms both need are computed once."""
    theta2 = (omega * omega).sum(-1)[..., None, None]
    small = theta2 < _EPS.get(theta2.dtype, 1e-4)
    t2 = torch.where(small, torch.ones_like(theta2), theta2)
    t = t2.sqrt()
    sin = torch.sin(t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2**2 / 720, (1 - torch.cos(t)) / t2)
    W = hat(omega)
    WW = W @ W
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(W)
    R = J = None
    if exp:
        a = torch.where(small, 1 - theta2 / 6 + theta2**2 / 120, sin / t)
        R = eye + a * W + b * WW
    if jacobian:
        c = torch.where(small, 1 / 6 - theta2 / 120, (t - sin) / (t2 * t))
        J = eye + b * W + c * WW
    return R, J


# Hand-written, not kornia.geometry.conversions.axis_angle_to_rotation_matrix (same values to 1e-16 in float64,
# jacfwd works through both): kornia's is ~1.4x slower at B = 1 and 300, and this runs in the filter's every
# prediction, injection and (jacobian=forward) linearisation.
def so3_exp(omega: Tensor) -> Tensor:
    """Rodrigues' formula: axis-angle (..., 3) -> rotation (..., 3, 3)."""
    return _so3(omega, True, False)[0]


def so3_left_jacobian(omega: Tensor) -> Tensor:
    """Left Jacobian of SO(3), (..., 3) -> (..., 3, 3): ``Exp(omega + d) = Exp(J_l(omega) d) Exp(omega)`` to first
    order in d; ``J_l = I + (1 - cos t)/t^2 W + (t - sin t)/t^3 W^2`` with ``W = hat(omega)``, t = |omega| (Taylor
    near 0). It is also the V matrix of SE(3)'s exponential (Barfoot, "State Estimation for Robotics", eq. 7.77)."""
    return _so3(omega, False, True)[1]


def so3_exp_and_left_jacobian(omega: Tensor) -> tuple[Tensor, Tensor]:
    """``(so3_exp(omega), so3_left_jacobian(omega))``, sharing their terms."""
    return _so3(omega, True, True)


# Hand-written, not kornia's rotation_matrix_to_axis_angle (or liegroup.So3.log): those go through a quaternion and
# are 3-5x slower, and the tracker takes a log per frame (its velocity); ours is within 1e-9 rad of kornia's at pi.
def so3_log(R: Tensor) -> Tensor:
    """Rotation (..., 3, 3) -> axis-angle (..., 3), angle in [0, pi].

    Stable near 0 (first order) and near pi (axis from the symmetric part of R).
    """
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"so3_log expects (..., 3, 3), got {tuple(R.shape)}")
    tr = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    cos = ((tr - 1) / 2).clamp(-1.0, 1.0)
    theta = torch.acos(cos)
    w = vee(R - R.transpose(-1, -2)) / 2  # sin(theta) * axis
    sin = torch.sin(theta)
    small = theta < 1e-3
    scale = torch.where(small, 1 + theta**2 / 6, theta / torch.where(small, torch.ones_like(sin), sin))
    out = w * scale[..., None]
    # Near pi sin(theta) -> 0 and the antisymmetric part carries no axis: use R + I = 2 a a^T (1 - cos)
    near_pi = theta > torch.pi - 1e-2
    if near_pi.any():
        # symmetric part: (1 + cos) I + (1 - cos) a a^T; remove the isotropic term, keep a a^T
        eye = torch.eye(3, dtype=R.dtype, device=R.device)
        B = (R + R.transpose(-1, -2)) / 2 - cos[..., None, None] * eye
        diag = torch.diagonal(B, dim1=-2, dim2=-1).clamp_min(0)
        k = diag.argmax(-1, keepdim=True)
        col = torch.take_along_dim(B, k[..., None, :].expand(*B.shape[:-2], 3, 1), dim=-1)[..., 0]
        axis = col / col.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        # choose the sign consistent with the (small) antisymmetric part
        sgn = torch.where((axis * w).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(R.dtype)
        out = torch.where(near_pi[..., None], axis * sgn * theta[..., None], out)
    return out


def _axis_rot(angle: Tensor, axis: int) -> Tensor:
    c, s = torch.cos(angle), torch.sin(angle)
    o, i = torch.zeros_like(angle), torch.ones_like(angle)
    if axis == 0:
        m = [i, o, o, o, c, -s, o, s, c]
    elif axis == 1:
        m = [c, o, s, o, i, o, -s, o, c]
    else:
        m = [c, -s, o, s, c, o, o, o, i]
    return torch.stack(m, dim=-1).reshape(*angle.shape, 3, 3)


def euler_to_matrix(angles: Tensor) -> Tensor:
    """Paper's Euler angles (rho, theta, phi) about x, y, z: (..., 3) -> ``Rz @ Ry @ Rx``."""
    rx, ry, rz = angles.unbind(-1)
    return _axis_rot(rz, 2) @ _axis_rot(ry, 1) @ _axis_rot(rx, 0)


def matrix_to_euler(R: Tensor) -> Tensor:
    """Inverse of :func:`euler_to_matrix`: (..., 3, 3) -> (rho, theta, phi), theta in [-pi/2, pi/2]."""
    theta = torch.asin((-R[..., 2, 0]).clamp(-1.0, 1.0))
    rho = torch.atan2(R[..., 2, 1], R[..., 2, 2])
    phi = torch.atan2(R[..., 1, 0], R[..., 0, 0])
    return torch.stack([rho, theta, phi], dim=-1)


def quat_xyzw_to_matrix(quat_xyzw: Tensor) -> Tensor:
    """Unit quaternion (..., 4) in x, y, z, w order -> rotation (..., 3, 3). Normalises the input."""
    if quat_xyzw.shape[-1] != 4:
        raise ValueError(f"quaternion must be (..., 4) xyzw, got {tuple(quat_xyzw.shape)}")
    q = quat_xyzw / quat_xyzw.norm(dim=-1, keepdim=True)
    return quaternion_to_rotation_matrix(q[..., _WXYZ])


def matrix_to_quat_xyzw(R: Tensor) -> Tensor:
    """Rotation (..., 3, 3) -> unit quaternion (..., 4) xyzw with w >= 0 (Shepperd's method, kornia's)."""
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"matrix_to_quat_xyzw expects (..., 3, 3), got {tuple(R.shape)}")
    q = rotation_matrix_to_quaternion(R)[..., _XYZW]  # kornia's is w, x, y, z and not normalised
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., 3:4] < 0, -q, q)


def rotation_angle(R: Tensor) -> Tensor:
    """Geodesic angle of a rotation (..., 3, 3) -> (...) radians, stable near 0 and pi."""
    return so3_log(R).norm(dim=-1)
