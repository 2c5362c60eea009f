"""Generic batched extended Kalman filter with autograd measurement Jacobians.

B independent filters (sequences) of state size S run in lockstep. Measurements come as N features of
M values each, padded to ``(B, N, M)`` with a ``valid`` mask: an invalid feature (or component) gets
zero information — its inverse variance is exactly 0 and its inputs, measurement and variance are
replaced (``torch.where``) before use, so NaN/inf garbage in padded slots never reaches the result or
its gradients.

The measurement model is written for ONE feature, ``h_single(x (S,), *feature_inputs_i, *sequence_inputs_b)
-> (M,)``, and its Jacobian is ``torch.func.vmap(torch.func.jacfwd(h_single))`` over features and then
sequences (STYLE.md #4) — never ``autograd.functional.jacobian`` on a batched function. A batched
``linearizer`` (e.g. a closed-form Jacobian, several times faster on CPU) can replace autograd.

Update forms (equal in exact arithmetic; a test checks it to 1e-8 in float64):

* ``"information"`` (default): ``Sigma+ = (Sigma-^-1 + H^T Q^-1 H)^-1`` with diagonal Q, where
  ``J = H^T Q^-1 H = sum_i H_i^T W_i H_i`` is accumulated from the per-feature (M x S) blocks — O(N S^2),
  no (MN x MN) matrix. It is evaluated without inverting ``Sigma-``: with ``Sigma- = L L^T``,
  ``Sigma+ = L (I + L^T J L)^-1 L^T = A A^T``, ``A = L C^-T``, ``C C^T = I + L^T J L`` (eigenvalues >= 1).
  ``Sigma+`` is a Gram matrix, hence symmetric PSD by construction — the information-form counterpart of
  Joseph's form (no subtraction of PSD terms anywhere).
* ``"gain"``: the paper's eq. (15), ``K = Sigma H^T (H Sigma H^T + Q)^-1``, with the (MN x MN) innovation
  covariance; the covariance uses Joseph's form ``(I - K H) Sigma (I - K H)^T + K Q K^T`` (eq. (15)'s
  ``(I - K H) Sigma`` is the same in exact arithmetic but can lose symmetry/PD in floating point).
  Reference implementation; O((MN)^3); computed in float64 whatever the input dtype.

Linearisation point: the first (or only) iteration linearises h at the PREDICTED mean ``mu-`` (standard
EKF). With ``iterations = k > 1`` the iterated EKF (Gauss–Newton on the MAP cost) re-linearises at the
latest estimate ``x_j``: ``x_{j+1} = mu- + K_j (z - h(x_j) - H_j (mu- - x_j))``; the returned covariance
uses the last Jacobian ``H_j``.

References: Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to Tracking and Navigation" (2001),
§5.2 (information form), §10.3 (iterated EKF); Gedik & Alatan (2013), eq. (15).
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import torch
from torch import Tensor

log = logging.getLogger(__name__)

Linearizer = Callable[[Tensor, Sequence[Tensor], Sequence[Tensor]], tuple[Tensor, Tensor]]


class Prediction(NamedTuple):
    """Predicted state. mean: (B, S); cov: (B, S, S)."""

    mean: Tensor
    cov: Tensor


class Update(NamedTuple):
    """Result of :func:`update`.

    Attributes:
        mean: (B, S) posterior mean.
        cov: (B, S, S) posterior covariance (symmetric PD).
        innovation: (B, N, M) ``z - h(mu-)`` at the predicted mean; 0 where invalid.
        num_valid: (B,) number of valid measurement components used.
    """

    mean: Tensor
    cov: Tensor
    innovation: Tensor
    num_valid: Tensor


@functools.lru_cache(maxsize=64)
def chi2_quantile(p: float, k: int) -> float:
    """Chi-square quantile with k degrees of freedom: the x with P(k/2, x/2) = p (regularised lower incomplete
    gamma), by bisection in float64 (exact to ~1e-12; closed form -2 log(1 - p) for k = 2)."""
    if not 0.0 < p < 1.0 or k < 1:
        raise ValueError(f"chi2_quantile: need 0 < p < 1 and k >= 1, got p={p}, k={k}")
    if k == 2:
        return -2.0 * math.log1p(-p)
    a = torch.tensor(k / 2.0, dtype=torch.float64, device="cpu")  # host arithmetic for a Python float
    lo, hi = 0.0, float(k)
    while float(torch.special.gammainc(a, torch.tensor(hi / 2.0, dtype=torch.float64, device="cpu"))) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if float(torch.special.gammainc(a, torch.tensor(mid / 2.0, dtype=torch.float64, device="cpu"))) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def symmetrize(cov: Tensor) -> Tensor:
    """``(P + P^T) / 2`` over the last two dims."""
    return 0.5 * (cov + cov.transpose(-1, -2))


def predict(mean: Tensor, cov: Tensor, F: Tensor | Callable[[Tensor], Tensor], Q: Tensor) -> Prediction:
    """EKF prediction ``mu- = g(mu)``, ``Sigma- = G Sigma G^T + Q`` (eq. (15), first line).

    Args:
        mean: (B, S); cov: (B, S, S).
        F: transition matrix (S, S) or (B, S, S), or ``g_single(x (S,)) -> (S,)`` whose Jacobian G is taken
            by ``vmap(jacfwd(g_single))`` at ``mean``.
        Q: (S, S) or (B, S, S) process-noise covariance.

    Returns:
        :class:`Prediction` with mean (B, S) and symmetrised cov (B, S, S).
    """
    _check_state(mean, cov, "predict")
    if callable(F):
        G, new_mean = torch.func.vmap(torch.func.jacfwd(_with_value(F), has_aux=True))(mean)
    else:
        if F.shape[-2:] != cov.shape[-2:]:
            raise ValueError(f"predict: F must be (B, S, S) or (S, S), got {tuple(F.shape)}")
        G = F
        new_mean = (G @ mean[..., None])[..., 0]
    return Prediction(new_mean, symmetrize(G @ cov @ G.transpose(-1, -2) + Q))


def linearize(
    h_single: Callable[..., Tensor],
    x: Tensor,
    feature_inputs: Sequence[Tensor] = (),
    sequence_inputs: Sequence[Tensor] = (),
    mode: Literal["forward", "reverse"] = "forward",
) -> tuple[Tensor, Tensor]:
    """Per-feature measurement prediction and Jacobian by autograd.

    ``h_single(x (S,), *feature_inputs_i, *sequence_inputs_b) -> (M,)`` is vectorised over the features of a
    sequence with ``vmap`` and over sequences with an outer ``vmap``. Forward mode differentiates the
    feature-vectorised function: ``vmap(jacfwd(vmap(h_single)))``. The features of a sequence share x, so its
    Jacobian (N, M, S) is exactly the per-feature Jacobians stacked (no cross-feature blocks; the cross-batch
    trap is only for x batched per feature), and the operations on x alone (the rotation) are differentiated
    once per sequence instead of under one more vmap level (measured ~10% faster than
    ``vmap(vmap(jacfwd(h_single)))``). ``mode="reverse"`` uses ``vmap(vmap(jacrev(h_single)))``.

    Args:
        x: (B, S) linearisation points.
        feature_inputs: tensors (B, N, ...), one slice per feature (at least one, to define N).
        sequence_inputs: tensors (B, ...), shared by the features of a sequence.

    Returns:
        h (B, N, M), H (B, N, M, S).
    """
    if not feature_inputs:
        raise ValueError("linearize: need at least one per-feature input (B, N, ...) to define N")
    nf, ns = len(feature_inputs), len(sequence_inputs)
    feature_dims = (None,) + (0,) * nf + (None,) * ns
    if mode == "forward":
        per_sequence = torch.func.jacfwd(torch.func.vmap(_with_value(h_single), in_dims=feature_dims), has_aux=True)
    else:
        per_sequence = torch.func.vmap(torch.func.jacrev(_with_value(h_single), has_aux=True), in_dims=feature_dims)
    H, h = torch.func.vmap(per_sequence)(x, *feature_inputs, *sequence_inputs)
    return h, H


def update(
    mean: Tensor,
    cov: Tensor,
    z: Tensor,
    var: Tensor,
    valid: Tensor,
    h_single: Callable[..., Tensor] | None = None,
    feature_inputs: Sequence[Tensor] = (),
    sequence_inputs: Sequence[Tensor] = (),
    *,
    form: Literal["information", "gain"] = "information",
    iterations: int = 1,
    jacobian: Literal["forward", "reverse"] = "forward",
    linearizer: Linearizer | None = None,
    linearization: tuple[Tensor, Tensor] | None = None,
) -> Update:
    """EKF measurement update with diagonal, per-feature noise (eq. (15) or its information form).

    Args:
        mean: (B, S) predicted mean ``mu-``; cov: (B, S, S) predicted covariance.
        z: (B, N, M) measurements; var: (B, N, M) their noise variances (diagonal of Q).
        valid: (B, N) or (B, N, M) bool; False entries contribute exactly zero information.
        h_single: per-feature model ``(x (S,), *feature_inputs_i, *sequence_inputs_b) -> (M,)``.
        feature_inputs: tensors (B, N, ...) for h_single; invalid features' values are zeroed first.
        sequence_inputs: tensors (B, ...) for h_single.
        form: "information" (default, O(N S^2)) or "gain" (paper's eq. (15), reference).
        iterations: 1 = EKF; k > 1 = iterated EKF, re-linearising at the new estimate k - 1 times.
        jacobian: autograd mode for h_single's Jacobian, "forward" (jacfwd) or "reverse" (jacrev).
        linearizer: optional batched ``(x (B,S), feature_inputs, sequence_inputs) -> (h (B,N,M), H (B,N,M,S))``
            replacing autograd (e.g. an analytic Jacobian).
        linearization: optional (h (B, N, M), H (B, N, M, S)) already computed at ``mean`` (e.g. shared with an
            innovation gate, or with a second update from the same prior): used instead of linearising again at
            the first iteration. Only the entries of valid features are read.

    Returns:
        :class:`Update`. A sequence without valid measurements keeps its prediction exactly.
    """
    _check_state(mean, cov, "update")
    if z.dim() != 3 or z.shape[0] != mean.shape[0] or var.shape != z.shape:
        raise ValueError(
            f"update: z and var must be (B, N, M) with B = {mean.shape[0]}, got {tuple(z.shape)} and {tuple(var.shape)}"
        )
    if valid.shape not in (z.shape, z.shape[:2]):
        raise ValueError(f"update: valid must be (B, N) or (B, N, M), got {tuple(valid.shape)}")
    if form not in ("information", "gain") or iterations < 1:
        raise ValueError(f"update: form must be 'information'|'gain' and iterations >= 1, got {form}, {iterations}")
    if h_single is None and linearizer is None:
        raise ValueError("update: give h_single or linearizer")
    feat_valid = valid if valid.dim() == 2 else valid.any(-1)
    valid = valid[..., None].expand_as(z) if valid.dim() == 2 else valid
    feature_inputs = [_zero_invalid(t, feat_valid) for t in feature_inputs]
    # double-where: no inf/NaN reaches 1/var or the residual, not even in masked slots (safe gradients)
    var_safe = torch.where(valid, var, torch.ones_like(var))
    w = torch.where(valid, 1.0 / var_safe, torch.zeros_like(var))
    z_safe = torch.where(valid, z, torch.zeros_like(z))
    if linearizer is None:

        def linearizer(x, fi, si):
            return linearize(h_single, x, fi, si, mode=jacobian)

    sw = w.sqrt()  # 1/sigma, 0 where invalid
    x = mean
    for it in range(iterations):
        if it == 0 and linearization is not None:
            h, H = linearization
        else:
            h, H = linearizer(x, feature_inputs, sequence_inputs)
        r = torch.where(valid, z_safe - h, torch.zeros_like(h))
        if it == 0:
            innovation = r
        if form == "information":  # whitened rows: H_i / sigma_i, one pass over the big (B,N,M,S) tensor
            Hs = torch.where(valid[..., None], H * sw[..., None], torch.zeros_like(H))
            rs = r * sw
            if it > 0:  # iterated EKF: model linearised at x, evaluated at the prior mean
                rs = rs - (Hs @ (mean - x)[:, None, :, None])[..., 0]
            x, new_cov = _information_step(mean, cov, Hs, rs)
        else:
            Hm = torch.where(valid[..., None], H, torch.zeros_like(H))
            if it > 0:
                r = r - (Hm @ (mean - x)[:, None, :, None])[..., 0]
            x, new_cov = _gain_step(mean, cov, Hm, var_safe, r)
    return Update(x, new_cov, innovation, valid.sum((1, 2)))


def _information_step(mean: Tensor, cov: Tensor, Hs: Tensor, rs: Tensor) -> tuple[Tensor, Tensor]:
    """Information form, O(N S^2), on whitened rows ``Hs = W^1/2 H``, ``rs = W^1/2 r``.

    ``J = Hs^T Hs = sum_i H_i^T W_i H_i``; ``Sigma+ = L (I + L^T J L)^-1 L^T = A A^T``; ``mu+ = mu- + Sigma+ Hs^T rs``.
    """
    B, N, M, S = Hs.shape
    Hf = Hs.reshape(B, N * M, S)
    HfT = Hf.transpose(-1, -2)
    J = HfT @ Hf  # B,S,S
    g = HfT @ rs.reshape(B, N * M, 1)  # B,S,1 = H^T W r
    L = cholesky_jittered(cov)
    eye = torch.eye(S, dtype=cov.dtype, device=cov.device)
    C = torch.linalg.cholesky(symmetrize(eye + L.transpose(-1, -2) @ J @ L))
    At = torch.linalg.solve_triangular(C, L.transpose(-1, -2), upper=False)  # A^T = C^-1 L^T
    new_cov = symmetrize(At.transpose(-1, -2) @ At)
    new_mean = mean + (At.transpose(-1, -2) @ (At @ g))[..., 0]
    return new_mean, new_cov


def _gain_step(mean: Tensor, cov: Tensor, H: Tensor, var: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """Paper's gain form, eq. (15), with Joseph's covariance update. Masked rows: H = 0, r = 0, var = 1.

    Computed in float64 whatever the input dtype: a float32 Cholesky of the (MN x MN) innovation
    covariance fails at realistic variances (pixel rows ~1e2, 3D rows ~1e-6).
    """
    dtype = mean.dtype
    mean, cov, H, var, r = (t.double() for t in (mean, cov, H, var, r))
    B, N, M, S = H.shape
    Hf = H.reshape(B, N * M, S)
    var = var.reshape(B, N * M)  # masked entries hold 1 (any positive value decouples them)
    innov_cov = symmetrize(Hf @ cov @ Hf.transpose(-1, -2)) + torch.diag_embed(var)  # B,NM,NM
    Lc = torch.linalg.cholesky(innov_cov)
    Kt = torch.cholesky_solve(Hf @ cov, Lc)  # K^T = (H Sigma H^T + Q)^-1 H Sigma, B,NM,S
    K = Kt.transpose(-1, -2)  # eq. (15)
    new_mean = mean + (K @ r.reshape(B, N * M, 1))[..., 0]
    I_KH = torch.eye(S, dtype=cov.dtype, device=cov.device) - K @ Hf
    new_cov = I_KH @ cov @ I_KH.transpose(-1, -2) + (K * var[:, None, :]) @ Kt
    return new_mean.to(dtype), symmetrize(new_cov).to(dtype)


def _with_value(fn: Callable[..., Tensor]) -> Callable[..., tuple[Tensor, Tensor]]:
    """Wrap ``fn`` to return ``(y, y)`` so that ``jacfwd(..., has_aux=True)`` also yields the value."""

    def f(*args):
        y = fn(*args)
        return y, y

    return f


def _zero_invalid(t: Tensor, feat_valid: Tensor) -> Tensor:
    if t.shape[:2] != feat_valid.shape:
        raise ValueError(f"update: feature inputs must be (B, N, ...), got {tuple(t.shape)}")
    if not t.is_floating_point():
        return t
    m = feat_valid.reshape(*feat_valid.shape, *([1] * (t.dim() - 2)))
    return torch.where(m, t, torch.zeros_like(t))


def cholesky_jittered(cov: Tensor) -> Tensor:
    """(B, S, S) Cholesky factor L of the covariances ``cov`` (B, S, S); where one is not numerically positive
    definite, of ``cov + 10^k m I`` instead (m its mean variance, k = -12, -10, ..., -2: the first that factors).
    The one fallback of the update (:func:`_information_step`) and of the innovation likelihood
    (:func:`torchtrack.filter.frame.innovation_nll`): both see the same ``P- = L L^T``."""
    L, info = torch.linalg.cholesky_ex(cov)
    bad = info > 0
    if not bool(bad.any()):
        return L
    scale = torch.diagonal(cov, dim1=-2, dim2=-1).abs().mean(-1)[:, None, None].clamp_min(1e-30)
    eye = torch.eye(cov.shape[-1], dtype=cov.dtype, device=cov.device)
    for k in range(-12, 0, 2):
        log.warning("EKF covariance not PD for %d sequence(s); adding jitter 1e%d x mean variance", int(bad.sum()), k)
        L_j, info = torch.linalg.cholesky_ex(cov + (10.0**k) * scale * eye)
        L = torch.where(bad[:, None, None], L_j, L)
        bad = bad & (info > 0)
        if not bool(bad.any()):
            return L
    raise ValueError("cholesky_jittered: the predicted covariance is not positive definite even with jitter")


def _check_state(mean: Tensor, cov: Tensor, where: str) -> None:
    if mean.dim() != 2 or cov.shape != (*mean.shape, mean.shape[-1]):
        raise ValueError(f"{where}: mean must be (B, S) and cov (B, S, S), got {tuple(mean.shape)}, {tuple(cov.shape)}")
