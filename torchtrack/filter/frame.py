"""One frame of the paper's fusion EKF as a pure function (:func:`ekf_frame`), and what it takes and gives.

The tracker's stateful owner of the filter state is :class:`torchtrack.filter.backend.EKFBackend`; the learned
weighting replays this function over recorded frames (:mod:`torchtrack.learn.rollout`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.filter.ekf import chi2_quantile, cholesky_jittered, symmetrize
from torchtrack.filter.fusion import FilterState, FusionEKF
from torchtrack.filter.models import measure_pose
from torchtrack.filter.noise_scale import NoiseScale, ScaleState, residual_statistics, scaled
from torchtrack.filter.weighting import Variances


@dataclass
class Observation:
    """What the front end measured for the current frame.

    Attributes:
        dt: (B,) seconds since the previous frame.
        points_obj: (B, N, 3) model points X_o in the (centroid-centred) object frame.
        points_d: (B, N, 3) measured 3D points X_d in the depth camera, eq. (6).
        pixels: (B, N, 2) measured pixels in the colour image, eq. (7).
        valid: (B, N) bool: the feature was tracked (its pixel is a measurement, eq. 7).
        K: (B, 3, 3) colour intrinsics.
        T_color_depth: (B, 4, 4) depth-to-colour extrinsic (R_dv, t_dv).
        has_depth: (B, N) bool: its 3D point was measured too (eq. 6); None: wherever ``valid``. A tracked feature
            without depth (a hole, an edge, a band the depth camera does not see) still measures its pixel.
    """

    dt: Tensor
    points_obj: Tensor
    points_d: Tensor
    pixels: Tensor
    valid: Tensor
    K: Tensor
    T_color_depth: Tensor
    has_depth: Tensor | None = None

    @property
    def valid_xyz(self) -> Tensor:
        """(B, N) bool: the features whose 3D point is a measurement."""
        return self.valid if self.has_depth is None else self.valid & self.has_depth


class FrameUpdate(NamedTuple):
    """One frame of the fusion EKF (:func:`ekf_frame`), batched over B.

    Attributes:
        posterior: the frame's :class:`FilterState` (mean (B, 12), cov (B, 12, 12), T_cam_obj (B, 4, 4)).
        prior: the prediction (:class:`FilterState`) the update started from.
        used_xyz, used_pix: (B, N) bool, the 3D points and the pixels the final update used.
        innovation: (B, N, 5) ``z - h(prior mean)``, 3D (m) then pixel (px); 0 where not used.
        innovation_var: (B, N, 5) ``diag(H P- H^T) + R``, the predicted innovation variances; 1 where not used. R is
            the variances the update used: the weighting's, times the noise scale when it is on.
        nll: (B,) negative log-likelihood of the used innovations under the full predicted innovation covariance
            ``S = H P- H^T + R`` (zeros unless asked for with ``with_nll``).
        updated: (B,) bool, False where no measurement was used (the prediction was kept).
        noise: the online noise scale after this frame (:class:`~torchtrack.filter.noise_scale.ScaleState`, its
            ``scale`` (B, 2) [pix, xyz]); None when the scale is off.
    """

    posterior: FilterState
    prior: FilterState
    used_xyz: Tensor
    used_pix: Tensor
    innovation: Tensor
    innovation_var: Tensor
    nll: Tensor
    updated: Tensor
    noise: ScaleState | None = None

    @property
    def T_cam_obj(self) -> Tensor:
        """(B, 4, 4) posterior object pose in the depth camera."""
        return self.posterior.T_cam_obj

    @property
    def mean(self) -> Tensor:
        """(B, 12) posterior state mean (the state's coordinates: Euler, or the SE(3) error state after its reset)."""
        return self.posterior.mean

    @property
    def cov(self) -> Tensor:
        """(B, 12, 12) posterior covariance."""
        return self.posterior.cov

    @property
    def noise_scale(self) -> Tensor | None:
        """(B, 2) the online noise scales [pix, xyz] after this frame (the next frame's R = scale x the weighting's),
        or None when the scale is off."""
        return None if self.noise is None else self.noise.scale


def ekf_frame(
    ekf: FusionEKF,
    state: FilterState,
    obs: Observation,
    var: Variances,
    *,
    gate: float | None = 0.999,
    refit: float | None = 0.999,
    with_nll: bool = False,
    noise_scale: NoiseScale | None = None,
    scale_state: ScaleState | None = None,
) -> FrameUpdate:
    """One frame of the paper's fusion EKF as a pure function: prior state, observation and variances in, posterior
    out; nothing is mutated. Differentiable in ``var``, ``state`` and the measurements; the discrete choices (gate,
    refit) are masks computed without gradient.

    Steps: constant-velocity prediction (eqs. 3-4); one linearisation of eqs. (6)-(7) at the prediction (the
    filter's Jacobian mode), shared by the gate, the update and the refit's second update; the gate (optional):
    a feature's 3D point is dropped when its innovation fails the chi-square test (quantile ``gate``, 3 dof) under
    ``diag(H P- H^T) + R``, its pixel only together with it (:func:`_keep`); the update (eq. 15); the refit
    (optional): each used 3D point's residual at the UPDATED pose is tested against R alone (quantile ``refit``),
    and when a used measurement fails, the update is redone from the same prior without it. With ``noise_scale``
    (optional, :mod:`~torchtrack.filter.noise_scale`): every step above uses ``R = k R0``, k (B, 2) the running scales
    of ``scale_state`` (default: k = 1) and R0 the weighting's ``var``; the used measurements' post-fit residuals then
    update the scales (:attr:`FrameUpdate.noise`), without gradient.

    Args:
        ekf: :class:`~torchtrack.filter.fusion.FusionEKF` (its parameters only).
        state: prior :class:`FilterState` (mean (B, 12), cov (B, 12, 12), T_cam_obj (B, 4, 4)).
        obs: :class:`Observation` of N features.
        var: per-feature :class:`~torchtrack.filter.weighting.Variances` (B, N).
        with_nll: also compute :attr:`FrameUpdate.nll` (the self-supervised training loss).
        noise_scale: the online noise scale's parameters (None: off, the weighting's R as it is); scale_state: its
            running state before this frame.
    """
    if noise_scale is not None:
        if scale_state is None:
            scale_state = noise_scale.initial(obs.valid.shape[0], device=obs.valid.device)
        from torchtrack.filter.noise_scale import used_scale

        var = scaled(var, used_scale(scale_state.scale))  # R = k R0 for every step of this frame
    prior = ekf.predicted(state, obs.dt)  # eqs. (3)-(4)
    dt = prior.mean.dtype
    points_obj, K, T_cd = obs.points_obj.to(dt), obs.K.to(dt), obs.T_color_depth.to(dt)
    z = torch.cat([obs.points_d, obs.pixels], -1).to(dt)  # B,N,5
    var5 = torch.cat([var.var_xyz[..., None].expand(-1, -1, 3), var.var_pix[..., None].expand(-1, -1, 2)], -1).to(dt)
    h, H = ekf.linearize_at(prior, points_obj, K, T_cd)  # at the prediction, once per frame
    s_prior = var5 + torch.einsum("bnms,bst,bnmt->bnm", H, prior.cov, H)  # diag(H P- H^T) + R
    measured = xyz = obs.valid_xyz
    pix = obs.valid
    z = torch.cat([torch.where(xyz[..., None], z[..., :3], h[..., :3].detach()), z[..., 3:]], -1)  # no 3D point: none
    if gate is not None:
        with torch.no_grad():
            xyz, pix = _keep(xyz, pix, *_chi2_tests(z, h, s_prior, gate), measured)

    def update(xyz: Tensor, pix: Tensor):
        return ekf.updated(
            prior,
            points_obj,
            obs.points_d,
            obs.pixels,
            xyz,
            pix,
            var.var_xyz,
            var.var_pix,
            K,
            T_cd,
            linearization=(h, H),
        )  # eqs. (6)-(7), (15); fmt: skip

    post = update(xyz, pix)
    posterior = ekf.injected(prior, post)
    if refit is not None:
        with torch.no_grad():
            h_post = measure_pose(posterior.T_cam_obj, points_obj, K, T_cd)
            xyz_new, pix_new = _keep(xyz, pix, *_chi2_tests(z, h_post, var5, refit), measured)
        if bool(((xyz_new != xyz) | (pix_new != pix)).any()):
            xyz, pix = xyz_new, pix_new
            post = update(xyz, pix)  # same prior, fewer measurements: the same linearisation
            posterior = ekf.injected(prior, post)
    used = torch.cat([xyz[..., None].expand(-1, -1, 3), pix[..., None].expand(-1, -1, 2)], -1)
    innovation = torch.where(used, z - h, torch.zeros_like(h))
    innovation_var = torch.where(used, s_prior, torch.ones_like(s_prior))
    nll = innovation_nll(prior.cov, H, innovation, var5, used) if with_nll else torch.zeros_like(prior.mean[:, 0])
    noise = None
    if noise_scale is not None:
        with torch.no_grad():
            valid5 = torch.cat([obs.valid_xyz[..., None].expand(-1, -1, 3), obs.valid[..., None].expand(-1, -1, 2)], -1)
            residual = torch.where(valid5, z - h, torch.zeros_like(h)) - torch.einsum(
                "bnms,bs->bnm", H, post.mean - prior.mean
            )  # linearised at x-
            post_hph = torch.einsum("bnms,bst,bnmt->bnm", H, post.cov, H)
            from torchtrack.filter import noise_scale as ns

            k_used = ns.used_scale(scale_state.scale)
            stats = residual_statistics(residual, post_hph, var5, valid5, used, k_used, noise_scale.clip)
            if ns.WHITE:
                white, last_r, last_rv, last_ok = ns.white_statistics(
                    residual, post_hph, var5, valid5, used, k_used, scale_state, noise_scale.clip
                )
                cols = ns.white_columns(residual.device)
                if white is None:
                    stats = ns.ScaleStats(torch.where(cols, scale_state.scale, stats.scale),
                                          torch.where(cols, torch.zeros_like(stats.weight), stats.weight))
                else:
                    stats = ns.ScaleStats(torch.where(cols, white.scale, stats.scale),
                                          torch.where(cols, white.weight, stats.weight))
                scale_state = scale_state._replace(last_r=last_r, last_rv=last_rv, last_ok=last_ok)
        noise = noise_scale.updated(scale_state, stats)
    updated = used.any(-1).any(-1)
    return FrameUpdate(posterior, prior, xyz, pix, innovation, innovation_var, nll, updated, noise)


def innovation_nll(prior_cov: Tensor, H: Tensor, innovation: Tensor, var5: Tensor, used: Tensor) -> Tensor:
    """(B,) ``0.5 (r^T S^-1 r + log det S + m log 2 pi)`` of the m used innovations r (B, N, 5) under the predicted
    innovation covariance ``S = H P- H^T + R`` (R = diag(var5)), without forming the (5N x 5N) S: with W = R^-1,
    ``J = H^T W H``, ``g = H^T W r`` and ``P- = L L^T``, ``C C^T = I + L^T J L``: Woodbury gives
    ``r^T S^-1 r = r^T W r - |C^-1 L^T g|^2`` and the determinant lemma ``log det S = log det R + 2 sum log diag C``.
    Unused entries (``used`` False) contribute nothing, and no gradient. ``P-`` is factored as the update factors it
    (:func:`~torchtrack.filter.ekf.cholesky_jittered`): where it is not numerically positive definite, both use the
    same jittered ``P-``, so the likelihood is that of the S the update used."""
    B, N, M, S = H.shape
    var_safe = torch.where(used, var5, torch.ones_like(var5))
    sw = torch.where(used, var_safe.rsqrt(), torch.zeros_like(var5))  # W^1/2
    Hs = (H * sw[..., None]).reshape(B, N * M, S)
    rs = (innovation * sw).reshape(B, N * M, 1)
    L = cholesky_jittered(prior_cov)
    J = Hs.transpose(-1, -2) @ Hs
    eye = torch.eye(S, dtype=J.dtype, device=J.device)
    C = torch.linalg.cholesky(symmetrize(eye + L.transpose(-1, -2) @ J @ L))  # >= I: always factors
    v = torch.linalg.solve_triangular(C, L.transpose(-1, -2) @ (Hs.transpose(-1, -2) @ rs), upper=False)
    quad = (rs**2).sum((1, 2)) - (v**2).sum((1, 2))
    logdet = torch.where(used, var_safe.log(), torch.zeros_like(var5)).sum((1, 2))
    logdet = logdet + 2.0 * torch.diagonal(C, dim1=-2, dim2=-1).log().sum(-1)
    return 0.5 * (quad + logdet + used.sum((1, 2)) * math.log(2.0 * math.pi))


def _keep(xyz: Tensor, pix: Tensor, ok_xyz: Tensor, ok_pix: Tensor, measured: Tensor) -> tuple[Tensor, Tensor]:
    """A failing 3D point is dropped; a pixel only with its 3D point, or on its own test where it has none. The 3D
    variances (eq. 14) are metric, the pixel variances of eq. (11) only relative (scaled to a mean), so a pixel test
    alone is not calibrated: dropping pixels on it alone was measured worse (7-Scenes ATE 106 vs 53-69 mm)."""
    return xyz & ok_xyz, pix & (ok_pix | (ok_xyz & measured))


def _chi2_tests(z: Tensor, h: Tensor, s: Tensor, p: float) -> tuple[Tensor, Tensor]:
    """Per-feature chi-square tests (quantile p) of the 3D and the pixel residual ``z - h`` (B, N, 5) with variances
    ``s`` (B, N, 5): (B, N) bool each."""
    d2 = torch.nan_to_num((z - h) ** 2 / s, nan=float("inf"))
    return d2[..., :3].sum(-1) < chi2_quantile(p, 3), d2[..., 3:].sum(-1) < chi2_quantile(p, 2)
