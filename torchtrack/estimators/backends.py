"""Pose back ends behind one interface, so that trackers differ only in how the pose is estimated.

The fusion EKF (paper §III-A) and the registration baselines (Horn, ICP, CPD; paper §IV) all take
the same per-frame :class:`Observation` of tracked features and return ``T_cam_obj`` (B, 4, 4).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from torchtrack.config import EKFBackendConfig
from torchtrack.filter.ekf import chi2_quantile, cholesky_jittered, symmetrize
from torchtrack.filter.error_state import left_twist_covariance
from torchtrack.filter.fusion import FilterState, FusionEKF
from torchtrack.filter.models import measure_pose
from torchtrack.filter.noise_scale import NoiseScale, ScaleState, residual_statistics, scaled
from torchtrack.filter.process_scale import ProcessScale, correction_statistics, velocity_variances
from torchtrack.filter.weighting import Variances

log = logging.getLogger(__name__)


@dataclass
class Observation:
    """What the front end measured for the current frame.

    Attributes:
        dt: (B,) seconds since the previous frame.
        points_obj: (B, N, 3) model points X_o in the (centroid-centred) object frame.
        points_d: (B, N, 3) measured 3D points X_d in the depth camera, eq. (6).
        pixels: (B, N, 2) measured pixels in the colour image, eq. (7).
        valid: (B, N) bool.
        K: (B, 3, 3) colour intrinsics.
        T_color_depth: (B, 4, 4) depth-to-colour extrinsic (R_dv, t_dv).
    """

    dt: Tensor
    points_obj: Tensor
    points_d: Tensor
    pixels: Tensor
    valid: Tensor
    K: Tensor
    T_color_depth: Tensor


class BackendResult(Protocol):
    @property
    def T_cam_obj(self) -> Tensor:
        """(B, 4, 4) the frame's object pose in the depth camera."""


class PoseBackend(Protocol):
    """A pose estimator that owns its state (the filter's, or the previous pose) between frames.

    ``fuses``: whether the back end is a filter whose frame update can be redone with more measurements of the same
    frame (re-acquired landmarks, ``landmarks.measure``): such a back end also has ``snapshot()`` and
    ``restore(snapshot, mask)`` (:class:`EKFBackend`); a registration baseline re-estimates the pose from scratch and
    has neither."""

    fuses: bool

    def start(self) -> None:
        """A new run (the tracker's first frame): forget everything; the next :meth:`reset` covers every sequence."""

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Start over at pose ``T_cam_obj`` (B, 4, 4) for the sequences where ``mask`` (B,) is True."""

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Move the current pose to ``T_cam_obj`` (B, 4, 4) where ``mask`` (B,), keeping the rest of the state."""

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> BackendResult:
        """One frame: observation and per-feature variances in, a named result with ``T_cam_obj`` (B, 4, 4) out.
        Sequences where ``active`` (B,) is False (ended) keep their state."""

    def pose_covariance(self) -> Tensor | None:
        """(B, 6, 6) the current pose's covariance as a left SE(3) twist ``(v, omega)`` of ``T_cam_obj``, or None
        where the back end has none (a registration baseline)."""

    def measurement_scale(self) -> Tensor | None:
        """(B, 2) the factors [pix, xyz] its measurement variances are scaled by (the online noise scale), or None."""


class BackendSnapshot(NamedTuple):
    """:meth:`EKFBackend.snapshot`: the filter state and the running noise and process scales (None where off)."""

    state: FilterState | None
    noise: ScaleState | None
    process: ScaleState | None


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
        process: the online process-noise scale after this frame (a ``ScaleState``, its ``scale`` (B, 2) [ang, lin],
            :mod:`~torchtrack.filter.process_scale`); None when it is off.
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
    process: ScaleState | None = None

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

    @property
    def process_scale(self) -> Tensor | None:
        """(B, 2) the online process-noise factors [ang, lin] after this frame (the next prediction's Q = c x the
        model's), or None when the process scale is off."""
        return None if self.process is None else self.process.scale


