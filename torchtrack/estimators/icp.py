"""Point-to-point ICP (Besl & McKay 1992), batched over B sequences with padding masks.

Each iteration matches every valid source point to its nearest valid destination point (brute-force
squared distances over the padded sets, one batched matmul: fine for N ~ 300), drops matches farther
than ``max_corr_dist``, and solves the rigid transform in closed form with Horn's method. Sequences
stop independently when the relative change of the mean squared matching error falls below ``tol``.

References:
    P. J. Besl and N. D. McKay, "A method for registration of 3-D shapes", IEEE TPAMI 14(2), 1992.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.base import (
    augment_targets,
    check_mask,
    check_points,
    check_T,
    not_collinear,
    sq_dists_to,
    zero_invalid,
)
from torchtrack.estimators.horn import horn_weighted
from torchtrack.geometry import transform_points


class ICPResult(NamedTuple):
    """T (B, 4, 4) = T_dst_src; rmse (B,) of the inlier matches at T; iterations (B,) pose updates made;
    converged (B,) stopping criterion met before ``max_iters``; valid (B,) >= 3 non-collinear points on each side
    and >= 3 inlier matches at T (T = T_init where not valid)."""

    T: Tensor
    rmse: Tensor
    iterations: Tensor
    converged: Tensor
    valid: Tensor


def nearest_neighbours(
    src: Tensor,
    dst: Tensor,
    valid_src: Tensor,
    valid_dst: Tensor,
    max_corr_dist: float | None,
    targets: tuple[Tensor, Tensor] | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """For each src point (B, N, 3) its nearest valid dst point (B, M, 3).

    Returns (matched dst point (B, N, 3), squared distance (B, N), inlier (B, N) bool: valid src with a valid
    match within ``max_corr_dist``). ``targets``: ``augment_targets(dst, valid_dst)`` when already computed.
    """
    targets = augment_targets(dst, valid_dst) if targets is None else targets
    idx = sq_dists_to(src, valid_src, targets).argmin(-1)  # B,N; argmin over B,N,M
    matched = torch.take_along_dim(dst, idx[..., None], dim=1)  # B,N,3
    d2min = (src - matched).square().sum(-1)  # exact, not from the expanded form
    inlier = valid_src & valid_dst.any(-1, keepdim=True)
    if max_corr_dist is not None:
        inlier = inlier & (d2min <= max_corr_dist**2)
    return matched, torch.where(inlier, d2min, 0.0), inlier


def icp(
    src: Tensor,
    dst: Tensor,
    valid_src: Tensor,
    valid_dst: Tensor,
    T_init: Tensor,
    *,
    max_iters: int = 50,
    tol: float = 1.0e-6,
    max_corr_dist: float | None = None,
) -> ICPResult:
    """Align ``src`` (B, N, 3) onto ``dst`` (B, M, 3), unknown correspondences, starting at ``T_init`` (B, 4, 4).

    Iteration k (Besl-McKay): match ``T_k src`` to ``dst`` by nearest neighbours, mse_k = mean squared inlier
    distance; stop if |mse_{k-1} - mse_k| <= tol * mse_{k-1} (or mse_k is at rounding level), else
    ``T_{k+1} = horn(src, matched dst)``. Each sequence has its own convergence mask; finished ones are frozen.
    """
    check_points("src", src, "icp")
    B, N, _ = src.shape
    check_points("dst", dst, "icp", B)
    check_mask("valid_src", valid_src, (B, N), "icp")
    check_mask("valid_dst", valid_dst, (B, dst.shape[1]), "icp")
    check_T("T_init", T_init, B, src.dtype, "icp")
    if max_iters < 0 or tol < 0 or (max_corr_dist is not None and max_corr_dist <= 0):
        raise ValueError(
            f"icp: need max_iters >= 0, tol >= 0, max_corr_dist > 0 (got {max_iters}, {tol}, {max_corr_dist})"
        )
    src, dst = zero_invalid(src, valid_src), zero_invalid(dst, valid_dst)
    ok = (valid_src.sum(-1) >= 3) & (valid_dst.sum(-1) >= 3)
    ok = ok & not_collinear(src, valid_src.to(src.dtype)) & not_collinear(dst, valid_dst.to(src.dtype))
    # rounding-level floor on the mse, relative to the coordinates' magnitude
    n_dst = valid_dst.sum(-1).clamp_min(1)
    spread2 = (dst.square().sum(-1).sum(-1) / n_dst).clamp_min(torch.finfo(src.dtype).tiny)
    mse_floor = (1e3 * torch.finfo(src.dtype).eps) ** 2 * spread2

    targets = augment_targets(dst, valid_dst)  # dst is fixed: its side of the distance matmul once
    T = T_init.clone()
    active, converged = ok.clone(), torch.zeros_like(ok)
    iterations = torch.zeros(B, dtype=torch.long, device=src.device)
    mse_prev = torch.full((B,), torch.inf, dtype=src.dtype, device=src.device)
    mse, n_in = torch.zeros_like(mse_prev), torch.zeros_like(iterations)
    for k in range(max_iters + 1):
        ids = active.nonzero()[:, 0]  # work on the sequences still iterating only
        if ids.numel() == 0:
            break
        s, Tk = src[ids], T[ids]
        tg = (targets[0][ids], targets[1][ids])
        matched, d2, inlier = nearest_neighbours(
            transform_points(Tk, s), dst[ids], valid_src[ids], valid_dst[ids], max_corr_dist, tg
        )
        n_in[ids] = inlier.sum(-1)
        mse[ids] = mse_k = d2.sum(-1) / n_in[ids].clamp_min(1)
        prev = mse_prev[ids]
        done = (torch.isfinite(prev) & ((prev - mse_k).abs() <= tol * prev)) | (mse_k <= mse_floor[ids])
        converged[ids] = done
        if k == max_iters:
            break
        est = horn_weighted(s, matched, inlier.to(src.dtype), check_collinear=False)  # sets checked once above
        go = ~done & est.valid  # too few inlier matches: stop where we are
        T[ids] = torch.where(go[:, None, None], est.T, Tk)
        iterations[ids] += go.long()
        mse_prev[ids] = mse_k
        active[ids] = go
    valid = ok & (n_in >= 3)
    T = torch.where(valid[:, None, None], T, T_init)
    return ICPResult(T, mse.sqrt(), iterations, converged & valid, valid)


class ICPEstimator:
    """ICP baseline behind the common estimator interface (paper §IV, [31]).

    The model points and the measured points are handed over as two unordered sets (the known
    correspondences are not used) and aligned starting from ``T_prev``, as in the paper. Weights are
    ignored. Sequences where ICP is not valid keep ``T_prev``.
    """

    def __init__(
        self,
        max_iters: int = 50,
        tol: float = 1.0e-6,
        max_corr_dist: float | None = None,
    ) -> None:
        self.max_iters, self.tol, self.max_corr_dist = max_iters, tol, max_corr_dist

    def __call__(
        self, points_obj: Tensor, points_d: Tensor, valid: Tensor, T_prev: Tensor, weights: Tensor | None = None
    ) -> Tensor:
        """points_obj (B, N, 3) model, points_d (B, N, 3) depth camera, valid (B, N), T_prev (B, 4, 4) -> T_cam_obj."""
        res = icp(
            points_obj,
            points_d,
            valid,
            valid,
            T_prev,
            max_iters=self.max_iters,
            tol=self.tol,
            max_corr_dist=self.max_corr_dist,
        )
        return res.T
