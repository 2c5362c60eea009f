"""Shared pieces of the 3D-3D pose estimators: the result type, input checks, masked reductions.

Conventions: column vectors, ``dst ≈ R @ src + t``; a returned ``T`` is ``T_dst_src`` (B, 4, 4).
Padded entries (``valid`` False) are zeroed on entry, so any garbage there (even NaN) changes nothing.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class RigidFit(NamedTuple):
    """Closed-form pose from correspondences.

    T: (B, 4, 4) ``T_dst_src`` (identity where not ``valid``).
    valid: (B,) bool, enough non-degenerate correspondences (>= 3, not collinear).
    """

    T: Tensor
    valid: Tensor


def check_points(name: str, points: Tensor, where: str, B: int | None = None) -> None:
    """Raise a one-line ValueError unless ``points`` is a floating (B, N, 3) tensor."""
    if points.ndim != 3 or points.shape[-1] != 3 or not points.is_floating_point():
        raise ValueError(f"{where}: {name} must be a float (B, N, 3) tensor, got {tuple(points.shape)} {points.dtype}")
    if B is not None and points.shape[0] != B:
        raise ValueError(f"{where}: {name} has batch {points.shape[0]}, expected {B}")


def check_mask(name: str, mask: Tensor, shape: tuple[int, int], where: str) -> None:
    """Raise unless ``mask`` is a bool tensor of the given (B, N) shape."""
    if mask.dtype != torch.bool or tuple(mask.shape) != tuple(shape):
        raise ValueError(f"{where}: {name} must be bool {tuple(shape)}, got {tuple(mask.shape)} {mask.dtype}")


def check_T(name: str, T: Tensor, B: int, dtype: torch.dtype, where: str) -> None:
    """Raise unless ``T`` is (B, 4, 4) of the points' dtype."""
    if tuple(T.shape) != (B, 4, 4) or T.dtype != dtype:
        raise ValueError(f"{where}: {name} must be ({B}, 4, 4) {dtype}, got {tuple(T.shape)} {T.dtype}")


def zero_invalid(points: Tensor, valid: Tensor) -> Tensor:
    """Points (B, N, 3) with padded entries set to 0 (so NaN/inf padding cannot leak into sums)."""
    return torch.where(valid[..., None], points, torch.zeros((), dtype=points.dtype, device=points.device))


def masked_mean(x: Tensor, w: Tensor) -> Tensor:
    """Weighted mean over dim -2: x (B, N, D), w (B, N) >= 0 -> (B, D); 0 where the weights sum to 0."""
    wsum = w.sum(-1, keepdim=True)
    return (w[..., None] * x).sum(-2) / torch.where(wsum > 0, wsum, torch.ones_like(wsum))


def not_collinear(points: Tensor, w: Tensor) -> Tensor:
    """(B, N, 3), weights (B, N) -> (B,) True where the weighted points span at least a plane.

    The second eigenvalue of the weighted scatter must exceed a dtype-relative fraction of the first
    (1e3 * eps: a 1 m long set needs about 1 cm of spread off its line in float32, 15 nm in float64).
    """
    c = points - masked_mean(points, w)[:, None]
    scatter = (w[..., None] * c).transpose(-1, -2) @ c  # B,3,3
    lam = torch.linalg.eigvalsh(scatter)  # ascending
    eps = torch.finfo(points.dtype).eps
    return (lam[:, 1] > 1e3 * eps * lam[:, 2]) & (lam[:, 2] > 0)


def augment_targets(y: Tensor, valid_y: Tensor) -> tuple[Tensor, Tensor]:
    """Target side of :func:`sq_dists`, reusable across iterations: (B, M, 3) -> ([-2y, 1, |y|^2]^T (B, 5, M),
    centre (B, 1, 3)), with |y|^2 = inf at padding. y must be finite (e.g. zeroed padding)."""
    c = y.mean(1, keepdim=True)
    y = y - c
    y2 = torch.where(valid_y, y.square().sum(-1), torch.tensor(torch.inf, dtype=y.dtype, device=y.device))
    return torch.cat([-2 * y, torch.ones_like(y2)[..., None], y2[..., None]], -1).transpose(-1, -2), c


def sq_dists_to(x: Tensor, valid_x: Tensor, targets: tuple[Tensor, Tensor], scale: Tensor | None = None) -> Tensor:
    """Squared distances from x (B, N, 3) to targets from :func:`augment_targets` -> (B, N, M); see :func:`sq_dists`."""
    y_aug_t, c = targets
    x = x - c
    x2 = torch.where(valid_x, x.square().sum(-1), torch.tensor(torch.inf, dtype=x.dtype, device=x.device))
    x_aug = torch.cat([x, x2[..., None], torch.ones_like(x2)[..., None]], -1)  # B,N,5
    if scale is not None:
        x_aug = x_aug * scale[:, None, None]
    return x_aug @ y_aug_t


def sq_dists(x: Tensor, y: Tensor, valid_x: Tensor, valid_y: Tensor, scale: Tensor | None = None) -> Tensor:
    """Pairwise squared distances (B, N, 3), (B, M, 3) -> (B, N, M), +inf where x or y is padded.

    One batched matmul of the augmented coordinates [x, |x|^2, 1] . [-2y, 1, |y|^2], the padding folded in
    as |x|^2 = inf (x, y must be finite, e.g. zeroed padding). Optional ``scale`` (B,) multiplies the result
    (CPD's -1/(2 sigma^2); then the padding is -inf). Both sets are first shifted by y's mean so that rounding
    scales with their extent, not their distance from the camera; callers needing exact values recompute them.
    """
    return sq_dists_to(x, valid_x, augment_targets(y, valid_y), scale)
