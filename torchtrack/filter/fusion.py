"""EKF fusion of 2D (colour pixel) and 3D (depth point) measurements: the paper's tracker core (§III-A).

:func:`fuse` is the pure batched update (eqs. (6)–(7), (15)); :class:`FusionEKF` is the thin stateful
wrapper that the tracker calls once per frame: ``predict(dt)`` then ``update(...)``.

Frames: ``cam`` is the DEPTH camera (the paper's ``d``); ``T_cam_obj`` = ``(R_do, t_do)``. The object frame
is expected to be centred at the model's centroid (the tracker passes ``points_obj`` already centred,
with axes of the model camera): the Euler angles then start near 0 and rotations about the object
centre are well-conditioned (decoupled from translation). The filter does not check this.
"""

from __future__ import annotations

import logging
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchtrack.config import FilterConfig
from torchtrack.filter import ekf
from torchtrack.filter.models import (
    STATE_SIZE,
    constant_velocity,
    measure_analytic,
    measure_single,
    pose_to_state,
    state_to_pose,
)

log = logging.getLogger(__name__)

JacobianMode = Literal["forward", "reverse", "analytic"]


class PoseEstimate(NamedTuple):
    """Filter output after an update.

    Attributes:
        T_cam_obj: (B, 4, 4) object pose in the depth camera (posterior mean).
        covariance: (B, 12, 12) posterior state covariance.
        state: (B, 12) posterior state (angles, translation, their velocities).
        innovation: (B, N, 5) ``z - h(predicted state)``: 3D (m) then pixel (px) residuals; 0 where invalid.
        num_valid: (B,) number of valid features used.
        updated: (B,) bool, False where no valid feature was given (the prediction was kept).
    """

    T_cam_obj: Tensor
    covariance: Tensor
    state: Tensor
    innovation: Tensor
    num_valid: Tensor
    updated: Tensor


def linearize(
    mean: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor, *, jacobian: JacobianMode = "analytic"
) -> tuple[Tensor, Tensor]:
    """Eqs. (6)-(7) and their Jacobian at ``mean`` (B, 12) for model points (B, N, 3): h (B, N, 5), H (B, N, 5, 12).

    ``jacobian``: "analytic" (:func:`~torchtrack.filter.models.measure_analytic`) or "forward" / "reverse"
    (``torch.func`` autograd of :func:`~torchtrack.filter.models.measure_single`, :func:`ekf.linearize`).
    Inputs are cast to ``mean``'s dtype.
    """
    dt = mean.dtype
    points_obj, K, T_color_depth = points_obj.to(dt), K.to(dt), T_color_depth.to(dt)
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
) -> ekf.Update:
    """One EKF update with N features of 5 measurements each, eqs. (6)–(7), (15).

    Args:
        mean: (B, 12) predicted state; cov: (B, 12, 12).
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
            CPU (experiments/bench_ekf.py), which would exceed the filter's 3 ms per-frame budget.
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
        return linearize(x, fi[0], *si, jacobian=jacobian)

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
    """The filter's belief about B sequences. mean: (B, 12) state; cov: (B, 12, 12) covariance."""

    mean: Tensor
    cov: Tensor


