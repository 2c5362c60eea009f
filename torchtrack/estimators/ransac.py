"""RANSAC on 3D-3D correspondences with Horn's closed form as the minimal solver, batched over B and hypotheses.

Every hypothesis is a weighted Horn fit (:func:`torchtrack.estimators.horn.horn_weighted`) whose weights are one
on three sampled correspondences and zero elsewhere, so all B x H hypotheses are one batched call. The best
hypothesis (most inliers) is refitted on its inliers once (a local optimisation step), and the inliers are
re-counted under the refit.

References:
    M. A. Fischler, R. C. Bolles, "Random Sample Consensus", CACM 1981.
    B. K. P. Horn, "Closed-form solution of absolute orientation using unit quaternions", JOSA A 1987.
    O. Chum, J. Matas, J. Kittler, "Locally Optimized RANSAC", DAGM 2003.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.horn import horn_weighted
from torchtrack.geometry import transform_points


class RansacFit(NamedTuple):
    """T (B, 4, 4) = T_dst_src refitted on the inliers; inliers (B, N) bool; valid (B,) a fit with >= 3 inliers."""

    T: Tensor
    inliers: Tensor
    valid: Tensor


def residuals(T: Tensor, src: Tensor, dst: Tensor) -> Tensor:
    """(..., N) ``|dst - T src|`` for T (..., 4, 4), src and dst (..., N, 3)."""
    return torch.linalg.vector_norm(dst - transform_points(T, src), dim=-1)


def ransac_rigid(
    src: Tensor, dst: Tensor, valid: Tensor, threshold: Tensor | float, *, hypotheses: int = 64, seed: int = 0
) -> RansacFit:
    """Robust ``dst ≈ R src + t`` from correspondences with outliers.

    Args:
        src, dst: (B, N, 3) corresponding points (e.g. model points X_o and measured X_d).
        valid: (B, N) bool; invalid pairs are never sampled nor counted.
        threshold: inlier distance in the units of the points, a float or (B, N) per pair (e.g. growing with depth).
        hypotheses: minimal samples per sequence; seed: of the sampling (deterministic).

    Returns:
        :class:`RansacFit`; where fewer than 3 pairs are valid, ``valid`` is False, T the identity and ``inliers``
        the input ``valid``.
    """
    if src.shape != dst.shape or src.dim() != 3 or src.shape[-1] != 3 or valid.shape != src.shape[:2]:
        raise ValueError(
            f"ransac_rigid: src, dst (B, N, 3) and valid (B, N), got {src.shape}, {dst.shape}, {valid.shape}"
        )
    B, N, _ = src.shape
    thr = torch.as_tensor(threshold, dtype=src.dtype).expand(B, N)
    g = torch.Generator().manual_seed(seed)
    keys = torch.rand(B, hypotheses, N, generator=g, dtype=src.dtype).masked_fill(~valid[:, None], -1.0)
    picks = keys.topk(min(3, N), dim=-1).indices  # B,H,3: three distinct pairs, valid ones first
    w = torch.zeros(B, hypotheses, N, dtype=src.dtype).scatter_(-1, picks, 1.0) * valid[:, None]
    fit = horn_weighted(_tile(src, hypotheses), _tile(dst, hypotheses), w.reshape(B * hypotheses, N))
    T = fit.T.reshape(B, hypotheses, 4, 4)
    inl = valid[:, None] & (residuals(T, src[:, None], dst[:, None]) <= thr[:, None])  # B,H,N
    score = torch.where(fit.valid.reshape(B, hypotheses), inl.sum(-1), -1)
    best = score.argmax(1)
    rows = torch.arange(B)
    inliers = inl[rows, best]
    refit = horn_weighted(src, dst, inliers.to(src.dtype))  # local optimisation on the consensus set
    T_best = torch.where(refit.valid[:, None, None], refit.T, T[rows, best])
    inliers = valid & (residuals(T_best, src, dst) <= thr)
    ok = (score[rows, best] >= 3) & (inliers.sum(1) >= 3)
    eye = torch.eye(4, dtype=src.dtype).expand(B, 4, 4)
    return RansacFit(torch.where(ok[:, None, None], T_best, eye), torch.where(ok[:, None], inliers, valid), ok)


def _tile(x: Tensor, h: int) -> Tensor:
    """(B, N, 3) -> (B * h, N, 3), each sequence repeated h times."""
    return x[:, None].expand(x.shape[0], h, *x.shape[1:]).reshape(-1, *x.shape[1:])
