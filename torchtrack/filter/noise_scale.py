"""Online noise scale: how large the measurement noise really is, per sequence and per block (pixel, 3D).

The weighting (eqs. 11-14, fixed, or learned) gives each feature's variances ``R0``; they are right only up to a
factor per block, since the nominal ``sigma2_pix``, ``sigma2_xyz`` were set by hand for another sensor. A Kalman
filter, unlike Gauss-Newton, is not invariant to a global scale of R (the prior is weighed against it), so the
factor must come from the data: ``R = k_b R0`` with ``k = (k_pix, k_xyz)`` estimated online from the residuals.

Derivation (residual-based covariance matching, i.e. variance-component estimation on the EKF update). At one frame,
with innovation ``v = z - h(x-)``, gain ``K`` and update ``dx = K v``, the residual of a measurement the update used
is ``r = v - H dx = (I - H K) v``; for a consistent filter ``E[r r^T] = R - H P+ H^T`` (Mohamed & Schwarz 1999). The
residual of a measured component the update did NOT use (the gate or the refit dropped it) is a prediction from the
others, independent of them: ``E[r r^T] = R + H P+ H^T``. Per component i::

    E[r_i^2] = R_i rho_i,    rho_i = 1 - (H P+ H^T)_ii / R_i  (used),   1 + (H P+ H^T)_ii / R_i  (not used)

``rho_i`` is the component's redundancy number (Förstner 1979; in [0, 1] when used: the share of it not spent on
fitting the pose). So for each feature f and block b (dof = 3 components for the 3D point, 2 for the pixel), under
the R the update used, ``R = k' R0``::

    q_f = dof * sum_i r_i^2 / R_i  /  sum_i rho_i   ~   (k_b / k'_b) chi2(dof)

and the frame's estimate is ``k_b = k'_b mean_f(q_f) / dof``, the mean weighted by each feature's redundancy
``sum_i rho_i`` (features the posterior already knows, ``H P H^T`` comparable to R, count little). This is one step
of Förstner's iterated variance-component estimation (Koch 1999, §3.6): unbiased at its fixed point (the filter run
with the scale it estimates), and nearly so away from it, since the update removes from the m residuals only the
few directions the 6-dof pose explains (a bias of O(6/m)). Frames are combined with a forgetting factor lambda
(Sage & Husa's fading memory), each weighted by its redundancy ``W_t`` (the sum of its features')::

    D_t = lambda D_{t-1} + W_t,   k_t = clamp((lambda D_{t-1} k_{t-1} + W_t k_b(t)) / D_t, k_min, k_max)

k_0 = 1 (the weighting's own R) with no weight (D_0 = 0): the first frame with measurements sets it.

Every measured feature counts, not only those the gate kept. A statistic over the kept ones feeds back on itself:
the gate under ``k R0`` keeps the features that fit, their residuals make k smaller, the smaller k makes the gate
keep fewer. On real data (heavy-tailed errors) that collapsed: on the rendered ViSP castle k fell to 0.04 and the
gate then rejected 96-100 % of the features (22 frames flagged lost), where with every measured feature k ends at
1.7 (pixel) and 4.1 (3D) and nothing is lost. Instead the statistic is made robust by winsorising: each ``q_f``
is capped at the chi-square ``clip`` quantile c (dof) of the scale being estimated, and the mean divided by
``E[min(chi2(dof), c)]`` instead of dof, so that it stays unbiased on Gaussian data. An outlier then weighs at
most ``c / E[min(.)]`` inliers, and a small fraction e of gross outliers biases k up by about
``e (c - E[min]) / (E[min] - (1 - clip) c)``: 1.6 e for the 3D block, 2.1 e for the pixel one at the default clip
0.9 (on the oracle, 5 % outliers: +12 %, +15 %; the median would give ~1.6 e, at about half the Gaussian
efficiency; clip 0.95 gives 2.0 e, 2.6 e). Since the cap is relative to the scale itself, the frame's estimate is
the fixed point ``s = k / k' = mean(min(q_f / s, c)) / E[min(chi2(dof), c)]`` (Huber's proposal 2 for a scale),
solved in closed form (the right side is piecewise linear in s: :func:`winsorised_scale`); so one frame finds a k
however far off the one it was run with.

Why residuals, not innovations. Innovation covariance matching (Mehra 1970; Sage-Husa) uses
``E[v v^T] = H P- H^T + R``, i.e. ``k_b = sum (v_i^2 - (H P- H^T)_ii) / sum R0_i``. That is unbiased only if the
prior covariance P- is, i.e. if the process noise Q is right; where ``H P- H^T`` dominates R (pixels: a 1 mrad
prediction error is 0.5 px at f = 525) it is the difference of two large numbers and mostly measures the error of
the constant-velocity Q, not of R. On the synthetic oracle (whose true acceleration is 0, well inside Q) it gave
k_pix = 0.33 for a true 1. The residuals see the prior only through the 6 pose directions the update fits.

The scale is a detached statistic (no gradient): training through the back end sees ``R = k R0`` with k a constant.

References: R. K. Mehra, "On the identification of variances and adaptive Kalman filtering", IEEE TAC 15(2), 1970;
A. P. Sage, G. W. Husa, "Adaptive filtering with unknown prior statistics", JACC 1969; A. H. Mohamed, K. P. Schwarz,
"Adaptive Kalman filtering for INS/GPS", J. Geodesy 73, 1999; W. Förstner, "Ein Verfahren zur Schätzung von Varianz-
und Kovarianzkomponenten", AVN 1979; K.-R. Koch, "Parameter Estimation and Hypothesis Testing in Linear Models",
Springer 1999; P. J. Huber, "Robust Statistics", Wiley 1981 (winsorised scale estimates).
"""