class FusionEKF:
    """12-state EKF over B sequences: constant-velocity prediction, 2D+3D fusion update.

    The pure methods (:meth:`initial_state`, :meth:`predicted`, :meth:`linearize_at`, :meth:`updated`) take and
    return a :class:`FilterState` and never touch ``self``'s state: the differentiable back end
    (:func:`torchtrack.estimators.backends.ekf_frame`) is built from them. ``reset``/``predict``/``update`` keep a state of
    their own on top of them, for direct use.

    Args:
        sigma2_pix: default pixel variance (px^2), used when update() gets no var_pix.
        sigma2_xyz: default 3D variance (m^2), used when update() gets no var_xyz.
        sigma_ang_acc: Euler-angle acceleration noise std (rad/s^2) of eqs. (3)–(4).
        sigma_lin_acc: linear acceleration noise std (m/s^2).
        init_sigma_angle, init_sigma_trans: initial pose std (rad, m) after :meth:`reset`.
        init_sigma_ang_vel, init_sigma_lin_vel: initial velocity std (rad/s, m/s) after :meth:`reset`.
        iterations: 1 = EKF (paper); > 1 = iterated EKF.
        form: "information" (fast, default) or "gain" (paper's eq. (15), O((5N)^3)).
        jacobian: "analytic" (closed form, default: the fastest, equal to autograd to 1e-10), "forward" (autograd
            jacfwd) or "reverse" (jacrev).
        dtype: filter state dtype (float64 default: the 12 x 12 algebra is cheap and well-conditioned).

    Poses and covariances are returned in ``dtype``.
    """

    def __init__(
        self,
        sigma2_pix: float = 1.0,
        sigma2_xyz: float = 1e-4,
        sigma_ang_acc: float = FilterConfig.sigma_ang_acc,
        sigma_lin_acc: float = FilterConfig.sigma_lin_acc,
        init_sigma_angle: float = FilterConfig.init_sigma_angle,
        init_sigma_trans: float = FilterConfig.init_sigma_trans,
        init_sigma_ang_vel: float = FilterConfig.init_sigma_ang_vel,
        init_sigma_lin_vel: float = FilterConfig.init_sigma_lin_vel,
        iterations: int = FilterConfig.iterations,
        form: Literal["information", "gain"] = FilterConfig.form,
        jacobian: JacobianMode = FilterConfig.jacobian,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        if form not in ("information", "gain") or jacobian not in ("forward", "reverse", "analytic"):
            raise ValueError(f"FusionEKF: bad form={form!r} or jacobian={jacobian!r}")
        if iterations < 1 or min(sigma2_pix, sigma2_xyz) <= 0:
            raise ValueError("FusionEKF: iterations must be >= 1 and variances > 0")
        self.sigma2_pix, self.sigma2_xyz = sigma2_pix, sigma2_xyz
        self.sigma_ang_acc, self.sigma_lin_acc = sigma_ang_acc, sigma_lin_acc
        init_std = [init_sigma_angle] * 3 + [init_sigma_trans] * 3 + [init_sigma_ang_vel] * 3 + [init_sigma_lin_vel] * 3
        self.init_var = torch.tensor(init_std, dtype=dtype) ** 2
        self.iterations, self.form, self.jacobian, self.dtype = iterations, form, jacobian, dtype
        self.mean: Tensor | None = None  # (B, 12)
        self.cov: Tensor | None = None  # (B, 12, 12)

    # -- pure: FilterState in, FilterState out ------------------------------------------------------------
    def initial_state(self, T_cam_obj: Tensor, velocity: Tensor | None = None) -> FilterState:
        """The state right after a (re-)selection: pose ``T_cam_obj`` (B, 4, 4), ``velocity`` (B, 6) (default 0),
        the initial covariance."""
        B = T_cam_obj.shape[0]
        x0 = pose_to_state(T_cam_obj.to(self.dtype), None if velocity is None else velocity.to(self.dtype))
        return FilterState(x0, torch.diag_embed(self.init_var.to(x0.device).expand(B, STATE_SIZE)))

    def predicted(self, state: FilterState, dt: Tensor) -> FilterState:
        """Constant-velocity prediction, eqs. (3)-(4), over ``dt`` (B,) seconds."""
        if dt.shape != (state.mean.shape[0],):
            raise ValueError(f"predict: dt must be ({state.mean.shape[0]},), got {tuple(dt.shape)}")
        F, Q = constant_velocity(dt.to(self.dtype), self.sigma_ang_acc, self.sigma_lin_acc)
        return FilterState(*ekf.predict(state.mean, state.cov, F, Q))

    def linearize_at(self, mean: Tensor, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> tuple[Tensor, Tensor]:
        """(h (B, N, 5), H (B, N, 5, 12)) of eqs. (6)-(7) at ``mean`` with this filter's Jacobian mode."""
        return linearize(mean, points_obj, K, T_color_depth, jacobian=self.jacobian)

    def updated(self, state: FilterState, points_obj, points_d, pixels, valid_xyz, valid_pix, var_xyz, var_pix, K,
                T_color_depth, linearization=None) -> ekf.Update:  # fmt: skip
        """The measurement update (:func:`fuse`, eq. 15) of ``state`` with this filter's form and iterations; the 3D
        part of feature i is used where ``valid_xyz`` (B, N), its pixel where ``valid_pix``."""
        return fuse(
            state.mean, state.cov, points_obj, points_d, pixels, valid_xyz | valid_pix, var_xyz, var_pix, K,
            T_color_depth, valid_xyz=valid_xyz, valid_pix=valid_pix, form=self.form, iterations=self.iterations,
            jacobian=self.jacobian, linearization=linearization,
        )  # fmt: skip

    # -- stateful convenience ----------------------------------------------------------------------------
    @property
    def T_cam_obj(self) -> Tensor:
        """(B, 4, 4) current object pose in the depth camera (the latest mean)."""
        return state_to_pose(self._state()[0])

    def reset(self, T_cam_obj: Tensor, mask: Tensor | None = None, velocity: Tensor | None = None) -> None:
        """Set pose to ``T_cam_obj``, velocity to ``velocity`` (zero by default), covariance to the initial one.

        Args:
            T_cam_obj: (B, 4, 4) object pose in the depth camera.
            mask: (B,) bool, sequences to reset (default all; the first reset must cover all). The tracker
                re-selects models per sequence.
            velocity: optional (B, 6) state velocity expressed for the NEW object frame (e.g.
                :func:`~torchtrack.filter.models.euler_velocity` of two poses of that frame).
        """
        B = T_cam_obj.shape[0]
        if T_cam_obj.shape != (B, 4, 4) or (mask is not None and mask.shape != (B,)):
            raise ValueError(f"reset: T_cam_obj must be (B, 4, 4) and mask (B,), got {tuple(T_cam_obj.shape)}")
        mask = torch.ones(B, dtype=torch.bool, device=T_cam_obj.device) if mask is None else mask.to(torch.bool)
        x0, P0 = self.initial_state(T_cam_obj, velocity)
        if self.mean is None or self.mean.shape[0] != B:
            if not bool(mask.all()):
                raise ValueError(f"reset: first reset (or a new batch size {B}) must cover every sequence")
            self.mean, self.cov = x0, P0
            return
        mask = mask.to(x0.device)
        self.mean = torch.where(mask[:, None], x0, self.mean)
        self.cov = torch.where(mask[:, None, None], P0, self.cov)

    def predict(self, dt: Tensor) -> Tensor:
        """Constant-velocity prediction, eqs. (3)–(4), over ``dt`` (B,) seconds. Returns T_cam_obj (B, 4, 4)."""
        self.mean, self.cov = self.predicted(FilterState(*self._state()), dt)
        return self.T_cam_obj

    def linearize(self, points_obj: Tensor, K: Tensor, T_color_depth: Tensor) -> tuple[Tensor, Tensor]:
        """(h (B, N, 5), H (B, N, 5, 12)) of eqs. (6)-(7) at the current mean, with this filter's Jacobian mode; pass
        it to :meth:`update` (``linearization=``) to share it, e.g. with an innovation gate."""
        return self.linearize_at(self._state()[0], points_obj, K, T_color_depth)

    def update(
        self,
        points_obj: Tensor,
        points_d: Tensor,
        pixels: Tensor,
        valid: Tensor,
        var_xyz: Tensor | None = None,
        var_pix: Tensor | None = None,
        K: Tensor | None = None,
        T_color_depth: Tensor | None = None,
        valid_xyz: Tensor | None = None,
        valid_pix: Tensor | None = None,
        linearization: tuple[Tensor, Tensor] | None = None,
    ) -> PoseEstimate:
        """Fuse one frame's features (see :func:`fuse` for shapes). K is required; T_color_depth defaults to I.

        ``var_xyz``/``var_pix`` default to the constant ``sigma2_xyz``/``sigma2_pix``. Sequences with no valid
        feature keep the prediction.
        """
        mean, cov = self._state()
        if K is None:
            raise ValueError("update: K (B, 3, 3) colour intrinsics is required")
        B, N = valid.shape
        like = torch.zeros(B, N, dtype=self.dtype, device=mean.device)
        var_xyz = like + self.sigma2_xyz if var_xyz is None else var_xyz
        var_pix = like + self.sigma2_pix if var_pix is None else var_pix
        if T_color_depth is None:
            T_color_depth = torch.eye(4, dtype=self.dtype, device=mean.device).expand(B, 4, 4)
        out = fuse(
            mean, cov, points_obj, points_d, pixels, valid, var_xyz, var_pix, K, T_color_depth,
            valid_xyz=valid_xyz, valid_pix=valid_pix, form=self.form, iterations=self.iterations, jacobian=self.jacobian,
            linearization=linearization,
        )  # fmt: skip
        self.mean, self.cov = out.mean, out.cov
        theta = self.mean[:, 1].abs()
        if bool((theta > 1.4).any()):
            log.warning("FusionEKF: |theta| > 80 deg, near the Euler singularity; re-select the model frame")
        return PoseEstimate(self.T_cam_obj, self.cov, self.mean, out.innovation, valid.sum(-1), out.num_valid > 0)

    def _state(self) -> tuple[Tensor, Tensor]:
        if self.mean is None or self.cov is None:
            raise ValueError("FusionEKF: call reset(T_cam_obj) before predict/update")
        return self.mean, self.cov
