"""The torchtrack pipeline: select -> track -> weight -> update -> (re-select), batched over B sequences.

Frames. ``cam`` is the depth camera. The object frame ``obj`` is the model frame's depth camera moved
to the centroid of the selected features (so rotations about it stay well-conditioned); the model
points X_o live in it. The tracker estimates ``T_cam_obj`` per frame; with the object static in the
world (scene tracking, or a camera moving around an object), the camera pose follows as
``T_world_depth = T_world_obj @ inv(T_cam_obj)``. The tracker's world is its first depth camera (identity); the
runner writes the colour camera's poses in ground truth's world (:mod:`torchtrack.geometry.rig`, the one conversion
between the two cameras). A re-selection makes the current frame
the new model frame and chains ``T_world_obj`` through the current estimate, so the trajectory stays
continuous.

References:
    O. S. Gedik, A. A. Alatan, "Fusing 2D and 3D Clues for 3D Tracking Using Visual and Range Data",
    FUSION 2013.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchtrack.config import PipelineConfig
from torchtrack.data.frame import FrameBatch
from torchtrack.estimators.backends import BackendResult, Observation, PoseBackend
from torchtrack.estimators.base import masked_mean
from torchtrack.estimators.ransac import ransac_rigid
from torchtrack.filter.models import measure_points
from torchtrack.filter.weighting import Variances, WeightingInputs
from torchtrack.frontend import FrontEnd, PreparedFrame, smooth_depth_mask
from torchtrack.geometry import T_inv, make_T, project, sample_depth, se3_exp, se3_log, transform_points
from torchtrack.image.flow import FlowFrame, TrackResult, prepare_frame
from torchtrack.keyframes import KeyframeAligner, set_backend_pose
from torchtrack.landmarks import LandmarkMap, far_from
from torchtrack.learn.cues import stack_cues, window_cues
from torchtrack.metrics import reprojection_errors


@dataclass
class StepResult:
    """Per-frame outputs, each batched over B.

    Attributes:
        T_cam_obj: (B, 4, 4) float64 object pose in the depth camera: the back end's estimate of the frame as
            tracked, under the model it was tracked with (also at a re-selection or a relocalisation).
        T_world_depth: (B, 4, 4) float64 the DEPTH camera's pose (camera-to-world) for a static object/scene, in the
            tracker's world (its first depth camera is the identity; at a relocalisation the relocalised pose).
            :func:`torchtrack.geometry.rig.color_poses` turns it into the colour camera's pose in ground truth's
            world, as the runner writes it.
        pixels: (B, N, 2) tracked feature pixels in the colour image; valid (B, N).
        winner: (B, N) 0 where the intensity tracker won, 1 where the SIM tracker won, -1 unknown.
        points_obj: (B, N, 3) model points; reprojection_error (B,) eq. (16) in pixels.
        n_features: (B,) surviving features; reselected (B,) bool: a new model was taken this frame.
        d_tim: (B, N) d_TIM of each feature's winning tracker (eq. 10), px; zeros on the first frame.
        observation: what the back end saw this frame (None on the first frame). Its features are those of
            ``pixels``/``valid`` BEFORE the residual drop (``max_residual_px``); a re-selection comes after.
        variances: the weighting's output that went with ``observation`` (None on the first frame).
        cues: (B, N, C) float32 cues (:data:`torchtrack.learn.cues.CUE_NAMES`) of the observation's features,
            zeros where not valid; only when the weighting needs them or the tracker records (else None).
        model_T_cam_obj: (B, 4, 4) float64, where ``reselected``: the pose the back end was reset to when the new
            model was taken at the end of this frame (other rows: the current pose); None when no re-selection.
        estimate: the back end's result for this frame (None on the first frame): the loss check reads it.
        loss: the loss check's :class:`torchtrack.relocalise.LossCheck` (None without a relocaliser).
    """

    T_cam_obj: Tensor
    T_world_depth: Tensor
    pixels: Tensor
    valid: Tensor
    winner: Tensor
    points_obj: Tensor
    reprojection_error: Tensor
    n_features: Tensor
    reselected: Tensor
    d_tim: Tensor
    observation: Observation | None = None
    variances: Variances | None = None
    cues: Tensor | None = None
    model_T_cam_obj: Tensor | None = None
    estimate: BackendResult | None = None
    loss: Any = None


@dataclass
class TrackerState:
    """What the tracker carries from one frame to the next, batched over B; empty (all None) before the first frame.

    Attributes:
        prev: the previous frame as the front end prepared it; timestamp (B,) its time stamps.
        pixels: (B, N, 2) the model's features, tracked to the previous frame (colour pixels); valid (B, N).
        points_obj: (B, N, 3) their model points X_o (object frame).
        age: (B, N) frames since selection; cornerness (B, N, 2) intensity and SIM cornerness of eq. (9) at selection.
        residuals: (B, N) reprojection error (eq. 16) of each feature under ``T_cam_obj``; inf where undefined.
        n_model: (B,) features of the current model when it was taken (the re-selection criterion).
        T_cam_obj: (B, 4, 4) float64 current object pose in the depth camera.
        T_world_obj: (B, 4, 4) float64 the model frame in the tracker's world (first camera = identity).
        velocity: (B, 6) float64 twist per second (v, omega) of the last frame-to-frame motion of the object in the
            camera, ``se3_log(T_cam_obj(t) inv(T_cam_obj(t-1))) / dt``: independent of the model frame, so it
            survives a re-selection (the EKF's velocity restarts at zero there). Zero before the second frame.
        model_flow: the model frame prepared for tracking (row b: sequence b's latest model frame), and
            model_pixels (B, N, 2) each feature's pixel there; kept only with ``track_from_model``.
    """

    prev: PreparedFrame | None = None
    timestamp: Tensor | None = None
    pixels: Tensor | None = None
    valid: Tensor | None = None
    points_obj: Tensor | None = None
    age: Tensor | None = None
    cornerness: Tensor | None = None
    residuals: Tensor | None = None
    n_model: Tensor | None = None
    T_cam_obj: Tensor | None = None
    T_world_obj: Tensor | None = None
    velocity: Tensor | None = None
    model_flow: FlowFrame | None = None
    model_pixels: Tensor | None = None

    @property
    def started(self) -> bool:
        return self.prev is not None

    @property
    def T_world_depth(self) -> Tensor:
        """(B, 4, 4) the current depth camera in the tracker's world (static object/scene)."""
        return self.T_world_obj @ T_inv(self.T_cam_obj)


def pad_to(x: Tensor, n: int) -> Tensor:
    """Pad (or keep) the feature dimension (dim 1) of x to n with zeros (False for masks)."""
    if x.shape[1] >= n:
        return x
    pad = torch.zeros(x.shape[0], n - x.shape[1], *x.shape[2:], dtype=x.dtype, device=x.device)
    return torch.cat([x, pad], dim=1)


_FEATURE_FIELDS = ("pixels", "valid", "points_obj", "age", "cornerness")  # (B, N, ...) per-feature state


class Tracker:
    """Model-free RGB-D rigid tracker (paper §III), batched over B sequences in lockstep.

    Args:
        frontend: per-frame preparation (registered depth, SIM, pyramids).
        region: ``region(depth (B,1,H,W)) -> (B,1,H,W) bool`` region of interest of the model
            (object by depth thresholding, or the whole frame).
        select: ``select(gray, depth, K, roi=, sim=) -> Features``, spatio-textural selection (eq. 9).
        flow: combined LK + TIM tracker (eq. 10), ``flow(prev, next, pixels, valid) -> TrackResult``.
        weighting: per-feature noise variances (eqs. 11-14).
        backend: the pose estimator (fusion EKF or a registration baseline), :class:`PoseBackend`.
        reselect_fraction: take a new model when fewer than this fraction of the model's features survive.
        min_features: ... or fewer than this many.
        edge_step: improvement (None = paper): select only where the depth in a 5x5 window varies by less
            than this fraction of the depth (no features on occlusion boundaries).
        max_residual_px: improvement (None = paper): drop features whose pixel is farther than this from
            the model point reprojected with the updated pose (slipped tracks, non-rigid or wrong depth).
        keep_survivors: improvement (False = paper): a re-selection keeps the features that still track,
            with their model points (re-expressed in the new model frame through the current pose, so
            their world positions do not change), and adds new ones only where no survivor is within
            ``min_separation_px``, up to the selector's count. The surviving points keep anchoring the
            pose, so a re-selection no longer resets the model to one frame's estimate (less drift).
        min_separation_px: new features closer than this to a survivor are not added.
        track_from_model: improvement (False = paper: from the previous frame): every frame LK tracks each feature
            from the model frame (its pixel there, the model frame's images) into the current frame, started at its
            previous pixel or the prediction (``predict_init``); the forward-backward check runs against the model
            frame. Frame-to-frame tracks add each frame's sub-pixel error to the next (they drift ~1 px in 10
            frames on exact images, RESULTS "The object case"); against the model frame a track's error does not
            grow with its age. A re-selection makes the new model frame the reference (survivors at their pixels).
        predict_init: improvement (False = paper): each feature's LK starts where the model point projects under the
            constant-velocity prediction of the pose (``TrackerState.velocity``), not at its previous pixel: under
            fast motion the displacement left to LK is the prediction's error, not the whole motion.
        ransac_threshold_m: improvement (None = off): before the update, keep only the features consistent with
            the best rigid motion of a RANSAC over the 3D-3D pairs (model point, measured point), Horn's closed form
            as the minimal solver (:func:`torchtrack.estimators.ransac.ransac_rigid`); a pair is an inlier within
            this distance times max(1, z^2) (depth noise grows with z^2). LK slips under fast motion are gross
            outliers that pull a Gaussian update before its gate can see them.
        ransac_min_motion_px: ... only in frames whose median tracked displacement exceeds this (large motion).
        record: compute the per-feature cues (:mod:`torchtrack.learn.cues`) of every frame into
            ``StepResult.cues`` even when the weighting does not need them (for the observation cache). Poses are
            the same with and without; a weighting with ``needs_cues = True`` gets them in any case.
        relocaliser: improvement (None = paper): after each frame, the loss check and relocalisation
            (:class:`torchtrack.relocalise.Relocaliser`; it calls :meth:`relocalise`).
        keyframe_align: improvement (False = paper): keep the last ``keyframe_count`` model frames (grey, depth,
            pose) and after each update align the frame densely (photometric + point-to-plane Gauss-Newton on the
            grid downsampled by ``keyframe_factor``) to the nearest of them; the aligned pose replaces the back
            end's (``keyframe_blend`` < 1: that fraction of the way), see :mod:`torchtrack.keyframes`;
            ``keyframe_photometric`` / ``keyframe_geometric`` switch its two terms; ``keyframe_anchor``: which
            corrections move the model frame (``T_world_obj``) instead of the pose the features measure: "older"
            (against a keyframe older than the model frame), "all" or "none".
        landmarks: improvement (False = paper): the model frames are also keyframes whose features outlive their
            model (:class:`torchtrack.landmarks.LandmarkMap`, the last ``landmark_keyframes``, up to
            ``landmark_per_keyframe`` features each): at a re-selection the visible ones are re-tracked from their
            keyframe (LK started at their projection, verified by the forward-backward check, the photometric
            residual and depth) and join the new model at their ORIGINAL world positions, after the survivors and
            before new features; ``landmark_correct``: the camera pose is first re-fitted to them and the survivors
            (:func:`torchtrack.landmarks.refine_pose`) where at least ``landmark_min_inliers`` agree, by moving the
            model frame in the world, so the new model is measured from the corrected pose.
            ``landmark_max_angle_deg``: only landmarks whose keyframe saw them within this angle (camera rotation and
            ray) are re-tracked. ``landmark_every`` > 0: also every that many frames into the current model (no new
            model; a correction moves ``T_world_obj``, never the filter's pose).
        reselect_coverage: improvement (None = paper): the fraction rule (``reselect_fraction``) re-selects only while
            the surviving features occupy fewer than this fraction of the ``reselect_grid`` x ``reselect_grid``
            image cells; ``min_features`` still always does. Under fast motion most of a new model's features can
            fail at once while the rest still span the view: no thrashing from one new model to the next.

    The tracker's model and last estimate live in one :class:`TrackerState`, ``self.state``.
    """

    def __init__(
        self,
        *,
        frontend: FrontEnd,
        region: Callable,
        select: Callable,
        flow: Callable,
        weighting: Callable,
        backend: PoseBackend,
        reselect_fraction: float = PipelineConfig.reselect_fraction,
        min_features: int = PipelineConfig.min_features,
        edge_step: float | None = PipelineConfig.edge_step,
        max_residual_px: float | None = PipelineConfig.max_residual_px,
        keep_survivors: bool = PipelineConfig.keep_survivors,
        min_separation_px: float = PipelineConfig.min_separation_px,
        predict_init: bool = PipelineConfig.predict_init,
        track_from_model: bool = PipelineConfig.track_from_model,
        ransac_threshold_m: float | None = PipelineConfig.ransac_threshold_m,
        ransac_min_motion_px: float = PipelineConfig.ransac_min_motion_px,
        record: bool = PipelineConfig.record,
        relocaliser: Callable | None = None,
        keyframe_align: bool = PipelineConfig.keyframe_align,
        keyframe_count: int = PipelineConfig.keyframe_count,
        keyframe_factor: int = PipelineConfig.keyframe_factor,
        keyframe_blend: float = PipelineConfig.keyframe_blend,
        keyframe_photometric: bool = PipelineConfig.keyframe_photometric,
        keyframe_geometric: bool = PipelineConfig.keyframe_geometric,
        keyframe_anchor: str = PipelineConfig.keyframe_anchor,
        landmarks: bool = PipelineConfig.landmarks,
        landmark_keyframes: int = PipelineConfig.landmark_keyframes,
        landmark_per_keyframe: int = PipelineConfig.landmark_per_keyframe,
        landmark_correct: bool = PipelineConfig.landmark_correct,
        landmark_min_inliers: int = PipelineConfig.landmark_min_inliers,
        landmark_max_angle_deg: float = PipelineConfig.landmark_max_angle_deg,
        landmark_every: int = PipelineConfig.landmark_every,
        reselect_coverage: float | None = PipelineConfig.reselect_coverage,
        reselect_grid: int = PipelineConfig.reselect_grid,
    ) -> None:
        if not 0.0 <= reselect_fraction < 1.0:
            raise ValueError(f"reselect_fraction must be in [0, 1), got {reselect_fraction}")
        self.frontend, self.region, self.select = frontend, region, select
        self.flow, self.weighting, self.backend = flow, weighting, backend
        self.reselect_fraction, self.min_features = reselect_fraction, min_features
        self.edge_step, self.max_residual_px = edge_step, max_residual_px
        self.keep_survivors, self.min_separation_px = keep_survivors, min_separation_px
        self.predict_init, self.track_from_model = predict_init, track_from_model
        self.ransac_threshold_m, self.ransac_min_motion_px = ransac_threshold_m, ransac_min_motion_px
        self.record = record
        self.relocaliser = relocaliser
        terms = dict(use_photometric=keyframe_photometric, use_geometric=keyframe_geometric)
        kf = dict(count=keyframe_count, factor=keyframe_factor, blend=keyframe_blend, **terms)
        self.keyframes = KeyframeAligner(**kf) if keyframe_align else None
        if keyframe_anchor not in ("none", "older", "all"):
            raise ValueError(f"keyframe_anchor must be none, older or all, got {keyframe_anchor!r}")
        self.keyframe_anchor = keyframe_anchor
        lm = dict(keyframes=landmark_keyframes, per_keyframe=landmark_per_keyframe, correct=landmark_correct,
                  min_inliers=landmark_min_inliers, min_separation_px=min_separation_px,
                  max_angle_deg=landmark_max_angle_deg)  # fmt: skip
        self.landmarks = LandmarkMap(**lm) if landmarks else None
        if landmark_every < 0:
            raise ValueError(f"landmark_every must be >= 0, got {landmark_every}")
        self.landmark_every = landmark_every
        if track_from_model and landmark_every > 0:
            raise ValueError(
                "track_from_model needs landmark_every=0: features added between models have no model pixel"
            )
        if reselect_coverage is not None and not 0.0 < reselect_coverage <= 1.0 or reselect_grid < 1:
            raise ValueError(f"reselect_coverage must be in (0, 1] and reselect_grid >= 1, got {reselect_coverage}, "
                             f"{reselect_grid}")  # fmt: skip
        self.reselect_coverage, self.reselect_grid = reselect_coverage, reselect_grid
        self.since_landmarks: Tensor | Any = 0  # (B,) frames since the last model or re-acquisition
        self.reacquired_total: Tensor | Any = 0  # (B,) landmarks re-acquired so far (after the first frame)
        self.state = TrackerState()

    @property
    def wants_cues(self) -> bool:
        """Whether this frame's cues are computed: when recording, or for a weighting with ``needs_cues``."""
        return self.record or bool(getattr(self.weighting, "needs_cues", False))

    def step(self, frame: FrameBatch) -> StepResult:
        """One frame of every sequence (:meth:`track`), then the relocaliser's loss check where there is one."""
        n_prev = self.state.valid.sum(1) if self.state.valid is not None else None
        res = self.track(frame)
        return res if self.relocaliser is None else self.relocaliser(self, n_prev, frame, res)

    def track(self, frame: FrameBatch) -> StepResult:
        """One frame of every sequence (paper §III)."""
        cur = self.frontend(frame)  # depth in the colour camera, SIM (eq. 8), LK pyramids
        if not self.state.started:
            return self._start(frame, cur)
        s, with_cues = self.state, self.wants_cues
        dt = (frame.timestamp - s.timestamp).double().clamp_min(1e-3)
        init = self._predicted_pixels(frame, dt) if self.predict_init else None
        if self.track_from_model:  # from the model frame, started where the feature was last (or is predicted)
            source, start, init = s.model_flow, s.model_pixels, s.pixels if init is None else init
        else:
            source, start = s.prev.flow, s.pixels
        track = self.flow(source, cur.flow, start, s.valid, **self._flow_args(with_cues, init))  # eq. (10)
        points_d, has_depth = measure_points(cur.depth, frame.K, frame.T_color_depth, track.points)  # X_d, eq. (6)
        valid = track.valid & has_depth & frame.active[:, None]
        if self.ransac_threshold_m is not None:
            valid = self._consensus(points_d, valid, track.points - s.pixels)
        cues = self._cues(frame, cur, track, points_d, valid) if with_cues else None
        inputs = WeightingInputs(track.d_tim, points_d[..., 2], points_d, valid, frame.K_depth[:, 0, 0], cues=cues)
        var = self.weighting(inputs)  # eqs. (11)-(14)
        obs = Observation(
            dt.to(points_d.dtype), s.points_obj, points_d, track.points, valid, frame.K, frame.T_color_depth
        )
        est = self.backend.step(obs, var, active=frame.active)  # eqs. (2)-(7), (15)
        T_cam_obj = est.T_cam_obj.double() if self.keyframes is None else self._keyframe_corrected(frame, cur, est)
        self.state = self._advanced(frame, cur, track.points, valid, T_cam_obj)  # and the residual drop
        if self.landmarks is not None and self.landmark_every > 0:
            self._reanchor(frame, cur)  # every k frames: landmarks back into the current model
        tracked, reselect = self.state, self._needs_model(frame.active, tuple(cur.gray.shape[-2:]))
        model_T_cam_obj = self._new_model(frame, cur, reselect) if reselect.any() else None  # §III re-selection
        extra = dict(observation=obs, variances=var, cues=cues, model_T_cam_obj=model_T_cam_obj, estimate=est)
        return self._result(tracked, track.winner, track.d_tim, reselect, **extra)  # the frame as tracked

    # ---------------------------------------------------------------------------------------------- per frame
    @staticmethod
    def _flow_args(with_cues: bool, init: Tensor | None) -> dict:
        args = dict(with_residual=True) if with_cues else {}  # the LK residual is a cue
        return args if init is None else {**args, "init": init}

    def _consensus(self, points_d: Tensor, valid: Tensor, motion_px: Tensor) -> Tensor:
        """(B, N) ``valid`` without the RANSAC outliers of the (model point, measured point) pairs, in the sequences
        whose median tracked displacement ``motion_px`` (B, N, 2) exceeds ``ransac_min_motion_px``."""
        s = self.state
        z = points_d[..., 2].double()
        thr = self.ransac_threshold_m * z.square().clamp_min(1.0)
        fit = ransac_rigid(s.points_obj.double(), points_d.double(), valid, thr)
        shift = torch.linalg.vector_norm(motion_px, dim=-1).masked_fill(~valid, float("nan")).nanmedian(1).values
        use = fit.valid & (shift > self.ransac_min_motion_px)
        return torch.where(use[:, None], fit.inliers, valid)

    def _predicted_pixels(self, frame: FrameBatch, dt: Tensor) -> Tensor:
        """(B, N, 2) colour pixels of the model points under the constant-velocity pose prediction over ``dt`` (B,)
        seconds, ``T_pred = exp(xi dt) T_cam_obj``; the previous pixel where the prediction does not project."""
        s = self.state
        T_pred = se3_exp(s.velocity * dt[:, None]) @ s.T_cam_obj
        points_c = transform_points(frame.T_color_depth.double() @ T_pred, s.points_obj.double())
        pix = project(frame.K.double(), points_c)
        ok = (points_c[..., 2] > 1e-3) & torch.isfinite(pix).all(-1) & s.valid
        return torch.where(ok[..., None], pix.to(s.pixels.dtype), s.pixels)

    def _keyframe_corrected(self, frame: FrameBatch, cur: PreparedFrame, est: BackendResult) -> Tensor:
        """(B, 4, 4) the object pose after the dense alignment to the nearest keyframe. Against the current model
        frame (the newest keyframe) the correction refines ``T_cam_obj`` and the back end's mean pose moves there
        (velocity and covariance kept). Against an older keyframe it moves the model frame in the world,
        ``T_world_obj``, and leaves ``T_cam_obj`` to the features: they are measured against the current model,
        and correcting their pose towards another frame would set the two against each other every frame.
        ``keyframe_anchor``: "older" as above, "all" every correction moves ``T_world_obj`` (the features and the
        filter never see it; only the trajectory and the next model's chain do), "none" every one moves ``T_cam_obj``."""
        s, T_cd = self.state, frame.T_color_depth.double()
        T_cam_obj = est.T_cam_obj.double()
        T_world_color = s.T_world_obj @ T_inv(T_cam_obj) @ T_inv(T_cd)
        fix = self.keyframes.correct(cur.gray, cur.depth, T_world_color, frame.active)
        T_world_depth = fix.T_world_color @ T_cd
        relative = {"none": fix.used, "older": fix.used & fix.latest, "all": torch.zeros_like(fix.used)}[
            self.keyframe_anchor
        ]
        anchor = fix.used & ~relative
        T_cam_obj_new = T_inv(T_world_depth) @ s.T_world_obj
        set_backend_pose(self.backend, T_cam_obj_new, relative)
        T_world_obj = torch.where(anchor[:, None, None], T_world_depth @ T_cam_obj, s.T_world_obj)
        self.state = replace(s, T_world_obj=T_world_obj)
        return torch.where(relative[:, None, None], T_cam_obj_new, T_cam_obj)

    def _reanchor(self, frame: FrameBatch, cur: PreparedFrame) -> None:
        """The sequences ``landmark_every`` frames past their last model or re-acquisition re-acquire landmarks into
        the current model (no new model): the camera pose is re-fitted (``landmark_correct``) by moving the model
        frame in the world, ``T_world_obj``, so the filter's pose of the object is untouched; the verified landmarks
        join the model at their ORIGINAL world positions, expressed in the (moved) model frame."""
        self.since_landmarks = self.since_landmarks + frame.active.long()
        mask = frame.active & (self.since_landmarks >= self.landmark_every)
        if not mask.any():
            return
        self.since_landmarks = torch.where(mask, 0, self.since_landmarks)
        s = self.state
        world = transform_points(s.T_world_obj, s.points_obj.double())
        acq = self.landmarks.reacquire(
            self.flow, cur, frame.K, frame.T_color_depth, s.T_world_depth, s.pixels, s.valid, mask, tracked_world=world
        )  # fmt: skip
        found = acq.valid & mask[:, None]
        self.reacquired_total = self.reacquired_total + found.sum(1)
        T_world_obj = torch.where(mask[:, None, None], acq.T_world_depth @ s.T_cam_obj, s.T_world_obj)
        points_obj = transform_points(T_inv(T_world_obj), acq.points_world).to(s.points_obj.dtype)
        new = dict(pixels=acq.pixels.to(s.pixels.dtype), valid=found, points_obj=points_obj,
                   age=torch.zeros_like(found, dtype=torch.long), cornerness=acq.cornerness.to(s.cornerness.dtype))  # fmt: skip
        merged = {k: torch.cat([getattr(s, k), v], 1) for k, v in new.items()}
        width = max(s.pixels.shape[1], int(merged["valid"].sum(1).max()))
        order = torch.sort((~merged["valid"]).to(torch.uint8), dim=1, stable=True).indices[:, :width]  # valid first
        rows = torch.arange(order.shape[0])[:, None]
        merged = {k: v[rows, order] for k, v in merged.items()}
        residuals = self._residuals(frame, s.T_cam_obj, merged["points_obj"], merged["pixels"], merged["valid"])
        self.state = replace(s, **merged, residuals=residuals, T_world_obj=T_world_obj)

    def _needs_model(self, active: Tensor, size: tuple[int, int]) -> Tensor:
        """(B,) bool: too few features survive (a fraction of the model's, or an absolute count); with
        ``reselect_coverage``, the fraction rule applies only where the survivors also cover too little of the image
        (``size`` (H, W)): a model whose features still span the view keeps tracking."""
        n, s = self.state.valid.sum(1), self.state
        few = n < self.reselect_fraction * s.n_model
        if self.reselect_coverage is not None:
            few = few & (coverage(s.pixels, s.valid, size, self.reselect_grid) < self.reselect_coverage)
        return active & (few | (n < self.min_features))

    def _cues(self, frame: FrameBatch, cur: PreparedFrame, track: TrackResult, points_d: Tensor, valid: Tensor):
        """(B, N, C) cues of the tracked features (:data:`torchtrack.learn.cues.CUE_NAMES`), zeros where not valid."""
        H, W = cur.gray.shape[-2:]
        s = self.state
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        sim = sample_depth(cur.sim.si, track.points) if cur.sim is not None else torch.full_like(track.d_tim, 0.5)
        cues = stack_cues(
            d_tim_int=track.d_tim_int, d_tim_sim=track.d_tim_sim, sim_won=track.winner == 1,
            lk_residual=track.residual, depth=points_d[..., 2],
            centroid_dist=torch.linalg.vector_norm(points_d - centroid[:, None], dim=-1),
            cornerness_int=s.cornerness[..., 0], cornerness_sim=s.cornerness[..., 1],
            sim_value=sim,  # nearest pixel of the SI map: masked (planar, no depth) pixels carry its fill value
            track_age=s.age + 1,
            prev_reproj=torch.where(s.age > 0, s.residuals, 0.0),  # a new feature has no previous frame
            u_norm=track.points[..., 0] / W, v_norm=track.points[..., 1] / H, fb_error=track.d_tim,
            **window_cues(cur.depth, track.points, s.prev.gray, s.pixels),
        )  # fmt: skip
        return torch.where(valid[..., None], cues, 0.0)

    def _advanced(
        self, frame: FrameBatch, cur: PreparedFrame, pixels: Tensor, valid: Tensor, T_cam_obj: Tensor
    ) -> TrackerState:
        """The state after this frame's update: the new pose (ended sequences keep theirs) and tracks, one frame
        older; features that do not fit the pose dropped (``max_residual_px``)."""
        s = self.state
        T_cam_obj = torch.where(frame.active[:, None, None], T_cam_obj, s.T_cam_obj)
        dt = (frame.timestamp - s.timestamp).double().clamp_min(1e-3)
        velocity = se3_log(T_cam_obj @ T_inv(s.T_cam_obj)) / dt[:, None]  # the motion of this frame, per second
        velocity = torch.where(frame.active[:, None], velocity, s.velocity)
        residuals = self._residuals(frame, T_cam_obj, s.points_obj, pixels, valid)  # for the drop and for eq. (16)
        if self.max_residual_px is not None:
            valid = valid & (residuals <= self.max_residual_px)
        return replace(s, prev=cur, timestamp=frame.timestamp, pixels=pixels, valid=valid, age=s.age + 1,
                       residuals=residuals, T_cam_obj=T_cam_obj, velocity=velocity)  # fmt: skip

    # ---------------------------------------------------------------------------------------------- the model
    def _start(self, frame: FrameBatch, cur: PreparedFrame) -> StepResult:
        """First frame: every sequence takes it as its model; the world is the first camera."""
        B = frame.rgb.shape[0]
        eye = torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone()
        zero = torch.zeros(B, 6, dtype=torch.float64)
        self.state = TrackerState(timestamp=frame.timestamp, T_cam_obj=eye, T_world_obj=eye.clone(), velocity=zero)
        if self.keyframes is not None:
            self.keyframes.reset()
        if self.landmarks is not None:
            self.landmarks.reset()
        self.reacquired_total = torch.zeros(B, dtype=torch.long)
        self.since_landmarks = torch.zeros(B, dtype=torch.long)
        everyone = torch.ones(B, dtype=torch.bool)
        model_T_cam_obj = self._new_model(frame, cur, everyone)
        return self._result(self.state, None, None, everyone, model_T_cam_obj=model_T_cam_obj)

    def _new_model(self, frame: FrameBatch, cur: PreparedFrame, mask: Tensor) -> Tensor:
        """Take the current frame as the model of the sequences in ``mask`` (B,): PCM features, pose, chain; the
        back end starts over there. Returns the pose (B, 4, 4) the back end is reset to (meaningful where ``mask``)."""
        kept = self._kept(frame, cur, mask)  # survivors, re-acquired landmarks (may correct T_world_obj)
        s = self.state
        roi = self.region(cur.depth)
        if self.edge_step is not None:
            roi = roi & smooth_depth_mask(cur.depth, self.edge_step)
        feats = self.select(cur.gray, cur.depth, frame.K, roi=roi, sim=cur.sim)  # eq. (9)
        pixels, cornerness = feats.pixels, torch.stack([feats.cornerness_int, feats.cornerness_sim], -1)
        points_d, has_depth = measure_points(cur.depth, frame.K, frame.T_color_depth, pixels)
        valid = feats.valid & has_depth
        age = torch.zeros_like(valid, dtype=torch.long)
        if kept is not None:
            found = self._found if self.landmarks is not None else None
            pixels, points_d, valid, age, cornerness = self._with_kept(kept, pixels, points_d, valid, cornerness, found)
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        points_obj = torch.where(valid[..., None], points_d - centroid[:, None], torch.zeros_like(points_d))
        T_cam_obj = make_T(torch.eye(3, dtype=torch.float64).expand(len(mask), 3, 3), centroid.double())
        new = dict(pixels=pixels, valid=valid, points_obj=points_obj, age=age, cornerness=cornerness)
        old = {k: getattr(s, k) for k in _FEATURE_FIELDS}
        if s.pixels is not None:  # selections differ in size: pad both to the larger N; old rows outside mask
            n = max(s.pixels.shape[1], valid.shape[1])
            new = {k: _where(mask, pad_to(v, n), pad_to(old[k], n)) for k, v in new.items()}
        m3 = mask[:, None, None]
        n_model = new["valid"].sum(1)
        T_cam_obj = torch.where(m3, T_cam_obj, s.T_cam_obj)
        state = replace(
            s, prev=cur, **new, T_cam_obj=T_cam_obj,
            T_world_obj=torch.where(m3, s.T_world_depth @ T_cam_obj, s.T_world_obj),
            n_model=n_model if s.n_model is None else torch.where(mask, n_model, s.n_model),
        )  # fmt: skip
        residuals = self._residuals(frame, T_cam_obj, state.points_obj, state.pixels, state.valid)
        self.state = replace(state, residuals=residuals)  # in the new layout: the next frame's prev_reproj cue
        if self.track_from_model:
            self.state = replace(self.state, **self._model_reference(s, cur, mask))
        self.backend.reset(T_cam_obj, mask)
        if self.keyframes is not None:  # the model frame is a keyframe
            T_world_color = self.state.T_world_depth @ T_inv(frame.T_color_depth.double())
            self.keyframes.add(cur.gray, cur.depth, frame.K, T_world_color, mask)
        if self.landmarks is not None:  # ... and its features are landmarks, at their world positions
            self.since_landmarks = torch.where(mask, 0, self.since_landmarks)
            st = self.state
            world = transform_points(st.T_world_obj, st.points_obj.double())
            self.landmarks.add(cur, frame.timestamp, st.T_world_depth, st.pixels, world, st.cornerness, st.valid, mask)
        return T_cam_obj

    def _model_reference(self, old: TrackerState, cur: PreparedFrame, mask: Tensor) -> dict:
        """``model_flow`` and ``model_pixels`` after a re-selection of the sequences in ``mask`` (B,): the current
        frame and the new model's pixels there; the other sequences keep theirs (``old``, the state before it)."""
        pixels = self.state.pixels
        if old.model_flow is None or bool(mask.all()):
            return dict(model_flow=cur.flow, model_pixels=pixels)
        m4 = mask.view(-1, 1, 1, 1)
        images = [torch.where(m4, new, kept) for new, kept in zip(cur.flow.images, old.model_flow.images, strict=True)]
        flow = prepare_frame(images[0], images[1] if len(images) > 1 else None, cur.flow.pyramid.levels,
                             max_window=cur.flow.pyramid.max_window)  # fmt: skip
        return dict(model_flow=flow, model_pixels=_where(mask, pixels, pad_to(old.model_pixels, pixels.shape[1])))

    def _kept(self, frame: FrameBatch, cur: PreparedFrame, mask: Tensor) -> _Kept | None:
        """What a re-selection of the sequences in ``mask`` (B,) keeps before it selects new features, in the
        current camera: the survivors (``keep_survivors``; their model points moved into the camera by the current
        pose, so that the new model frame sees them where the old one did) and then the re-acquired landmarks
        (``landmarks``; their stored world positions moved into the camera by the camera pose, corrected first
        where the landmarks re-fit it). None on the first frame or with neither switch."""
        s = self.state
        self._found = torch.zeros(len(mask), dtype=torch.long)
        if s.pixels is None or not (self.keep_survivors or self.landmarks is not None):
            return None
        keep = s.valid & mask[:, None] if self.keep_survivors else torch.zeros_like(s.valid)
        points = transform_points(s.T_cam_obj.float(), s.points_obj.float())
        kept = _Kept(s.pixels, points, keep, s.age, s.cornerness)
        if self.landmarks is None:
            return kept
        world = transform_points(s.T_world_obj, s.points_obj.double())
        acq = self.landmarks.reacquire(
            self.flow, cur, frame.K, frame.T_color_depth, s.T_world_depth, s.pixels, keep, mask, tracked_world=world
        )  # fmt: skip
        T_world_depth = torch.where(mask[:, None, None], acq.T_world_depth, s.T_world_depth)
        self.state = replace(s, T_world_obj=T_world_depth @ s.T_cam_obj)  # the landmarks' correction, if any
        self._found = (acq.valid & mask[:, None]).sum(1)
        self.reacquired_total = self.reacquired_total + self._found
        points = transform_points(T_inv(T_world_depth), acq.points_world).float()  # the ORIGINAL world positions
        found = _Kept(acq.pixels, points, acq.valid & mask[:, None], torch.zeros_like(acq.valid, dtype=torch.long),
                      acq.cornerness)  # fmt: skip
        return _Kept(*(torch.cat([a, b.to(a.dtype)], 1) for a, b in zip(kept, found, strict=True)))

    def _with_kept(
        self, kept: _Kept, pixels: Tensor, points_d: Tensor, valid: Tensor, cornerness: Tensor, n_found: Tensor | None
    ):
        """The kept features (B, K) first, then the new ones (B, M) that are at least ``min_separation_px`` from all
        of them, up to the larger of M and the current model's width (a poor selection never cuts the kept ones); with
        ``n_found`` (B,) re-acquired landmarks among the kept, up to the larger of M and the survivors, plus those.
        Kept features keep their age and cornerness (B, M, 2 for the new ones).
        Returns (pixels (B, W, 2), points in the camera (B, W, 3), valid (B, W), age (B, W), cornerness (B, W, 2))."""
        apart = far_from(pixels, kept.pixels.to(pixels.dtype), kept.valid, self.min_separation_px)
        ok = torch.cat([kept.valid, valid & apart], 1)
        if n_found is None:
            width = max(valid.shape[1], self.state.pixels.shape[1])
        else:  # per sequence: the survivors or the new selection's count, plus the re-acquired (batched equals looped)
            n_surv = kept.valid.sum(1) - n_found
            cap = torch.maximum(n_surv, valid.sum(1)) + n_found
            ok = ok & (ok.long().cumsum(1) <= cap[:, None])
            width = int(ok.sum(1).max())
        order = torch.sort((~ok).to(torch.uint8), dim=1, stable=True).indices[:, :width]  # valid first
        rows = torch.arange(ok.shape[0])[:, None]
        ok = ok[rows, order]
        pixels = torch.cat([kept.pixels.to(pixels.dtype), pixels], 1)[rows, order]
        points = torch.cat([kept.points.to(points_d.dtype), points_d], 1)[rows, order]
        age = torch.cat([kept.age, torch.zeros_like(valid, dtype=torch.long)], 1)[rows, order]
        cornerness = torch.cat([kept.cornerness.to(cornerness.dtype), cornerness], 1)[rows, order]
        ok3 = ok[..., None]
        return (
            torch.where(ok3, pixels, 0.0), torch.where(ok3, points, 0.0), ok, torch.where(ok, age, 0),
            torch.where(ok3, cornerness, 0.0),
        )  # fmt: skip

    def relocalise(self, frame: FrameBatch, T_world_depth: Tensor, mask: Tensor) -> Tensor:
        """After a tracking loss: the sequences in ``mask`` (B,) take the current frame as a new model at the camera
        pose ``T_world_depth`` (B, 4, 4, the tracker's world) found by relocalisation; their features are dropped
        first (they followed the wrong motion), so no survivor carries over. Returns the pose (B, 4, 4) the back
        end was reset to (meaningful where ``mask``), as :attr:`StepResult.model_T_cam_obj`."""
        s = self.state
        T_world_obj = torch.where(mask[:, None, None], T_world_depth.double() @ s.T_cam_obj, s.T_world_obj)
        self.state = replace(s, valid=s.valid & ~mask[:, None], T_world_obj=T_world_obj)
        if self.landmarks is not None:  # a model taken this frame, at the lost pose, is no keyframe
            self.landmarks.forget(frame.timestamp, mask)
        return self._new_model(frame, s.prev, mask)

    # ---------------------------------------------------------------------------------------------- outputs
    @staticmethod
    def _residuals(frame: FrameBatch, T_cam_obj: Tensor, points_obj: Tensor, pixels: Tensor, valid: Tensor) -> Tensor:
        """(B, N) reprojection error of each feature (eq. 16) under ``T_cam_obj``; inf where undefined."""
        T_color_obj = frame.T_color_depth.double() @ T_cam_obj
        err = reprojection_errors(frame.K, T_color_obj, points_obj, pixels, valid).float()
        return torch.nan_to_num(err, nan=float("inf"))

    @staticmethod
    def _result(
        s: TrackerState, winner: Tensor | None, d_tim: Tensor | None, reselected: Tensor, **extra
    ) -> StepResult:
        """The frame's result from the state ``s`` (``extra``: StepResult's optional fields)."""
        B, N = s.valid.shape
        res = torch.where(s.valid, s.residuals, torch.zeros_like(s.pixels[..., 0]))
        err = res.sum(1) / s.valid.sum(1).clamp_min(1)  # mean reprojection error, eq. (16)
        return StepResult(
            T_cam_obj=s.T_cam_obj,
            T_world_depth=s.T_world_depth,
            pixels=s.pixels,
            valid=s.valid,
            winner=winner if winner is not None else torch.full((B, N), -1, dtype=torch.long),
            points_obj=s.points_obj,
            reprojection_error=err,
            n_features=s.valid.sum(1),
            reselected=reselected,
            d_tim=d_tim if d_tim is not None else torch.zeros(B, N),
            **extra,
        )


class _Kept(NamedTuple):
    """Features a re-selection keeps, (B, K, ...): colour pixels, points in the current depth camera, valid, age,
    cornerness (B, K, 2)."""

    pixels: Tensor
    points: Tensor
    valid: Tensor
    age: Tensor
    cornerness: Tensor


def coverage(pixels: Tensor, valid: Tensor, size: tuple[int, int], grid: int) -> Tensor:
    """(B,) fraction of the ``grid`` x ``grid`` cells of an image of ``size`` (H, W) that hold a valid feature
    (pixels (B, N, 2), valid (B, N)): how far the features span the view (paper Table I: spread lowers the error)."""
    H, W = size
    col = (pixels[..., 0] * grid / W).long().clamp(0, grid - 1)
    row = (pixels[..., 1] * grid / H).long().clamp(0, grid - 1)
    hit = torch.zeros(pixels.shape[0], grid * grid).scatter_add_(1, row * grid + col, valid.float())
    return (hit > 0).float().mean(1)


def _where(mask: Tensor, new: Tensor, old: Tensor) -> Tensor:
    """Rows of ``new`` where ``mask`` (B,), else of ``old``; any trailing shape."""
    return torch.where(mask.view(-1, *([1] * (new.dim() - 1))), new, old)
