"""EKF fusion of 2D (colour pixel) and 3D (depth point) measurements: the paper's tracker core (§III-A).

:func:`fuse` is the pure batched update (eqs. (6)–(7), (15)); :class:`FusionEKF` holds the filter's parameters and
its pure steps (:class:`FilterState` in, :class:`FilterState` out). The one stateful filter is the tracker's back
end, :class:`torchtrack.filter.backend.EKFBackend`, which runs
:func:`~torchtrack.filter.frame.ekf_frame` once per frame.

Two parametrisations of the pose (``FusionEKF(state=...)``): ``"se3"`` (default), the local error state on SE(3)
of :mod:`torchtrack.filter.error_state`, regular at every attitude; ``"euler"``, the paper's eq. (2) (Euler angles,
:mod:`torchtrack.filter.models`), singular at 90 degrees of pitch (``+experiment=paper`` selects it).

Frames: ``cam`` is the DEPTH camera (the paper's ``d``); ``T_cam_obj`` = ``(R_do, t_do)``. The object frame
is expected to be centred at the model's centroid (the tracker passes ``points_obj`` already centred,
with axes of the model camera): the Euler angles then start near 0 and rotations about the object
centre are well-conditioned (decoupled from translation). The filter does not check this.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchtrack.filter import ekf, error_state
from torchtrack.filter.models import (
    STATE_SIZE,
    constant_velocity,
    measure_analytic,
    measure_single,
    pose_to_state,
    state_to_pose,
)
from torchtrack.filter.noise_scale import NoiseScale

JacobianMode = Literal["forward", "reverse", "analytic"]
StateMode = Literal["se3", "euler"]


def linearize(
    mean: Tensor,
    points_obj: Tensor,
    K: Tensor,
    T_color_depth: Tensor,
    *,
    jacobian: JacobianMode = "analytic",
    nominal: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Eqs. (6)-(7) and their Jacobian at ``mean`` (B, 12) for model points (B, N, 3): h (B, N, 5), H (B, N, 5, 12).

    ``nominal`` None: ``mean`` is the paper's Euler state (:mod:`~torchtrack.filter.models`); a pose (B, 4, 4):
    ``mean`` is the error state about it (:mod:`~torchtrack.filter.error_state`), h is evaluated at
    ``nominal (+) mean`` and H is with respect to the error state. ``jacobian``: "analytic" (closed form) or
    "forward" / "reverse" (``torch.func`` autograd of the per-feature model, :func:`ekf.linearize`). Inputs are cast
    to ``mean``'s dtype.
    """
    dt = mean.dtype
    points_obj, K, T_color_depth = points_obj.to(dt), K.to(dt), T_color_depth.to(dt)
    if nominal is not None:
        nominal = nominal.to(dt)
        if jacobian == "analytic":
            return tuple(error_state.measure_analytic(mean, nominal, points_obj, K, T_color_depth))
        seq = (nominal[:, :3, :3], nominal[:, :3, 3], K, T_color_depth)
        return ekf.linearize(error_state.measure_single, mean, (points_obj,), seq, mode=jacobian)
    if jacobian == "analytic":
        return tuple(measure_analytic(mean, points_obj, K, T_color_depth))
    return ekf.linearize(measure_single, mean, (points_obj,), (K, T_color_depth), mode=jacobian)