from __future__ import annotations

import functools
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
    """One frame's estimate per block, (B, 2) [pix, xyz]: ``scale`` the frame's k, ``weight`` its redundancy W_t
    (0 where the frame had no measurement of the block; ``scale`` is then the k the update used)."""

    scale: Tensor
    weight: Tensor


def scaled(var: Variances, scale: Tensor) -> Variances:
    """The variances ``k R0`` of each block: ``var`` (B, N) each times ``scale`` (B, 2) [pix, xyz], detached."""
    k = scale.detach()
    return Variances(var.var_pix * k[:, PIX, None], var.var_xyz * k[:, XYZ, None])


def residual_statistics(
    residual: Tensor, post_hph: Tensor, var5: Tensor, valid: Tensor, used: Tensor, scale: Tensor, clip: float | None
) -> ScaleStats:
    """This frame's :class:`ScaleStats` (see the module docstring), without gradient.

    Args:
        residual: (B, N, 5) residuals ``z - h(x-) - H (x+ - x-)`` of the measured features, 3D (m) then pixel (px).
        post_hph: (B, N, 5) ``diag(H P+ H^T)``.
        var5: (B, N, 5) the R the update used (``k R0``); valid, used: (B, N, 5) bool, the components measured and
            the components the update used.
        scale: (B, 2) the k [pix, xyz] the update used.
        clip: chi-square quantile at which each feature's normalised residual is winsorised, or None.
    """
    with torch.no_grad():
        R = torch.where(valid, var5, torch.ones_like(var5))
        d = torch.where(valid, residual.square() / R, torch.zeros_like(R))  # B,N,5
        rho = torch.where(used, 1.0 - post_hph / R, 1.0 + post_hph / R).clamp_min(0.0)  # fitted / predicted
        rho = torch.where(valid, rho, torch.zeros_like(rho))
        blocks = [
            _block(d[..., 3:], rho[..., 3:], valid[..., 3:], clip),
            _block(d[..., :3], rho[..., :3], valid[..., :3], clip),
        ]
        k = torch.stack([b[0] for b in blocks], -1)
        weight = torch.stack([b[1] for b in blocks], -1)
    return ScaleStats(torch.where(weight > 0, k * scale.to(k.dtype), scale.to(k.dtype)), weight)


def _block(d: Tensor, rho: Tensor, valid: Tensor, clip: float | None) -> tuple[Tensor, Tensor]:
    """One block's (B,) ratio ``s = k / k'`` of the true to the used scale and its (B,) weight (the sum of the
    features' redundancies), from the (B, N, dof) normalised squared residuals ``d = r^2 / R``, redundancies ``rho``
    and ``valid`` of its components: the redundancy-weighted mean of the q_f (module docstring), winsorised at c
    relative to s itself, ``s = mean(min(q_f / s, c)) / E[min(chi2(dof), c)]``."""
    dof = d.shape[-1]
    d_f, rho_f = d.sum(-1), rho.sum(-1)  # B,N per feature
    ok = valid.all(-1) & (rho_f > 1e-9)
    w = torch.where(ok, rho_f, torch.zeros_like(rho_f))
    weight = w.sum(-1)
    q = torch.where(ok, d_f * dof / rho_f.clamp_min(1e-9), torch.zeros_like(d_f))  # ~ (k / k') chi2(dof)
    if clip is None:
        return (w * q).sum(-1) / weight.clamp_min(1e-12) / dof, weight
    c = chi2_quantile(clip, dof)
    return winsorised_scale(q, w, c, winsorised_chi2_mean(dof, c)), weight


