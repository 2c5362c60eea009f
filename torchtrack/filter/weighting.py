"""Measurement weighting, eqs. (11)–(14): per-feature quality in, per-feature noise variances out.

The interface is deliberately small so that a learned module can replace the paper's formulas:
``weighting(WeightingInputs(...)) -> Variances(var_pix, var_xyz)``, all (B, N). Sums and N run over the
VALID features of each sequence only; invalid features get the nominal variances (finite, harmless —
the EKF gives them zero information anyway).

References: Gedik & Alatan (2013), §III-D; Khoshelham & Oude Elberink, "Accuracy and resolution of
Kinect depth data" (Sensors 2012) for the optional depth-dependent variance.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor


class WeightingInputs(NamedTuple):
    """Per-feature quality cues of one frame.

    Attributes:
        d_tim: (B, N) template-inverse-matching error in pixels (eq. (10)).
        depth: (B, N) measured depth z of each feature in metres (depth camera).
        points_d: (B, N, 3) measured 3D points X_d in the depth camera, metres.
        valid: (B, N) bool.
        focal: (B,) depth-camera focal length in pixels (f of eq. (12)).
        cues: (B, N, C) per-feature cues in :data:`torchtrack.filter.cues.CUE_NAMES` order, for learned
            weightings; the tracker fills it only when the weighting (or an observer of its step) has
            ``needs_cues = True``.
    """

    d_tim: Tensor
    depth: Tensor
    points_d: Tensor
    valid: Tensor
    focal: Tensor
    cues: Tensor | None = None


class Variances(NamedTuple):
    """Per-feature measurement noise variances. var_pix: (B, N) px^2; var_xyz: (B, N) m^2."""

    var_pix: Tensor
    var_xyz: Tensor


def _check(inp: WeightingInputs) -> None:
    B, N = inp.valid.shape
    ok = inp.d_tim.shape == (B, N) and inp.depth.shape == (B, N) and inp.points_d.shape == (B, N, 3)
    if not ok or inp.focal.shape != (B,) or inp.valid.dtype != torch.bool:
        raise ValueError(
            "weighting: expected d_tim, depth (B, N), points_d (B, N, 3), valid (B, N) bool, focal (B,); got "
            f"{tuple(inp.d_tim.shape)}, {tuple(inp.depth.shape)}, {tuple(inp.points_d.shape)}, "
            f"{tuple(inp.valid.shape)} {inp.valid.dtype}, {tuple(inp.focal.shape)}"
        )


def _normalise_mean(w: Tensor, valid: Tensor) -> Tensor:
    """``N w_i / sum_j w_j`` over valid features (mean 1 over them); 1 where invalid or no valid feature."""
    w = torch.where(valid, w, torch.zeros_like(w))
    n = valid.sum(-1, keepdim=True).to(w.dtype)
    total = w.sum(-1, keepdim=True)
    ok = valid & (total > 0)
    return torch.where(ok, n * w / torch.where(total > 0, total, torch.ones_like(total)), torch.ones_like(w))


def paper_variances(
    inp: WeightingInputs,
    sigma2_pix: float,
    sigma2_xyz: float,
    d_tim_floor: float = 0.01,
    dist_floor: float = 0.001,
    depth_var_exponent: float = 4.0,
    depth_ref: float = 1.0,
) -> Variances:
    """Eqs. (11)–(14), batched over B sequences with masks.

    Args:
        inp: :class:`WeightingInputs`.
        sigma2_pix: nominal pixel variance (px^2); sigma2_xyz: nominal 3D variance (m^2).
        d_tim_floor: each d_TIM is floored at this many pixels; a perfectly re-matched feature
            (d_TIM = 0) would otherwise get zero variance, i.e. infinite weight (and all-zero d_TIM 0/0).
        dist_floor: floor (m) on ``||X_d,i - centroid||`` in eq. (13) for a feature at the centroid.
        depth_var_exponent: ``e > 0`` (default 4, an improvement) multiplies var_xyz by ``(z / depth_ref)^e``
            after eq. (14) — structured-light depth noise grows with depth (std ~ z^2 for the Kinect, i.e.
            ``e = 4``); the mean is then not preserved. 0 is the paper.
        depth_ref: reference depth (m) at which the nominal sigma2_xyz holds for that option.

    Returns:
        :class:`Variances`; on valid features ``mean(var_pix) = sigma2_pix`` and (with exponent 0)
        ``mean(var_xyz) = sigma2_xyz``.
    """
    _check(inp)
    valid = inp.valid
    one = torch.ones_like(inp.d_tim)
    d = torch.where(valid, inp.d_tim, one).clamp_min(d_tim_floor)  # garbage in padded slots stays out
    depth = torch.where(valid, inp.depth, one)
    var_pix = _normalise_mean(d, valid) * sigma2_pix  # eq. (11)
    w1 = depth / inp.focal[:, None] * d  # eq. (12)
    w1n = _normalise_mean(w1, valid)  # normalised to mean 1 instead of sum 1: same ratios in eq. (14)
    n = valid.sum(-1, keepdim=True).clamp_min(1).to(inp.points_d.dtype)
    pts = torch.where(valid[..., None], inp.points_d, torch.zeros_like(inp.points_d))
    centroid = pts.sum(-2, keepdim=True) / n[..., None]
    dist = (pts - centroid).norm(dim=-1).clamp_min(dist_floor)
    w2n = _normalise_mean(1.0 / dist, valid)  # eq. (13)
    var_xyz = _normalise_mean(w1n + w2n, valid) * sigma2_xyz  # eq. (14)
    if depth_var_exponent != 0.0:
        z = torch.where(valid, depth, torch.full_like(depth, depth_ref)).clamp_min(1e-3)
        var_xyz = var_xyz * (z / depth_ref) ** depth_var_exponent
    return Variances(var_pix, var_xyz)


def pixel_only_variances(var: Variances, valid: Tensor, valid_xyz: Tensor) -> Variances:
    """``var`` (the weighting's, over the features with depth ``valid_xyz`` (B, N)) with the features tracked without
    depth (``valid`` and not ``valid_xyz``) at their sequence's mean pixel variance over the features with depth (eq.
    11 normalises over those: the nominal ``sigma2_pix``; 1 px^2 where none has depth)."""
    only = valid & ~valid_xyz
    if not bool(only.any()):
        return var
    w = valid_xyz.to(var.var_pix.dtype)
    mean = (var.var_pix * w).sum(-1, keepdim=True) / w.sum(-1, keepdim=True).clamp_min(1)
    mean = torch.where(valid_xyz.any(-1, keepdim=True), mean, torch.ones_like(mean))
    return Variances(torch.where(only, mean.expand_as(var.var_pix), var.var_pix), var.var_xyz)


class PaperWeighting:
    """Eqs. (11)–(14) as a module: ``PaperWeighting(sigma2_pix, sigma2_xyz)(inputs) -> Variances``.

    See :func:`paper_variances` for the arguments.
    """

    def __init__(
        self,
        sigma2_pix: float = 1.0,
        sigma2_xyz: float = 4.0e-6,
        d_tim_floor: float = 0.01,
        dist_floor: float = 0.001,
        depth_var_exponent: float = 4.0,
        depth_ref: float = 1.0,
    ) -> None:
        if sigma2_pix <= 0 or sigma2_xyz <= 0 or d_tim_floor <= 0 or dist_floor <= 0 or depth_ref <= 0:
            raise ValueError("PaperWeighting: variances, floors and depth_ref must be > 0")
        self.sigma2_pix, self.sigma2_xyz = sigma2_pix, sigma2_xyz
        self.d_tim_floor, self.dist_floor = d_tim_floor, dist_floor
        self.depth_var_exponent, self.depth_ref = depth_var_exponent, depth_ref

    def __call__(self, inputs: WeightingInputs) -> Variances:
        return paper_variances(
            inputs,
            self.sigma2_pix,
            self.sigma2_xyz,
            self.d_tim_floor,
            self.dist_floor,
            self.depth_var_exponent,
            self.depth_ref,
        )


class FixedWeighting:
    """Constant variances for every feature: the paper's EKF-3 ablation (no weighting)."""

    def __init__(self, sigma2_pix: float = 1.0, sigma2_xyz: float = 1.0e-4) -> None:
        if sigma2_pix <= 0 or sigma2_xyz <= 0:
            raise ValueError("FixedWeighting: variances must be > 0")
        self.sigma2_pix, self.sigma2_xyz = sigma2_pix, sigma2_xyz

    def __call__(self, inputs: WeightingInputs) -> Variances:
        _check(inputs)
        like = inputs.d_tim
        return Variances(torch.full_like(like, self.sigma2_pix), torch.full_like(like, self.sigma2_xyz))