def ekf_frame(
    ekf: FusionEKF,
    state: FilterState,
    obs: Observation,
    var: Variances,
    *,
    gate: float | None = EKFBackendConfig.gate,
    refit: float | None = EKFBackendConfig.refit,
    with_nll: bool = False,
    noise_scale: NoiseScale | None = None,
    scale_state: ScaleState | None = None,
    process_scale: ProcessScale | None = None,
    process_state: ScaleState | None = None,
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
    update the scales (:attr:`FrameUpdate.noise`), without gradient. With ``process_scale`` (optional,
    :mod:`~torchtrack.filter.process_scale`): the prediction uses ``Q = c Q0``, c (B, 2) [ang, lin] the running
    factors of ``process_state`` (default: c = 1), and the update's velocity correction updates them
    (:attr:`FrameUpdate.process`), without gradient.

    Args:
        ekf: :class:`~torchtrack.filter.fusion.FusionEKF` (its parameters only).
        state: prior :class:`FilterState` (mean (B, 12), cov (B, 12, 12), T_cam_obj (B, 4, 4)).
        obs: :class:`Observation` of N features.
        var: per-feature :class:`~torchtrack.filter.weighting.Variances` (B, N).
        with_nll: also compute :attr:`FrameUpdate.nll` (the self-supervised training loss).
        noise_scale: the online noise scale's parameters (None: off, the weighting's R as it is); scale_state: its
            running state before this frame.
        process_scale: the online process-noise scale's parameters (None: off, the model's Q); process_state: its
            running state before this frame.
    """
    if noise_scale is not None:
        if scale_state is None:
            scale_state = noise_scale.initial(obs.valid.shape[0], device=obs.valid.device)
        var = scaled(var, scale_state.scale)  # R = k R0 for every step of this frame
    if process_scale is not None and process_state is None:
        process_state = process_scale.initial(obs.valid.shape[0], device=obs.valid.device)
    q_scale = process_state.scale if process_scale is not None else None  # Q = c Q0 only with the scale on
    prior = ekf.predicted(state, obs.dt, q_scale)  # eqs. (3)-(4)
    dt = prior.mean.dtype
    points_obj, K, T_cd = obs.points_obj.to(dt), obs.K.to(dt), obs.T_color_depth.to(dt)
    z = torch.cat([obs.points_d, obs.pixels], -1).to(dt)  # B,N,5
    var5 = torch.cat([var.var_xyz[..., None].expand(-1, -1, 3), var.var_pix[..., None].expand(-1, -1, 2)], -1).to(dt)
    h, H = ekf.linearize_at(prior, points_obj, K, T_cd)  # at the prediction, once per frame
    s_prior = var5 + torch.einsum("bnms,bst,bnmt->bnm", H, prior.cov, H)  # diag(H P- H^T) + R
    xyz = pix = obs.valid
    if gate is not None:
        with torch.no_grad():
            xyz, pix = _keep(xyz, pix, *_chi2_tests(z, h, s_prior, gate))

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
            xyz_new, pix_new = _keep(xyz, pix, *_chi2_tests(z, h_post, var5, refit))
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
            valid5 = obs.valid[..., None].expand_as(used)
            residual = torch.where(valid5, z - h, torch.zeros_like(h)) - torch.einsum(
                "bnms,bs->bnm", H, post.mean - prior.mean
            )  # linearised at x-
            post_hph = torch.einsum("bnms,bst,bnmt->bnm", H, post.cov, H)
            stats = residual_statistics(residual, post_hph, var5, valid5, used, scale_state.scale, noise_scale.clip)
        noise = noise_scale.updated(scale_state, stats)
    updated = used.any(-1).any(-1)
    process = None
    if process_scale is not None:
        q0 = velocity_variances(obs.dt.to(dt), ekf.sigma_ang_acc, ekf.sigma_lin_acc)
        stats = correction_statistics(prior.mean, post.mean, prior.cov, post.cov, q0, process_state.scale, updated,
                                      process_scale.clip)  # fmt: skip
        process = process_scale.updated(process_state, stats)
    return FrameUpdate(posterior, prior, xyz, pix, innovation, innovation_var, nll, updated, noise, process)


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


def _keep(xyz: Tensor, pix: Tensor, ok_xyz: Tensor, ok_pix: Tensor) -> tuple[Tensor, Tensor]:
    """A failing 3D point is dropped; a pixel only with its 3D point. The 3D variances (eq. 14) are metric, the pixel
    variances of eq. (11) only relative (scaled to a mean), so a pixel test alone is not calibrated: dropping pixels
    on it alone was measured worse (7-Scenes ATE 106 vs 53-69 mm)."""
    return xyz & ok_xyz, pix & (ok_pix | ok_xyz)


def _chi2_tests(z: Tensor, h: Tensor, s: Tensor, p: float) -> tuple[Tensor, Tensor]:
    """Per-feature chi-square tests (quantile p) of the 3D and the pixel residual ``z - h`` (B, N, 5) with variances
    ``s`` (B, N, 5): (B, N) bool each."""
    d2 = torch.nan_to_num((z - h) ** 2 / s, nan=float("inf"))
    return d2[..., :3].sum(-1) < chi2_quantile(p, 3), d2[..., 3:].sum(-1) < chi2_quantile(p, 2)


class EKFBackend:
    """The paper's fusion EKF as a tracker back end: owns the filter state, runs :func:`ekf_frame` once per frame.

    Args:
        ekf: a :class:`torchtrack.filter.fusion.FusionEKF` (its parameters; its own state is not used).
        gate: improvement over the paper (None = off): chi-square quantile of the innovation gate (see
            :func:`ekf_frame`). Nearest-pixel depth at occlusion boundaries and LK slips produce outliers of metres
            or pixels that a Gaussian update cannot absorb.
        refit: improvement over the paper (None = off): chi-square quantile of the refit at the updated pose (see
            :func:`ekf_frame`). The gate can only see outliers larger than the prediction's uncertainty; the refit
            catches the smaller ones that would otherwise bias this frame's pose before the tracker drops them.
        noise_scale: improvement over the paper (False = off): the online noise scale per sequence and block
            (:mod:`torchtrack.filter.noise_scale`): R = k R0 with k (B, 2) [pix, xyz] estimated from the residuals.
            The back end owns k; a re-selection (:meth:`reset`) keeps it (the sensor did not change).
        noise_forgetting, noise_scale_min, noise_scale_max, noise_clip: its forgetting factor, bounds and
            winsorising quantile (:class:`~torchtrack.filter.noise_scale.NoiseScale`).
        process_scale: improvement over the paper (False = off): the online process-noise scale per sequence and
            block (:mod:`torchtrack.filter.process_scale`): Q = c Q0 with c (B, 2) [ang, lin] estimated from the
            update's velocity corrections. Owned and kept across re-selections like the noise scale.
        process_forgetting, process_scale_min, process_scale_max, process_clip: its forgetting factor, bounds and
            winsorising quantile (:class:`~torchtrack.filter.process_scale.ProcessScale`).
    """

    fuses = True  # a frame update can be redone from a snapshot (PoseBackend)

    def __init__(
        self,
        ekf: FusionEKF,
        gate: float | None = EKFBackendConfig.gate,
        refit: float | None = EKFBackendConfig.refit,
        noise_scale: bool = EKFBackendConfig.noise_scale,
        noise_forgetting: float = EKFBackendConfig.noise_forgetting,
        noise_scale_min: float = EKFBackendConfig.noise_scale_min,
        noise_scale_max: float = EKFBackendConfig.noise_scale_max,
        noise_clip: float | None = EKFBackendConfig.noise_clip,
        process_scale: bool = EKFBackendConfig.process_scale,
        process_forgetting: float = EKFBackendConfig.process_forgetting,
        process_scale_min: float = EKFBackendConfig.process_scale_min,
        process_scale_max: float = EKFBackendConfig.process_scale_max,
        process_clip: float | None = EKFBackendConfig.process_clip,
    ) -> None:
        for name, p in (("gate", gate), ("refit", refit)):
            if p is not None and not 0.0 < p < 1.0:
                raise ValueError(f"EKFBackend: {name} is a probability in (0, 1), got {p}")
        self.ekf = ekf
        self.gate, self.refit = gate, refit
        self.noise = NoiseScale(noise_forgetting, noise_scale_min, noise_scale_max, noise_clip) if noise_scale else None
        self.process = (
            ProcessScale(process_forgetting, process_scale_min, process_scale_max, process_clip)
            if process_scale
            else None
        )
        self.state: FilterState | None = None
        self.scale_state: ScaleState | None = None  # the online noise scale's, (B, 2) each
        self.process_state: ScaleState | None = None  # the online process-noise scale's, (B, 2) each

    def start(self) -> None:
        """A new run: the filter state and the noise and process scales are forgotten (the scales are the sensor's
        and the motion's within a run, a re-selection keeps them; a new run starts them at 1 again)."""
        self.state, self.scale_state, self.process_state = None, None, None

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Start the sequences in ``mask`` (B,) over at ``T_cam_obj`` (B, 4, 4), zero velocity, initial covariance.
        The noise and process scales are kept (they start at 1 after :meth:`start` or with a new batch size)."""
        init = self.ekf.initial_state(T_cam_obj)
        if self.state is None or self.state.mean.shape[0] != T_cam_obj.shape[0]:
            if not bool(mask.all()):
                raise ValueError(
                    "EKFBackend.reset: the first reset (after start, or a new batch size) must cover every sequence"
                )
            self.state = init
            B = T_cam_obj.shape[0]
            self.scale_state = None if self.noise is None else self.noise.initial(B, device=T_cam_obj.device)
            self.process_state = None if self.process is None else self.process.initial(B, device=T_cam_obj.device)
            return
        self.state = init.select(mask, self.state)

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Move the pose to ``T_cam_obj`` (B, 4, 4) where ``mask`` (B,) is True, keeping velocity and covariance (a
        pose corrected outside the filter is taken as its new mean, not fused as a measurement)."""
        if self.state is None:
            raise ValueError("EKFBackend: call reset(T_cam_obj, mask) before set_pose")
        self.state = self.ekf.with_pose(self.state, T_cam_obj, mask)

    def pose_covariance(self) -> Tensor | None:
        """(B, 6, 6) the posterior covariance of the pose as a left SE(3) twist ``(v, omega)`` of ``T_cam_obj``
        (:func:`~torchtrack.filter.error_state.left_twist_covariance`): the prior a keyframe window gives the current
        camera. None before the first reset, or with the paper's Euler state (its pose block is not a twist)."""
        if self.state is None or self.ekf.state != "se3":
            return None
        return left_twist_covariance(self.state.cov[:, :6, :6], self.state.T_cam_obj)

    def measurement_scale(self) -> Tensor | None:
        """(B, 2) the online noise scale's current factors [pix, xyz] of the weighting's R (None when it is off or
        before the first reset): what a keyframe window weighing the same measurements multiplies them by."""
        return None if self.scale_state is None else self.scale_state.scale

    def snapshot(self) -> BackendSnapshot:
        """The back end's whole state now (the filter's, the noise and the process scales'), for :meth:`restore`: a
        frame's update can be redone from the same start with more measurements of that frame (re-acquired
        landmarks)."""
        return BackendSnapshot(self.state, self.scale_state, self.process_state)

    def restore(self, snapshot: BackendSnapshot, mask: Tensor | None = None) -> None:
        """Go back to a :meth:`snapshot` (tensors are never modified in place, so it is the state as it was), for the
        sequences where ``mask`` (B,) is True (default: all)."""
        state, scale_state, process_state = snapshot
        if mask is None:
            self.state, self.scale_state, self.process_state = state, scale_state, process_state
            return
        self.state = state.select(mask, self.state)
        if scale_state is not None:
            self.scale_state = _kept(scale_state, self.scale_state, mask)
        if process_state is not None:
            self.process_state = _kept(process_state, self.process_state, mask)

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> FrameUpdate:
        """One frame: the named result of :func:`ekf_frame`; the posterior becomes the state of the sequences where
        ``active`` (B,) is True (default: all); ended sequences keep theirs (no prediction runs on without them), and
        their noise and process scales (the result's ``noise`` and ``process`` are the back end's after the frame)."""
        if self.state is None:
            raise ValueError("EKFBackend: call reset(T_cam_obj, mask) before the first frame")
        out = ekf_frame(self.ekf, self.state, obs, var, gate=self.gate, refit=self.refit, noise_scale=self.noise,
                        scale_state=self.scale_state, process_scale=self.process,
                        process_state=self.process_state)  # fmt: skip
        self.state = out.posterior if active is None else out.posterior.select(active, self.state)
        if out.noise is not None:
            out = out._replace(noise=_kept(out.noise, self.scale_state, active))
            self.scale_state = out.noise
        if out.process is not None:
            out = out._replace(process=_kept(out.process, self.process_state, active))
            self.process_state = out.process
        near = out.mean[:, 1].abs() > 1.4  # only the sequences this step updated
        if self.ekf.euler and bool((near if active is None else near & active).any()):
            log.warning("EKFBackend: |theta| > 80 deg, near the Euler singularity; re-select the model frame")
        return out


def _kept(new: ScaleState, old: ScaleState | None, active: Tensor | None) -> ScaleState:
    """A running scale after a frame: ``new`` where ``active`` (B,) is True (default: all), ``old`` elsewhere."""
    if active is None or old is None:
        return new
    return ScaleState(*(torch.where(active[:, None], n, o) for n, o in zip(new, old, strict=True)))


class Registration(NamedTuple):
    """One frame of a :class:`RegistrationBackend`, batched over B.

    Attributes:
        T_cam_obj: (B, 4, 4) the registered object pose in the depth camera.
        used: (B, N) bool, the 3D-3D correspondences it was given (the observation's valid features).
        weights: (B, N) the per-correspondence weights (``1 / var_xyz``), or None when unweighted.
    """

    T_cam_obj: Tensor
    used: Tensor
    weights: Tensor | None


class RegistrationBackend:
    """A 3D-3D registration baseline (Horn, ICP or CPD) started from the previous pose (paper §IV).

    ``estimator(points_obj, points_d, valid, T_prev, weights)`` returns ``T_cam_obj`` (B, 4, 4).
    With ``weighted`` the 3D variances of eq. (14) become weights ``1 / var_xyz``. Owns the previous pose.
    """

    fuses = False  # each step registers anew (PoseBackend)

    def __init__(self, estimator, weighted: bool = False) -> None:
        self.estimator = estimator
        self.weighted = weighted
        self.T_prev: Tensor | None = None

    def start(self) -> None:
        """A new run: no previous pose."""
        self.T_prev = None

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        if self.T_prev is None:
            self.T_prev = T_cam_obj.clone()
        self.T_prev = torch.where(mask[:, None, None], T_cam_obj, self.T_prev)

    def pose_covariance(self) -> None:
        """A registration has no covariance."""
        return None

    def measurement_scale(self) -> None:
        return None

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """The previous pose of the sequences in ``mask`` (B,) becomes ``T_cam_obj`` (B, 4, 4) (no other state)."""
        if self.T_prev is None:
            raise ValueError("RegistrationBackend: call reset(T_cam_obj, mask) before set_pose")
        self.T_prev = torch.where(mask[:, None, None], T_cam_obj.to(self.T_prev.dtype), self.T_prev)

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> Registration:
        """One frame; the result becomes the previous pose of the sequences where ``active`` (B,) is True."""
        if self.T_prev is None:
            raise ValueError("RegistrationBackend: call reset(T_cam_obj, mask) before the first frame")
        weights = 1.0 / var.var_xyz.clamp_min(1e-12) if self.weighted else None
        T_prev = self.T_prev.to(obs.points_obj.dtype)
        T = self.estimator(obs.points_obj, obs.points_d, obs.valid, T_prev, weights)
        self.T_prev = T if active is None else torch.where(active[:, None, None], T, T_prev)
        return Registration(T, obs.valid, weights)
