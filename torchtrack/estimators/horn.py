"""Closed-form absolute orientation with unit quaternions (Horn 1987), batched, masked, weighted.

The paper's "quaternion-based 3D pose estimator" baseline [27]: given known 3D-3D correspondences,
``dst_i ≈ R @ src_i + t`` in the least-squares sense.

References:
    B. K. P. Horn, "Closed-form solution of absolute orientation using unit quaternions",
    J. Opt. Soc. Am. A 4(4), 1987.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix
from torch import Tensor

from torchtrack.estimators.base import (
    RigidFit,
    check_mask,
    check_points,
    check_T,
    masked_mean,
    not_collinear,
    zero_invalid,
)
from torchtrack.geometry import make_T


def horn_N_matrix(S: Tensor) -> Tensor:
    """Horn's symmetric 4x4 matrix N (Horn 1987, section 4) from S (B, 3, 3), S_ab = sum_i w_i src_a dst_b."""
    xx, xy, xz = S[..., 0, 0], S[..., 0, 1], S[..., 0, 2]
    yx, yy, yz = S[..., 1, 0], S[..., 1, 1], S[..., 1, 2]
    zx, zy, zz = S[..., 2, 0], S[..., 2, 1], S[..., 2, 2]
    rows = [
        xx + yy + zz, yz - zy, zx - xz, xy - yx,
        yz - zy, xx - yy - zz, xy + yx, zx + xz,
        zx - xz, xy + yx, -xx + yy - zz, yz + zy,
        xy - yx, zx + xz, yz + zy, -xx - yy + zz,
    ]  # fmt: skip
    return torch.stack(rows, -1).reshape(*S.shape[:-2], 4, 4)


def horn(src: Tensor, dst: Tensor, valid: Tensor, weights: Tensor | None = None) -> RigidFit:
    """Least-squares rigid transform from known correspondences: ``dst ≈ R @ src + t``.

    Args:
        src: (B, N, 3) source points (e.g. model points X_o).
        dst: (B, N, 3) corresponding destination points (e.g. measured X_d in the depth camera).
        valid: (B, N) bool; padded/invalid pairs contribute nothing.
        weights: optional (B, N) non-negative per-pair weights (minimises sum_i w_i |dst_i - R src_i - t|^2).

    Returns:
        RigidFit(T (B, 4, 4) = T_dst_src, valid (B,)): ``valid`` needs >= 3 pairs with positive weight
        whose source and destination points are not collinear; T is the identity elsewhere.
        The rotation is always proper (det +1), also for planar sets: the quaternion cannot reflect.
    """
    check_points("src", src, "horn")
    B, N, _ = src.shape
    check_points("dst", dst, "horn", B)
    if dst.shape[1] != N:
        raise ValueError(f"horn: src and dst need the same N (correspondences), got {N} and {dst.shape[1]}")
    check_mask("valid", valid, (B, N), "horn")
    w = valid.to(src.dtype)
    if weights is not None:
        if tuple(weights.shape) != (B, N):
            raise ValueError(f"horn: weights must be ({B}, {N}), got {tuple(weights.shape)}")
        weights = torch.where(valid, weights.to(src.dtype), 0.0)
        if (weights < 0).any() or not torch.isfinite(weights).all():
            raise ValueError("horn: weights must be finite and non-negative")
        w = weights
    return horn_weighted(zero_invalid(src, valid), zero_invalid(dst, valid), w)


def horn_weighted(src: Tensor, dst: Tensor, w: Tensor, check_collinear: bool = True) -> RigidFit:
    """:func:`horn` without input checks, for inner loops: finite src, dst (B, N, 3), weights w (B, N) >= 0.
    ``check_collinear=False`` only requires 3 positive weights (callers that checked the full sets once)."""
    mu_s, mu_d = masked_mean(src, w), masked_mean(dst, w)  # centroids: t = mu_d - R mu_s
    a, b = src - mu_s[:, None], dst - mu_d[:, None]
    S = (w[..., None] * a).transpose(-1, -2) @ b  # B,3,3, S_ij = sum_n w_n a_ni b_nj
    _, V = torch.linalg.eigh(horn_N_matrix(S))  # ascending eigenvalues
    R = quaternion_to_rotation_matrix(
        V[..., -1]
    )  # Horn's quaternion is w, x, y, z, as kornia's; eigenvector of the largest eigenvalue maximises sum w d.(q s q*)
    t = mu_d - (R @ mu_s[..., None])[..., 0]
    ok = (w > 0).sum(-1) >= 3
    if check_collinear:
        ok = ok & not_collinear(src, w) & not_collinear(dst, w)
    eye = torch.eye(4, dtype=src.dtype, device=src.device).expand(src.shape[0], 4, 4)
    return RigidFit(torch.where(ok[:, None, None], make_T(R, t), eye), ok)


class HornEstimator:
    """Quaternion baseline behind the common estimator interface (paper §IV, [27]).

    Uses the tracked correspondences directly; ``T_prev`` is kept for sequences with too few
    (or collinear) valid points. With ``use_weights`` the per-feature weights are used when given.
    """

    def __init__(self, use_weights: bool = True) -> None:
        self.use_weights = use_weights

    def __call__(
        self, points_obj: Tensor, points_d: Tensor, valid: Tensor, T_prev: Tensor, weights: Tensor | None = None
    ) -> Tensor:
        """points_obj (B, N, 3) model, points_d (B, N, 3) depth camera, valid (B, N), T_prev (B, 4, 4) -> T_cam_obj."""
        check_T("T_prev", T_prev, points_obj.shape[0], points_obj.dtype, "HornEstimator")
        est = horn(points_obj, points_d, valid, weights if self.use_weights else None)
        return torch.where(est.valid[:, None, None], est.T, T_prev)