def fuse(
    mean: Tensor,
    cov: Tensor,
    points_obj: Tensor,
    points_d: Tensor,
    pixels: Tensor,
    valid: Tensor,
    var_xyz: Tensor,
    var_pix: Tensor,
    K: Tensor,
    T_color_depth: Tensor,
    *,
    valid_xyz: Tensor | None = None,
    valid_pix: Tensor | None = None,
    form: Literal["information", "gain"] = "information",
    iterations: int = 1,
    jacobian: JacobianMode = "analytic",
    linearization: tuple[Tensor, Tensor] | None = None,
    nominal: Tensor | None = None,
) -> ekf.Update:
    """One EKF update with N features of 5 measurements each, eqs. (6)–(7), (15).

    Args:
        mean: (B, 12) predicted state; cov: (B, 12, 12). With ``nominal`` (B, 4, 4), the error state about that
            nominal pose (:mod:`~torchtrack.filter.error_state`; the returned mean is the error to inject), else the
            paper's Euler state.
        points_obj: (B, N, 3) model points X_o (object frame, centred at the model centroid).
        points_d: (B, N, 3) measured 3D points X_d in the depth camera (eq. (6)).
        pixels: (B, N, 2) measured pixels in the colour image (eq. (7)).
        valid: (B, N) bool; valid_xyz, valid_pix: optional (B, N) bool that additionally mask only the 3D part,
            only the pixel part.
        var_xyz, var_pix: (B, N) per-feature variances (m^2, px^2), e.g. from eqs. (11)–(14).
        K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4) depth -> colour extrinsic (R_dv, t_dv).
        form, iterations: see :func:`torchtrack.filter.ekf.update`.
        linearization: (h (B, N, 5), H (B, N, 5, 12)) at ``mean`` (:func:`linearize`), when the caller has it
            already: the first iteration then skips linearising.
        jacobian: "analytic" (default) uses :func:`~torchtrack.filter.models.measure_analytic`; "forward" /
            "reverse" take ``vmap(jacfwd / jacrev(measure_single))`` by autograd. Equal to 1e-10 (tested);
            analytic is the default for speed: ~0.5 ms vs ~3.5-7 ms for jacfwd at N = 300 on a laptop-class
            CPU (experiments/bench/bench_ekf.py), which would exceed the filter's 3 ms per-frame budget.
    """
    B, N = valid.shape
    if points_obj.shape != (B, N, 3) or points_d.shape != (B, N, 3) or pixels.shape != (B, N, 2):
        raise ValueError(
            f"fuse: expected points_obj, points_d (B, N, 3), pixels (B, N, 2) with (B, N) = {(B, N)}; got "
            f"{tuple(points_obj.shape)}, {tuple(points_d.shape)}, {tuple(pixels.shape)}"
        )
    if var_xyz.shape != (B, N) or var_pix.shape != (B, N) or K.shape != (B, 3, 3) or T_color_depth.shape != (B, 4, 4):
        raise ValueError("fuse: var_xyz, var_pix must be (B, N), K (B, 3, 3), T_color_depth (B, 4, 4)")
    dt = mean.dtype
    z = torch.cat([points_d, pixels], -1).to(dt)  # B,N,5
    var = torch.cat([var_xyz[..., None].expand(B, N, 3), var_pix[..., None].expand(B, N, 2)], -1).to(dt)
    v3 = valid if valid_xyz is None else valid & valid_xyz
    v2 = valid if valid_pix is None else valid & valid_pix
    valid5 = torch.cat([v3[..., None].expand(B, N, 3), v2[..., None].expand(B, N, 2)], -1)

    def lin(x, fi, si):
        return linearize(x, fi[0], *si, jacobian=jacobian, nominal=nominal)

    return ekf.update(
        mean,
        cov,
        z,
        var,
        valid5,
        measure_single,
        (points_obj.to(dt),),
        (K.to(dt), T_color_depth.to(dt)),
        form=form,
        iterations=iterations,
        linearizer=lin,
        linearization=linearization,
    )


class FilterState(NamedTuple):
    """The filter's belief about B sequences.

    Attributes:
        mean: (B, 12) state mean: the paper's Euler state (eq. 2), or the SE(3) error state ``[0, 0, omega, v]``
            (its pose error is zero between frames, :mod:`~torchtrack.filter.error_state`).
        cov: (B, 12, 12) its covariance.
        T_cam_obj: (B, 4, 4) the pose (the Euler state's, or the nominal pose).
    """

    mean: Tensor
    cov: Tensor
    T_cam_obj: Tensor

    def select(self, mask: Tensor, other: FilterState) -> FilterState:
        """This state where ``mask`` (B,) is True, ``other``'s elsewhere."""
        return FilterState(
            *(torch.where(mask.reshape(-1, *[1] * (a.dim() - 1)), a, b) for a, b in zip(self, other, strict=True))
        )


