"""Online noise scale: how large the measurement noise really is, per sequence and per block (pixel, 3D).

The weighting (eqs. 11-14, fixed, or learned) gives each feature's variances ``R0``; they are right only up to a
factor per block, since the nominal ``sigma2_pix``, ``sigma2_xyz`` were set by hand for another sensor. A Kalman
filter, unlike Gauss-Newton, is not invariant to a global scale of R (the prior is weighed against it), so the
factor must come from the data: ``R = k_b R0`` with ``k = (k_pix, k_xyz)`` estimated online from the residuals.

Derivation (residual-based covariance matching, i.e. variance-component estimation on the EKF update). At one frame,
with innovation ``v = z - h(x-)``, gain ``K`` and update ``dx = K v``, the post-fit residual is
``r = v - H dx = (I - H K) v``. For a consistent filter ``E[r r^T] = R - H P+ H^T`` (Mohamed & Schwarz 1999, eq. 22),
so per measured component ``i``::

    E[r_i^2] = R_i rho_i,    rho_i = 1 - (H P+ H^T)_ii / R_i  in [0, 1]

``rho_i`` is the component's redundancy number (Förstner 1979): the share of it not used up by fitting the pose. With
``R_i = k_b R0_i`` for the components of block b::

    E[ sum_{i in b} r_i^2 / R0_i ] = k_b sum_{i in b} rho_i   =>   k_b = sum r_i^2 / R0_i  /  sum rho_i.

This is one step of Förstner's iterated variance-component estimation (Koch 1999, §3.6): unbiased at its fixed
point (the filter run with the scale it estimates), and nearly so away from it, because the update removes only
the few directions the 6-dof pose can explain from the m residuals (the bias is O(6/m)). Frames are combined by
sums with a forgetting factor lambda (Sage & Husa's fading memory), not by averaging per-frame ratios::

    D_t = lambda D_{t-1} + sum rho_i,   k_t = clamp((lambda D_{t-1} k_{t-1} + sum r_i^2 / R0_i) / D_t, k_min, k_max)

so a frame counts by its redundancy: a frame with few features, or whose measurements the posterior already knows
(``H P H^T`` comparable to R, rho_i -> 0), barely moves the estimate instead of adding a noisy ratio. k_0 = 1 (the
weighting's own R) with no weight (D_0 = 0): the first frame with measurements sets it.

Why residuals, not innovations. Innovation covariance matching (Mehra 1970; Sage-Husa) uses
``E[v v^T] = H P- H^T + R``, i.e. ``k_b = sum (v_i^2 - (H P- H^T)_ii) / sum R0_i``. That is unbiased only if the
prior covariance P- is, i.e. if the process noise Q is right; and where ``H P- H^T`` dominates R (pixels: a 1 mrad
prediction error is 0.5 px at f = 525) it is the difference of two large numbers and mostly measures the error of
the constant-velocity Q, not of R. The residuals see the prior only through the 6 pose directions the update fits.

Robustness: the statistic runs on the measurements the update used (after the gate and the refit); each feature's
normalised squared residual per block, ``sum r^2 / R`` over its 3 (or 2) components under the R the update used,
is winsorised at the chi-square ``clip`` quantile (3 or 2 dof) -- a bounded influence for outliers that passed the
gate, < 0.1 % bias on Gaussian data at 0.999 -- and the scale is clamped to ``[min_scale, max_scale]``. The
statistic is computed without gradient (a detached, non-differentiated statistic): training through the back end
sees ``R = k R0`` with k a constant.

References: R. K. Mehra, "On the identification of variances and adaptive Kalman filtering", IEEE TAC 15(2), 1970;
A. P. Sage, G. W. Husa, "Adaptive filtering with unknown prior statistics", JACC 1969; A. H. Mohamed, K. P. Schwarz,
"Adaptive Kalman filtering for INS/GPS", J. Geodesy 73, 1999; W. Förstner, "Ein Verfahren zur Schätzung von Varianz-
und Kovarianzkomponenten", AVN 1979; K.-R. Koch, "Parameter Estimation and Hypothesis Testing in Linear Models",
Springer 1999.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.filter.ekf import chi2_quantile
from torchtrack.filter.weighting import Variances

PIX, XYZ = 0, 1  # the column of each block in the (B, 2) scales: the order of Variances (var_pix, var_xyz)


class ScaleState(NamedTuple):
    """The running estimate. scale: (B, 2) factors k [pix, xyz] of the weighting's R; dof: (B, 2) the
    forgetting-weighted redundancy (effective number of residuals) behind them."""

    scale: Tensor
    dof: Tensor


class ScaleStats(NamedTuple):
    """One frame's residual statistics per block, (B, 2) [pix, xyz]: ``ssr = sum r_i^2 / R0_i`` (winsorised) and
    ``redundancy = sum rho_i`` over the components the update used."""

    ssr: Tensor
    redundancy: Tensor


def scaled(var: Variances, scale: Tensor) -> Variances:
    """The variances ``k R0`` of each block: ``var`` (B, N) each times ``scale`` (B, 2) [pix, xyz], detached."""
    k = scale.detach()
    return Variances(var.var_pix * k[:, PIX, None], var.var_xyz * k[:, XYZ, None])


def residual_statistics(
    residual: Tensor, post_hph: Tensor, var5: Tensor, used: Tensor, scale: Tensor, clip: tuple[float, float] | None
) -> ScaleStats:
    """This frame's :class:`ScaleStats` (see the module docstring), without gradient.

    Args:
        residual: (B, N, 5) post-fit residuals ``z - h(x-) - H (x+ - x-)``, 3D (m) then pixel (px).
        post_hph: (B, N, 5) ``diag(H P+ H^T)``.
        var5: (B, N, 5) the R the update used (``k R0``); used: (B, N, 5) bool, the components it used.
        scale: (B, 2) the k [pix, xyz] the update used.
        clip: per-feature caps of ``sum r^2 / R`` for the 3D block and the pixel block, or None.
    """
    with torch.no_grad():
        R = torch.where(used, var5, torch.ones_like(var5))
        d = torch.where(used, residual.square() / R, torch.zeros_like(R))  # B,N,5
        rho = torch.where(used, (1.0 - post_hph / R).clamp(0.0, 1.0), torch.zeros_like(R))
        d_xyz, d_pix = d[..., :3].sum(-1), d[..., 3:].sum(-1)  # B,N per feature and block
        if clip is not None:
            d_xyz, d_pix = d_xyz.clamp_max(clip[0]), d_pix.clamp_max(clip[1])
        k = scale.to(d.dtype)
        ssr = torch.stack([d_pix.sum(-1), d_xyz.sum(-1)], -1) * k  # r^2 / R0 = k r^2 / R
        redundancy = torch.stack([rho[..., 3:].sum((-1, -2)), rho[..., :3].sum((-1, -2))], -1)
    return ScaleStats(ssr, redundancy)


class NoiseScale:
    """The online noise scale's parameters and its pure running update (the back end owns the state).

    Args:
        forgetting: lambda in (0, 1]: the weight of the past per frame (an effective window of 1 / (1 - lambda)
            frames; 1 = never forget).
        min_scale, max_scale: bounds of k (0 < min_scale <= 1 <= max_scale).
        clip: chi-square quantile in (0, 1) at which each feature's normalised squared residual is winsorised, or
            None (no winsorising).
    """

    def __init__(
        self, forgetting: float = 0.98, min_scale: float = 0.01, max_scale: float = 100.0, clip: float | None = 0.999
    ) -> None:
        if not 0.0 < forgetting <= 1.0 or not 0.0 < min_scale <= 1.0 <= max_scale:
            raise ValueError(
                f"NoiseScale: need 0 < forgetting <= 1 and 0 < min_scale <= 1 <= max_scale, got {forgetting}, "
                f"{min_scale}, {max_scale}"
            )
        if clip is not None and not 0.0 < clip < 1.0:
            raise ValueError(f"NoiseScale: clip is a probability in (0, 1) or None, got {clip}")
        self.forgetting, self.min_scale, self.max_scale, self.clip = forgetting, min_scale, max_scale, clip

    def initial(self, B: int, dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> ScaleState:
        """k = 1 (the weighting's R as it is) with no weight, for B sequences."""
        return ScaleState(torch.ones(B, 2, dtype=dtype, device=device), torch.zeros(B, 2, dtype=dtype, device=device))

    def caps(self) -> tuple[float, float] | None:
        """(3D, pixel) caps of the per-feature normalised squared residuals: chi-square quantiles, 3 and 2 dof."""
        return None if self.clip is None else (chi2_quantile(self.clip, 3), chi2_quantile(self.clip, 2))

    def updated(self, state: ScaleState, stats: ScaleStats) -> ScaleState:
        """The running estimate after one frame's statistics (module docstring); unchanged where the frame had none."""
        with torch.no_grad():
            past = self.forgetting * state.dof
            dof = past + stats.redundancy
            k = (past * state.scale + stats.ssr) / dof.clamp_min(1e-12)
            k = torch.where(dof > 0, k, state.scale).clamp(self.min_scale, self.max_scale)
        return ScaleState(k, dof)
