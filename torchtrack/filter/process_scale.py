"""Online process-noise scale: how strongly the tracked body really accelerates, per sequence and per block.

The constant-velocity model (eqs. 3-4) drives the velocities by white acceleration of hand-set std ``sigma_ang_acc``,
``sigma_lin_acc`` (:func:`~torchtrack.filter.models.constant_velocity`): ``Q0``. A hand-held camera, a turntable and a
fast skip-3 copy of a sequence accelerate very differently, and the Kalman gain depends on Q against R. So, like the
measurement noise (:mod:`~torchtrack.filter.noise_scale`), the process noise gets a factor per block from the data:
``Q = c_b Q0`` on the angular block b = ang (rotation and angular velocity) and the linear one b = lin (translation
and velocity), ``c = (c_ang, c_lin)`` estimated online from the filter's own corrections.

Derivation (covariance matching on the state correction; Mohamed & Schwarz 1999). At one frame the update moves the
prediction by ``dx = x+ - x- = K v``; for a consistent filter ``E[dx dx^T] = K S K^T = P- - P+ =: A``, with
``P- = F P+_{t-1} F^T + c Q0``. Mohamed & Schwarz solve this for Q: ``Q^ = dx dx^T + P+ - F P+_{t-1} F^T``, i.e.
for one scalar factor per block, ``c_t = c' + (|dx_b|^2 - tr A_b) / tr Q0_b`` under the c' the filter ran with.
Which rows of dx to use matters, since H has no velocity columns: ``dx = P- H^T S^-1 v`` gives the velocity
correction ``dv = P-_vp (P-_pp)^-1 dp`` — a fixed linear map of the pose correction dp, so both carry the same
information, and the whitened statistic ``d_b = dx_b^T A_b^-1 dx_b ~ chi2(3)`` is the same number whether taken on
the pose rows or the velocity rows of a block. They differ in the *sensitivity* ``tr(A_b^-1 Q0_b)`` that turns
``d_b - 3`` into a step in c:

* velocity rows: F leaves a velocity as it is, so ``A_vv = Q_vv + P+_vv(t-1) - P+_vv(t)``, which in steady state
  is ``Q_vv = c' sigma^2 dt^2 I`` exactly, at any measurement accuracy: ``g_b = c' tr(A_vv^-1 Q0_vv) / 3 = 1`` and
  the frame's estimate is ``c_t = c' d_b / 3`` (the fixed-point iteration of "corrections as large as predicted");
* pose rows: ``A_pp`` is mostly the propagated velocity uncertainty ``dt^2 P_vv``, of which this frame's ``Q_pp``
  (``sigma^2 dt^4 / 4``) is a share of only ~Lambda / 8 (Lambda = sigma dt^2 / sigma_pose, Kalata's tracking
  index, about 1 here), while the true sensitivity of ``E[d]`` to c in steady state is ~1/2 (``A ~ sqrt(c)`` at low
  Lambda): the pose-row step would overshoot ~4 / Lambda times, a diverging iteration for Lambda < 2.

So per block the velocity rows are used, whitened (a weighted least squares instead of the plain trace)::

    d_b = dv_b^T A_b^-1 dv_b,   g_b = c'_b tr(A_b^-1 Q0_b) / 3,   c_t = c'_b (1 + (d_b - 3) / (3 g_b))

unbiased at its fixed point (E[d_b] = 3 for the filter run with the c it estimates: measured 0.99-1.06 on the
oracle) and, since ``Var(c_t) / c'^2 = 2 / (3 g^2)``, weighted by ``W_t = min(g_b, 1)^2``: right after a
(re-)selection the velocity prior (init_sigma_*_vel) dominates A, the frame says little about c and weighs little;
in steady state W_t = 1. Frames without an update (no measurement; ``dt = 0``: ``Q0 = 0``) weigh 0 and change
nothing.

Combining frames. Away from the fixed point one frame's ``c_t`` moves only part of the way: ``E[d] / 3 ~
(c_true / c')^gamma`` with an elasticity gamma that falls with the tracking index (the filter that follows its
measurements sees the process noise fully, gamma -> 1; where measurements dominate the corrections, less): on the
oracle, 0.81, 0.54 and 0.26 at tracking indices of about 20, 5 and 1. Averaging the ``c_t`` (as the noise scale
does) then converges as ``(1 - gamma / D)`` per frame: 16x too much Q was still 1.5-3x too much after 60 frames.
So the running estimate takes a Robbins-Monro step on log c with a Newton gain ``1 / gamma_0`` (GAIN = 2, gamma_0
= 1/2 the middle of the measured range; stable for any gamma <= 1 since the step ``W_t / D_t <= 1``)::

    D_t = lambda D_{t-1} + W_t,   log c_t = log c_{t-1} + GAIN (W_t / D_t) (c_t / c' - 1),   clamped to [c_min, c_max]

(``c_t / c' - 1 = (d_b - 3) / (3 g_b)``: zero mean at the fixed point, so the fixed point is kept). The start is
c = 1 with the weight of PRIOR_WEIGHT = 1 steady-state frame (with none, the first frame, whose A is all velocity
prior and W ~ 0, would set c alone; on the oracle it set c to the bound 0.01). Forgetting lambda = 0.9 (a window of
~10 frames: the shared sequences have 14-1000 frames, and a scale that needs 50 frames to settle never does on the
short ones); each sequence's c then scatters by ~30 % about its value (RESULTS). Detached: no gradient.

Robustness: a frame with a gross error (a re-selection the filter did not expect, an LK slip the gate missed) makes
one huge correction. ``d_b`` is winsorised at the chi-square ``clip`` quantile q of 3 dof, and replaced by
``3 min(d_b, q) / E[min(chi2(3), q)]`` so that it stays unbiased on Gaussian data (tested at q = the median); one
frame then moves log c by at most ``GAIN (W_t / D_t) (3 q / E[min] - 3) / (3 g)``.

Identifiability with the measurement scale (both on). The R scale reads the *residuals* after the update (m - 6
components per frame, the pose's 6 directions fitted out), the Q scale the 6-dof *correction*. A wrong R changes
P+ and hence A; a wrong Q changes P- and hence the gain, and the residuals only through the 6 fitted directions
(the O(6 / m) part of the redundancy numbers). The two statistics are thus nearly orthogonal: on the oracle with Q 16x and the pixel noise 4x
the model's, each scale with the other on reads what it reads alone with the other block given its truth, within 4 %
(tests/test_process_scale.py).

References: A. H. Mohamed, K. P. Schwarz, "Adaptive Kalman filtering for INS/GPS", J. Geodesy 73, 1999; R. K.
Mehra, "Approaches to adaptive filtering", IEEE TAC 17(5), 1972; P. R. Kalata, "The tracking index", IEEE TAES
20(2), 1984; Y. Bar-Shalom, X. R. Li, T. Kirubarajan, "Estimation with Applications to Tracking and Navigation",
Wiley 2001, §6.3 (piecewise-constant white acceleration).
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.config import EKFBackendConfig
from torchtrack.filter.ekf import chi2_quantile
from torchtrack.filter.noise_scale import NoiseScale, ScaleState, ScaleStats, winsorised_chi2_mean

ANG, LIN = 0, 1  # the column of each block in the (B, 2) factors: angular, linear
VELOCITY_ROWS = (slice(6, 9), slice(9, 12))  # the velocity rows of each block in the 12-state (eq. 2's order)
PRIOR_WEIGHT = 1.0  # the weight of the initial c = 1, in steady-state frames (module docstring)
GAIN = 2.0  # the Newton gain 1 / gamma_0 of the log-c step (module docstring)

__all__ = ["ANG", "LIN", "ProcessScale", "ScaleState", "correction_statistics", "velocity_variances"]


def velocity_variances(dt: Tensor, sigma_ang_acc: float, sigma_lin_acc: float) -> Tensor:
    """(B, 2) [ang, lin] the velocity diagonal of the model's ``Q0`` over ``dt`` (B,): ``sigma^2 dt^2`` (eqs. 3-4,
    :func:`~torchtrack.filter.models.constant_velocity`)."""
    sig2 = torch.tensor([sigma_ang_acc**2, sigma_lin_acc**2], dtype=dt.dtype, device=dt.device)
    return sig2 * dt[:, None] ** 2


def correction_statistics(
    prior_mean: Tensor,
    post_mean: Tensor,
    prior_cov: Tensor,
    post_cov: Tensor,
    q0: Tensor,
    scale: Tensor,
    updated: Tensor,
    clip: float | None,
) -> ScaleStats:
    """This frame's estimate of c per block and its weight (module docstring), without gradient.

    Args:
        prior_mean, post_mean: (B, 12) the state before and after the update (the update's own mean, before an
            SE(3) reset; the velocity rows are the same either way).
        prior_cov, post_cov: (B, 12, 12) P- (with ``c' Q0``) and the update's P+.
        q0: (B, 2) [ang, lin] the model's velocity process variance this frame (:func:`velocity_variances`).
        scale: (B, 2) the factors c' the prediction used.
        updated: (B,) bool, whether the update used any measurement.
        clip: chi-square quantile (3 dof) at which ``d_b`` is winsorised, or None.

    Returns:
        :class:`~torchtrack.filter.noise_scale.ScaleStats` (B, 2): ``scale`` the frame's c_t (c' where the weight
        is 0), ``weight`` W_t.
    """
    with torch.no_grad():
        dof = 3
        c_prev = scale.to(prior_cov.dtype)
        dx = post_mean - prior_mean
        A = prior_cov - post_cov
        A = 0.5 * (A + A.transpose(-1, -2))
        if clip is not None:
            cap = chi2_quantile(clip, dof)
            expected = winsorised_chi2_mean(dof, cap)
        cs, ws = [], []
        for b, rows in enumerate(VELOCITY_ROWS):
            Ab = A[:, rows, rows]
            L, info = torch.linalg.cholesky_ex(Ab)
            ok = updated & (info == 0) & (q0[:, b] > 0)
            eye = torch.eye(dof, dtype=A.dtype, device=A.device).expand_as(Ab)
            L = torch.where(ok[:, None, None], L, eye)
            Linv = torch.linalg.solve_triangular(L, eye, upper=False)
            d = (Linv @ dx[:, rows, None]).square().sum((1, 2))  # dv^T A^-1 dv
            if clip is not None:
                d = torch.minimum(d, torch.full_like(d, cap)) * (dof / expected)
            g = c_prev[:, b] * q0[:, b] * Linv.square().sum((1, 2)) / dof  # c' tr(A^-1 Q0) / 3
            ok = ok & (g > 0)
            g_safe = torch.where(ok, g, torch.ones_like(g))
            cs.append(torch.where(ok, c_prev[:, b] * (1.0 + (d - dof) / (dof * g_safe)), c_prev[:, b]))
            ws.append(torch.where(ok, g.clamp(max=1.0).square(), torch.zeros_like(g)))
    return ScaleStats(torch.stack(cs, -1), torch.stack(ws, -1))


class ProcessScale(NoiseScale):
    """The online process-noise scale's parameters and its pure running update (the back end owns the state).

    Args:
        forgetting: lambda in (0, 1]: the weight of the past per frame (a window of about 1 / (1 - lambda) frames).
        min_scale, max_scale: bounds of c (0 < min_scale <= 1 <= max_scale).
        clip: chi-square quantile (3 dof) in (0, 1) at which each frame's whitened correction is winsorised, or None.
    """

    def __init__(
        self,
        forgetting: float = EKFBackendConfig.process_forgetting,
        min_scale: float = EKFBackendConfig.process_scale_min,
        max_scale: float = EKFBackendConfig.process_scale_max,
        clip: float | None = EKFBackendConfig.process_clip,
    ) -> None:
        super().__init__(forgetting, min_scale, max_scale, clip)  # the same checks, named after this class

    def initial(self, B: int, dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> ScaleState:
        """c = 1 (the model's Q) for B sequences, with the weight of PRIOR_WEIGHT steady-state frames."""
        state = super().initial(B, dtype, device)
        return state._replace(dof=torch.full_like(state.dof, PRIOR_WEIGHT))

    def updated(self, state: ScaleState, stats: ScaleStats) -> ScaleState:
        """The running factors after one frame's :func:`correction_statistics` (module docstring: a Robbins-Monro
        step on log c with gain GAIN / D_t); unchanged where the frame has no weight."""
        with torch.no_grad():
            dof = self.forgetting * state.dof + stats.weight
            step = stats.weight / dof.clamp_min(1e-12) * (stats.scale / state.scale - 1.0) * GAIN
            c = (state.scale * torch.exp(step)).clamp(self.min_scale, self.max_scale)
        return ScaleState(torch.where(stats.weight > 0, c, state.scale), torch.where(stats.weight > 0, dof, state.dof))
