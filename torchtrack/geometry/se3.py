"""SE(3) as 4x4 homogeneous matrices: construction, inverse, exp/log, point transforms.

Transform names say both frames: ``T_cam_obj`` maps object coordinates into the camera,
``p_cam = R @ p_obj + t``. The tangent vector is ``xi = (v, omega)``: translation part first.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry.rotation import hat, so3_exp_and_left_jacobian, so3_left_jacobian, so3_log


def make_T(R: Tensor, t: Tensor) -> Tensor:
    """(..., 3, 3), (..., 3) -> (..., 4, 4)."""
    T = torch.zeros(*R.shape[:-2], 4, 4, dtype=R.dtype, device=R.device)
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1
    return T


def T_inv(T: Tensor) -> Tensor:
    """Inverse of rigid transforms (..., 4, 4), exact (no general matrix inverse)."""
    Rt = T[..., :3, :3].transpose(-1, -2)
    return make_T(Rt, -(Rt @ T[..., :3, 3:])[..., 0])


def rigid(T: Tensor) -> Tensor:
    """(..., 4, 4) ``T`` with its 3x3 block replaced by the nearest rotation (Frobenius norm: ``U V^T`` of its SVD,
    the sign of the last singular vector flipped where the determinant would be -1); the translation kept.

    :func:`T_inv` takes the transpose for the inverse, so a pose whose rotation block drifted from orthonormality
    (round-off fed back through products of poses and their "inverses") would amplify the drift at every round trip:
    a pose computed from other poses, rather than by the filter or an exponential, is projected back first.
    Transforms with a non-finite entry are returned as they are (the caller's finiteness check sees them). Not for
    autograd: the SVD's gradient is undefined at repeated singular values, i.e. at every rotation."""
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"rigid: transforms (..., 4, 4), got {tuple(T.shape)}")
    finite = torch.isfinite(T).flatten(-2).all(-1)
    M = torch.where(finite[..., None, None], T[..., :3, :3], torch.eye(3, dtype=T.dtype, device=T.device))
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(U @ Vh)
    U = torch.cat([U[..., :2], U[..., 2:] * d[..., None, None]], -1)
    return torch.where(finite[..., None, None], make_T(U @ Vh, T[..., :3, 3]), T)


def transform_points(T: Tensor, points: Tensor) -> Tensor:
    """Apply T (..., 4, 4) to points (..., N, 3) -> (..., N, 3)."""
    return points @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


_V_matrix = so3_left_jacobian  # SE(3)'s V is SO(3)'s left Jacobian

# se3_exp and se3_log are hand-written, not kornia.geometry.liegroup.Se3's exp/log (same values to 1e-16 in float64):
# Se3 wraps a quaternion and an object per call and measures 2-3x slower on 4x4 matrices, on the tracker's per-frame
# prediction and velocity.


def se3_exp(xi: Tensor) -> Tensor:
    """Twist (..., 6) = (v, omega) -> transform (..., 4, 4)."""
    v, omega = xi[..., :3], xi[..., 3:]
    R, V = so3_exp_and_left_jacobian(omega)
    return make_T(R, (V @ v[..., None])[..., 0])


def se3_log(T: Tensor) -> Tensor:
    """Transform (..., 4, 4) -> twist (..., 6) = (v, omega)."""
    omega = so3_log(T[..., :3, :3])
    v = torch.linalg.solve(_V_matrix(omega), T[..., :3, 3:])[..., 0]
    return torch.cat([v, omega], dim=-1)


def pose_from_euler(angles_t: Tensor) -> Tensor:
    """Paper's 6-vector (rho, theta, phi, tx, ty, tz) (..., 6) -> (..., 4, 4)."""
    from torchtrack.geometry.rotation import euler_to_matrix

    return make_T(euler_to_matrix(angles_t[..., :3]), angles_t[..., 3:])


def point_jacobian(p: Tensor) -> Tensor:
    """(..., 3, 6) derivative of ``exp(xi) p`` at xi = 0 for points p (..., 3), xi = (v, omega): ``[I, -[p]x]``."""
    eye = torch.eye(3, dtype=p.dtype, device=p.device).expand(*p.shape[:-1], 3, 3)
    return torch.cat([eye, -hat(p)], -1)