class FusionEKF:
    """12-state EKF over B sequences: constant-velocity prediction, 2D+3D fusion update; parameters and pure steps.

    The methods (:meth:`initial_state`, :meth:`predicted`, :meth:`linearize_at`, :meth:`updated`, :meth:`injected`,
    :meth:`with_pose`) take and return :class:`FilterState` and never keep state: the back end
    (:class:`~torchtrack.filter.backend.EKFBackend`, :func:`~torchtrack.filter.frame.ekf_frame`) is built
    from them.

    Args:
        sigma_ang_acc: angular acceleration noise std (rad/s^2) of eqs. (3)–(4) (Euler-angle accelerations for
            ``state="euler"``).
        sigma_lin_acc: linear acceleration noise std (m/s^2).
        init_sigma_angle, init_sigma_trans: initial pose std (rad, m) after a (re-)selection.
        init_sigma_ang_vel, init_sigma_lin_vel: initial velocity std (rad/s, m/s).
        iterations: 1 = EKF (paper); > 1 = iterated EKF.
        form: "information" (fast, default) or "gain" (paper's eq. (15), O((5N)^3)).
        jacobian: "analytic" (closed form, default: the fastest, equal to autograd to 1e-10), "forward" (autograd
            jacfwd) or "reverse" (jacrev).
        state: "se3" (default: the local error state on SE(3), regular at every attitude,
            :mod:`~torchtrack.filter.error_state`) or "euler" (the paper's eq. (2), singular at 90 degrees pitch).
        gate: improvement over the paper (None = off): chi-square quantile of the innovation gate of each frame
            (:func:`~torchtrack.filter.frame.ekf_frame`). Nearest-pixel depth at occlusion boundaries and LK slips
            produce outliers of metres or pixels that a Gaussian update cannot absorb.
        refit: improvement over the paper (None = off): chi-square quantile of the refit at the updated pose: the gate
            only sees outliers larger than the prediction's uncertainty; the refit catches the smaller ones that would
            otherwise bias this frame's pose.
        noise_scale: improvement over the paper (False = off): the online noise scale per sequence and block
            (:mod:`torchtrack.filter.noise_scale`), R = k R0 with k (B, 2) [pix, xyz] estimated from the residuals.
        noise_forgetting, noise_scale_min, noise_scale_max, noise_clip: its forgetting factor, bounds and winsorising
            quantile (:class:`~torchtrack.filter.noise_scale.NoiseScale`).
        dtype: filter state dtype (float64 default: the 12 x 12 algebra is cheap and well-conditioned).

    Poses and covariances are returned in ``dtype``.
    """

    def __init__(
        self,
        sigma_ang_acc: float = 3.0,
        sigma_lin_acc: float = 2.0,
        init_sigma_angle: float = 0.001,
        init_sigma_trans: float = 0.001,
        init_sigma_ang_vel: float = 1.0,
        init_sigma_lin_vel: float = 0.5,
        iterations: int = 1,
        form: Literal["information", "gain"] = "information",
        jacobian: JacobianMode = "analytic",
        state: StateMode = "se3",
        gate: float | None = 0.999,
        refit: float | None = 0.999,
        noise_scale: bool = True,
        noise_forgetting: float = 0.98,
        noise_scale_min: float = 0.01,
        noise_scale_max: float = 100.0,
        noise_clip: float | None = 0.9,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        for name, p in (("gate", gate), ("refit", refit)):
            if p is not None and not 0.0 < p < 1.0:
                raise ValueError(f"FusionEKF: {name} is a probability in (0, 1), got {p}")
        if form not in ("information", "gain") or jacobian not in ("forward", "reverse", "analytic"):
            raise ValueError(f"FusionEKF: bad form={form!r} or jacobian={jacobian!r}")
        if state not in ("se3", "euler"):
            raise ValueError(f"FusionEKF: state must be 'se3' or 'euler', got {state!r}")
        if iterations < 1:
            raise ValueError("FusionEKF: iterations must be >= 1")
        self.sigma_ang_acc, self.sigma_lin_acc = sigma_ang_acc, sigma_lin_acc
        init_std = [init_sigma_angle] * 3 + [init_sigma_trans] * 3 + [init_sigma_ang_vel] * 3 + [init_sigma_lin_vel] * 3
        self.init_var = torch.tensor(init_std, dtype=dtype, device="cpu") ** 2  # moved to each pose's device
        self.iterations, self.form, self.jacobian, self.state, self.dtype = iterations, form, jacobian, state, dtype
        self.gate, self.refit = gate, refit
        self.noise = NoiseScale(noise_forgetting, noise_scale_min, noise_scale_max, noise_clip) if noise_scale else None

    @property
    def euler(self) -> bool:
        """True for the paper's Euler state."""
        return self.state == "euler"

    def initial_state(self, T_cam_obj: Tensor, velocity: Tensor | None = None) -> FilterState:
        """The state right after a (re-)selection: pose ``T_cam_obj`` (B, 4, 4), ``velocity`` (B, 6) in the state's
        coordinates (default 0: Euler-angle rates or ``[omega, v]``), the initial covariance."""
        B = T_cam_obj.shape[0]
        T = T_cam_obj.to(self.dtype)
        vel = None if velocity is None else velocity.to(self.dtype)
        if self.euler:
            x0 = pose_to_state(T, vel)
            T = state_to_pose(x0)
        else:
            zero = torch.zeros(B, 6, dtype=T.dtype, device=T.device)
            x0 = torch.cat([zero, zero if vel is None else vel], -1)  # the pose error is 0 at the nominal pose
        P0 = torch.diag_embed(self.init_var.to(T.device).expand(B, STATE_SIZE))
        return FilterState(x0, P0, T)

    def predicted(self, state: FilterState, dt: Tensor) -> FilterState:
        """Constant-velocity prediction, eqs. (3)-(4), over ``dt`` (B,) seconds."""
        if dt.shape != (state.mean.shape[0],):
            raise ValueError(f"predict: dt must be ({state.mean.shape[0]},), got {tuple(dt.shape)}")
        dt = dt.to(self.dtype)
        if self.euler:
            F, Q = constant_velocity(dt, self.sigma_ang_acc, self.sigma_lin_acc)
            mean, cov = ekf.predict(state.mean, state.cov, F, Q)
            return FilterState(mean, cov, state_to_pose(mean))
        F, Q = error_state.transition(dt, state.mean[:, 6:9], self.sigma_ang_acc, self.sigma_lin_acc)
        # the error's mean stays [0, v]: the nominal moves
        _, cov = ekf.predict(state.mean, state.cov, F, Q)
        return FilterState(
            state.mean, cov, error_state.predict_nominal(state.T_cam_obj, state.mean[:, 6:], dt, F[:, :3, :3])
        )

    def linearize_at(
        self, state: FilterState, points_obj: Tensor, K: Tensor, T_color_depth: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(h (B, N, 5), H (B, N, 5, 12)) of eqs. (6)-(7) at ``state`` with this filter's Jacobian mode."""
        if self.euler or self.jacobian != "analytic":
            return linearize(
                state.mean, points_obj, K, T_color_depth, jacobian=self.jacobian, nominal=self._nominal(state)
            )
        # the SE(3) state's pose error is 0 between frames: error_state.measure_analytic at dx = 0, without Exp(0), J_l(0)
        return error_state.measure_at_nominal(state.T_cam_obj, points_obj, K, T_color_depth)

    def updated(self, state: FilterState, points_obj, points_d, pixels, valid_xyz, valid_pix, var_xyz, var_pix, K,
                T_color_depth, linearization=None) -> ekf.Update:  # fmt: skip
        """The measurement update (:func:`fuse`, eq. 15) of ``state`` with this filter's form and iterations; the 3D
        part of feature i is used where ``valid_xyz`` (B, N), its pixel where ``valid_pix``. The result is in the
        state's coordinates (for "se3", the error to inject): :meth:`injected` makes it the posterior."""
        return fuse(
            state.mean, state.cov, points_obj, points_d, pixels, valid_xyz | valid_pix, var_xyz, var_pix, K,
            T_color_depth, valid_xyz=valid_xyz, valid_pix=valid_pix, form=self.form, iterations=self.iterations,
            jacobian=self.jacobian, linearization=linearization, nominal=self._nominal(state),
        )  # fmt: skip

    def injected(self, prior: FilterState, update: ekf.Update) -> FilterState:
        """The posterior :class:`FilterState` of an :meth:`updated` ``prior``: for "euler" the update's mean and
        covariance; for "se3" the error injected into the nominal pose (``T <- T (+) dx``), the pose error reset to 0
        and the covariance moved to the new nominal (``G P G^T``, :func:`~torchtrack.filter.error_state.reset_jacobian`)."""
        if self.euler:
            return FilterState(update.mean, update.cov, state_to_pose(update.mean))
        dx = update.mean
        mean = torch.cat([torch.zeros_like(dx[:, :6]), dx[:, 6:]], -1)
        cov = error_state.reset_covariance(update.cov, dx)
        return FilterState(mean, cov, error_state.inject(prior.T_cam_obj, dx))

    def with_pose(self, state: FilterState, T_cam_obj: Tensor, mask: Tensor) -> FilterState:
        """``state`` with its pose replaced by ``T_cam_obj`` (B, 4, 4) where ``mask`` (B,); velocity and covariance
        kept (e.g. a pose corrected outside the filter). Euler angles are unwrapped next to the old ones."""
        T = T_cam_obj.to(state.T_cam_obj.dtype)
        if self.euler:
            x = pose_to_state(T)[:, :6]
            old = state.mean[:, :6]
            ang = old[:, :3] + torch.remainder(x[:, :3] - old[:, :3] + torch.pi, 2 * torch.pi) - torch.pi
            mean = torch.cat([ang, x[:, 3:], state.mean[:, 6:]], 1)
            new = FilterState(mean, state.cov, state_to_pose(mean))
        else:
            new = FilterState(state.mean, state.cov, T)
        return new.select(mask, state)

    def _nominal(self, state: FilterState) -> Tensor | None:
        return None if self.euler else state.T_cam_obj