def winsorised_scale(q: Tensor, w: Tensor, c: float, expected: float) -> Tensor:
    """The positive root s (B,) of ``s E = sum_i w_i min(q_i, c s) / sum_i w_i`` over the (B, N) values ``q >= 0``
    with weights ``w >= 0`` (Huber's proposal 2 for a scale, ``expected`` = E < c), in closed form. With the q in
    ascending order the right side is linear in s between two of them, ``(A_j + c s B_j) / W`` (A_j the weighted sum
    of the j + 1 smallest, B_j the weight of the others), so the root is ``s = A_j / (W E - c B_j)`` for the last j
    whose q is not clipped at the root. That j is read off the sign of ``h(s) = s E W - sum w min(q, c s)`` at the
    breakpoints ``s = q_j / c``: h is convex and negative just above 0, so ``h <= 0`` exactly up to the root and the
    test is a prefix of the sorted q (a rounding slip at a breakpoint picks the neighbouring segment, whose root is
    the same within rounding). (Iterating the right side, a contraction, converges to it.) 1e-12 where a row has no
    positive root (no weight, or too little weight on q > 0); NaN where a weighted q is NaN."""
    qs, order = torch.where(w > 0, q, torch.full_like(q, float("inf"))).sort(-1)
    ws = w.gather(-1, order)
    W = ws.sum(-1, keepdim=True)
    qz = torch.where(ws > 0, qs, torch.zeros_like(qs))
    A = (ws * qz).cumsum(-1)
    above = (W - ws.cumsum(-1)).clamp_min(0.0)
    unclipped = (ws > 0) & (qz * W * expected <= c * (A + qz * above))  # h(q_j / c) <= 0, times c
    j = (unclipped.sum(-1, keepdim=True) - 1).clamp_min(0)
    den = W * expected - c * above.gather(-1, j)
    s = A.gather(-1, j) / torch.where(den > 0, den, torch.ones_like(den))
    s = torch.where(unclipped.any(-1, keepdim=True) & (den > 0), s, torch.zeros_like(s))[..., 0].clamp_min(1e-12)
    nan = (torch.isnan(q) & (w > 0)).any(-1)
    return torch.where(nan, torch.full_like(s, float("nan")), s)


@functools.lru_cache(maxsize=16)
def winsorised_chi2_mean(dof: int, c: float) -> float:
    """``E[min(X, c)]`` for X ~ chi-square(dof): ``dof F_{dof+2}(c) + c (1 - F_dof(c))`` (F the chi-square CDF)."""

    def cdf(k: int) -> float:
        a, x = (torch.tensor(v / 2.0, dtype=torch.float64, device="cpu") for v in (k, c))  # host: a Python float
        return float(torch.special.gammainc(a, x))

    return dof * cdf(dof + 2) + c * (1.0 - cdf(dof))


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
        self, forgetting: float = 0.98, min_scale: float = 0.01, max_scale: float = 100.0, clip: float | None = 0.9
    ) -> None:
        if not 0.0 < forgetting <= 1.0 or not 0.0 < min_scale <= 1.0 <= max_scale:
            raise ValueError(
                f"{type(self).__name__}: need 0 < forgetting <= 1 and 0 < min_scale <= 1 <= max_scale, got {forgetting}, "
                f"{min_scale}, {max_scale}"
            )
        if clip is not None and not 0.0 < clip < 1.0:
            raise ValueError(f"{type(self).__name__}: clip is a probability in (0, 1) or None, got {clip}")
        self.forgetting, self.min_scale, self.max_scale, self.clip = forgetting, min_scale, max_scale, clip

    def initial(self, B: int, dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> ScaleState:
        """k = 1 (the weighting's R as it is) with no weight, for B sequences."""
        return ScaleState(torch.ones(B, 2, dtype=dtype, device=device), torch.zeros(B, 2, dtype=dtype, device=device))

    def updated(self, state: ScaleState, stats: ScaleStats) -> ScaleState:
        """The running estimate after one frame's statistics (module docstring); unchanged where the frame had none."""
        with torch.no_grad():
            past = self.forgetting * state.dof
            dof = past + stats.weight
            k = (past * state.scale + stats.weight * stats.scale) / dof.clamp_min(1e-12)
            k = torch.where(dof > 0, k, state.scale).clamp(self.min_scale, self.max_scale)
        return ScaleState(k, dof)
