"""The torchtrack pipeline: select -> track -> weight -> update -> (re-select), batched over B sequences.

Frames. ``cam`` is the depth camera. The object frame ``obj`` is the model frame's depth camera moved
to the centroid of the selected features (so rotations about it stay well-conditioned); the model
points X_o live in it. The tracker estimates ``T_cam_obj`` per frame; with the object static in the
world (scene tracking, or a camera moving around an object), the camera pose follows as
``T_world_depth = T_world_obj @ inv(T_cam_obj)``. The tracker's world is its first depth camera (identity); the
runner writes the colour camera's poses in ground truth's world (:mod:`torchtrack.geometry.rig`, the one conversion
between the two cameras). A re-selection makes the current frame the new model frame and chains ``T_world_obj``
through the current estimate, so the trajectory stays continuous.

References:
    O. S. Gedik, A. A. Alatan, "Fusing 2D and 3D Clues for 3D Tracking Using Visual and Range Data",
    FUSION 2013.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import torch
from torch import Tensor

from torchtrack.config import PipelineConfig
from torchtrack.data.frame import FrameBatch
from torchtrack.estimators.backends import Observation, PoseBackend
from torchtrack.estimators.base import masked_mean
from torchtrack.estimators.landmark_update import FrameFusion, joint_update, landmark_variances, mean_variances
from torchtrack.filter.cues import stack_cues, window_cues
from torchtrack.filter.models import measure_points
from torchtrack.filter.weighting import Variances, WeightingInputs
from torchtrack.frontend import FrontEnd, PreparedFrame
from torchtrack.geometry import T_inv, make_T, project, rigid, sample_depth, se3_exp, se3_log, transform_points
from torchtrack.image.flow import TrackResult
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.landmark_window import refine_at_reselection
from torchtrack.pipeline.landmarks import LandmarkMap
from torchtrack.pipeline.outliers import ResidualDrop, feature_residuals
from torchtrack.pipeline.relocalise import Relocalisation, Relocaliser
from torchtrack.pipeline.reselect import Kept, PointEstimate, Reselection
from torchtrack.pipeline.state import FEATURE_FIELDS, StepResult, TrackerState, pad_to, valid_first, where_rows


class Tracker:
    """Model-free RGB-D rigid tracker (paper §III), batched over B sequences in lockstep, composed of stages.

    Args:
        frontend: per-frame preparation (registered depth, SIM, pyramids).
        flow: combined LK + TIM tracker (eq. 10), ``flow(prev, next, pixels, valid) -> TrackResult``.
        weighting: per-feature noise variances (eqs. 11-14).
        backend: the pose estimator (fusion EKF or a registration baseline), :class:`PoseBackend`.
        reselect: the model stage (:class:`~torchtrack.pipeline.reselect.Reselection`): its region of interest and
            spatio-textural selection (eq. 9) take a model's features; when too few survive it takes a new one, and
            what the new model keeps.
        outliers: which features leave the model after the update (:class:`~torchtrack.pipeline.outliers.ResidualDrop`).
        keyframes: the one keyframe store (:class:`~torchtrack.pipeline.keyframes.KeyframeStore`; None: a default
            one): a model frame, or a tracked frame every ``keyframes.every`` frames, with a trusted pose becomes a
            keyframe; the landmarks and the relocaliser attach their content to it.
        landmarks: improvement (None = paper): model points that outlive their model
            (:class:`~torchtrack.pipeline.landmarks.LandmarkMap`), the model keyframes' features: at a re-selection (and
            every ``landmarks.every`` frames when > 0) the visible landmarks are re-tracked from their keyframe and
            join the model at their ORIGINAL world positions, after the survivors and before new features; with
            ``landmarks.correct`` the camera pose is first re-fitted to them by moving the model frame in the world.
        relocaliser: improvement (None = no loss check): after each frame, the loss check
            (:class:`~torchtrack.pipeline.relocalise.Relocaliser`) against the keyframes' ORB descriptors; its
            :class:`Relocalisation` decision is applied here: the relocalised sequences take a new model at the
            found camera pose.
        predict_init: improvement (False = paper): each feature's LK starts where the model point projects under the
            constant-velocity prediction of the pose (``TrackerState.velocity``), not at its previous pixel: under
            fast motion the displacement left to LK is the prediction's error, not the whole motion.
        record: compute the per-feature cues (:mod:`torchtrack.filter.cues`) of every frame into
            ``StepResult.cues`` even when the weighting does not need them (for the observation cache). Poses are
            the same with and without; a weighting with ``needs_cues = True`` gets them in any case.

    The tracker's model and last estimate live in one :class:`TrackerState`, ``self.state``, which only the tracker
    writes; each stage keeps its own state (the back end its filter, the landmarks their keyframes, the relocaliser
    its store). A back end's pose is moved through ``backend.reset`` / ``backend.set_pose`` only.
    """

    def __init__(
        self,
        *,
        frontend: FrontEnd,
        flow: Callable,
        weighting: Callable,
        backend: PoseBackend,
        reselect: Reselection,
        outliers: ResidualDrop | None = None,
        keyframes: KeyframeStore | None = None,
        landmarks: LandmarkMap | None = None,
        relocaliser: Relocaliser | None = None,
        predict_init: bool = PipelineConfig.predict_init,
        record: bool = PipelineConfig.record,
    ) -> None:
        self.frontend, self.flow, self.weighting, self.backend = frontend, flow, weighting, backend
        self.reselect = reselect
        self.outliers = outliers if outliers is not None else ResidualDrop()
        self.keyframes = keyframes if keyframes is not None else KeyframeStore()
        self.landmarks, self.relocaliser = landmarks, relocaliser
        self.predict_init, self.record = predict_init, record
        self.state = TrackerState()

    def reset(self) -> None:
        """Forget the run: the next :meth:`step` is a first frame (new sequences, any batch size), and every stage
        starts anew there (the back end's noise scales included)."""
        self.state = TrackerState()

    @property
    def wants_cues(self) -> bool:
        """Whether this frame's cues are computed: when recording, or for a weighting with ``needs_cues``."""
        return self.record or bool(getattr(self.weighting, "needs_cues", False))

    def step(self, frame: FrameBatch) -> StepResult:
        """One frame of every sequence (paper §III), then the relocaliser's loss check and its decision, then the
        keyframe the frame may become."""
        n_prev = self.state.valid.sum(1) if self.state.valid is not None else None
        cur = self.frontend(frame)  # depth in the colour camera, SIM (eq. 8), LK pyramids
        res = self._track(frame, cur) if self.state.started else self._start(frame, cur)
        trusted = frame.active
        if self.relocaliser is not None:
            decision = self.relocaliser.check(self.keyframes, frame, cur, res, n_prev)
            if decision.relocalised.any():
                res = self._relocalised(frame, cur, res, decision)
            res, trusted = replace(res, loss=decision.loss), trusted & self.relocaliser.trusted(decision)
        self._keyframe(frame, cur, self.keyframes.due(res.reselected, frame.active) & trusted, res.reselected)
        return res

    def _track(self, frame: FrameBatch, cur: PreparedFrame) -> StepResult:
        """One frame after the first: track, weight, update, drop outliers, re-acquire landmarks, re-select."""
        s, with_cues = self.state, self.wants_cues
        dt = (frame.timestamp - s.timestamp).double().clamp_min(1e-3)
        init = self._predicted_pixels(s, frame, dt) if self.predict_init else None
        track = self.flow(s.prev.flow, cur.flow, s.pixels, s.valid, **_flow_args(with_cues, init))  # eq. (10)
        points_d, has_depth = measure_points(cur.depth, frame.K, frame.T_color_depth, track.points)  # X_d, eq. (6)
        valid = track.valid & has_depth & frame.active[:, None]
        cues = self._cues(s, cur, track, points_d, valid) if with_cues else None
        inputs = WeightingInputs(track.d_tim, points_d[..., 2], points_d, valid, frame.K_depth[:, 0, 0], cues=cues)
        var = self.weighting(inputs)  # eqs. (11)-(14)
        obs = Observation(
            dt.to(points_d.dtype), s.points_obj, points_d, track.points, valid, frame.K, frame.T_color_depth
        )
        # with ``landmarks.measure`` a re-selection redoes this update with the re-acquired landmarks as more features
        # of the frame (:func:`~torchtrack.estimators.landmark_update.joint_update`): keep what it started from
        joint = self.landmarks is not None and self.landmarks.measure and self.backend.fuses
        before = self.backend.snapshot() if joint else None
        est = self.backend.step(obs, var, active=frame.active)  # eqs. (2)-(7), (15)
        fusion = FrameFusion(before, obs, var, frame.active) if joint else None
        if self.landmarks is not None:  # this frame's noise level: the landmarks' (nothing else reads it)
            s = replace(s, mean_var=mean_variances(var, valid))
        tracked = self._advanced(s, frame, cur, track.points, valid, est.T_cam_obj.double(), points_d, var)
        winner, d_tim = track.winner, track.d_tim
        if self.landmarks is not None and self.landmarks.every > 0:  # every k frames: landmarks back into the model
            tracked, order = self._reanchored(tracked, frame, cur)
            if order is not None:  # the features were re-ordered and joined by landmarks: so are their outputs
                winner, d_tim = _gather_padded(winner, order, -1), _gather_padded(d_tim, order, 0.0)
        reselect = self.reselect.needed(tracked.valid, tracked.n_model, frame.active)
        self.state, model_T_cam_obj = tracked, None
        if reselect.any():  # §III re-selection
            self.state, model_T_cam_obj = self._new_model(tracked, frame, cur, reselect, fusion)
        extra = dict(observation=obs, variances=var, cues=cues, model_T_cam_obj=model_T_cam_obj, estimate=est)
        return _result(tracked, winner, d_tim, reselect, **extra)  # the frame as tracked

    # ---------------------------------------------------------------------------------------------- per frame
    @staticmethod
    def _predicted_pixels(s: TrackerState, frame: FrameBatch, dt: Tensor) -> Tensor:
        """(B, N, 2) colour pixels of the model points under the constant-velocity pose prediction over ``dt`` (B,)
        seconds, ``T_pred = exp(xi dt) T_cam_obj``; the previous pixel where the prediction does not project."""
        T_pred = se3_exp(s.velocity * dt[:, None]) @ s.T_cam_obj
        points_c = transform_points(frame.T_color_depth.double() @ T_pred, s.points_obj.double())
        pix = project(frame.K.double(), points_c)
        ok = (points_c[..., 2] > 1e-3) & torch.isfinite(pix).all(-1) & s.valid
        return torch.where(ok[..., None], pix.to(s.pixels.dtype), s.pixels)

    @staticmethod
    def _cues(s: TrackerState, cur: PreparedFrame, track: TrackResult, points_d: Tensor, valid: Tensor) -> Tensor:
        """(B, N, C) cues of the tracked features (:data:`torchtrack.filter.cues.CUE_NAMES`), zeros where not valid."""
        H, W = cur.gray.shape[-2:]
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

    def _advanced(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, pixels: Tensor, valid: Tensor,
                  T_cam_obj: Tensor, points_d: Tensor, var: Variances) -> TrackerState:  # fmt: skip
        """The state after this frame's update: the new pose (ended sequences keep theirs) and tracks, one frame
        older; features that do not fit the pose dropped (the outlier stage); with ``reselect.point_mean`` the kept
        features' depth samples ``points_d`` (B, N, 3) with the weighting's variances ``var`` fused into their model
        points' estimates (with ``frame``: the model points are now those)."""
        T_cam_obj = torch.where(frame.active[:, None, None], T_cam_obj, s.T_cam_obj)
        dt = (frame.timestamp - s.timestamp).double().clamp_min(1e-3)
        velocity = se3_log(T_cam_obj @ T_inv(s.T_cam_obj)) / dt[:, None]  # the motion of this frame, per second
        velocity = torch.where(frame.active[:, None], velocity, s.velocity)
        residuals = feature_residuals(frame.K, frame.T_color_depth, T_cam_obj, s.points_obj, pixels, valid)  # eq. (16)
        s = replace(s, prev=cur, timestamp=frame.timestamp, pixels=pixels, valid=self.outliers(residuals, valid),
                    age=s.age + 1, residuals=residuals, T_cam_obj=T_cam_obj, velocity=velocity)  # fmt: skip
        if not self.reselect.estimates_points:
            return s
        est = self.reselect.fused(PointEstimate(s.points_mean, s.points_info), T_cam_obj, points_d, var.var_xyz,
                                  var.var_pix, frame.K_depth[:, 0, 0], s.valid)  # fmt: skip
        frame_mean = self.reselect.point_mean == "frame"
        return replace(s, points_mean=est.mean, points_info=est.info,
                       points_obj=est.mean.to(s.points_obj.dtype) if frame_mean else s.points_obj)  # fmt: skip

    def _reanchored(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame) -> tuple[TrackerState, Tensor | None]:
        """``s`` where the sequences ``landmarks.every`` frames past their last model or re-acquisition re-acquired
        landmarks into the current model (no new model): the camera pose is re-fitted (``landmarks.correct``) by
        moving the model frame in the world, ``T_world_obj``, so the filter's pose of the object is untouched; the
        verified landmarks join the model at their ORIGINAL world positions, expressed in the (moved) model frame.
        Also returns the new feature order (B, N') as indices into [the old N features, the re-acquired ones] (None:
        nothing re-acquired, the order unchanged)."""
        since = s.since_landmarks + frame.active.long()
        mask = frame.active & (since >= self.landmarks.every)
        if not mask.any():
            return replace(s, since_landmarks=since), None
        acq = self.landmarks.reacquire_into(self.keyframes, self.flow, cur, frame.K, frame.T_color_depth, s, s.valid,
                                            mask)  # fmt: skip
        found = acq.valid & mask[:, None]
        T_world_obj = torch.where(mask[:, None, None], acq.T_world_depth @ s.T_cam_obj, s.T_world_obj)
        points_obj = transform_points(T_inv(T_world_obj), acq.points_world).to(s.points_obj.dtype)
        new = dict(pixels=acq.pixels.to(s.pixels.dtype), valid=found, points_obj=points_obj,
                   age=torch.zeros_like(found, dtype=torch.long), cornerness=acq.cornerness.to(s.cornerness.dtype))  # fmt: skip
        if s.points_mean is not None:  # model points as estimates: the landmarks' positions, not yet weighed
            new |= dict(points_mean=points_obj.double(), points_info=s.points_info.new_zeros(*found.shape, 3, 3))
        merged = {k: torch.cat([getattr(s, k), v], 1) for k, v in new.items()}
        order = valid_first(merged["valid"], max(s.pixels.shape[1], int(merged["valid"].sum(1).max())))
        rows = torch.arange(order.shape[0], device=order.device)[:, None]
        merged = {k: v[rows, order] for k, v in merged.items()}
        residuals = feature_residuals(frame.K, frame.T_color_depth, s.T_cam_obj, merged["points_obj"],
                                      merged["pixels"], merged["valid"])  # fmt: skip
        return replace(s, **merged, residuals=residuals, T_world_obj=T_world_obj, since_landmarks=torch.where(
            mask, 0, since), reacquired_total=s.reacquired_total + found.sum(1)), order  # fmt: skip

    # ---------------------------------------------------------------------------------------------- the model
    def _start(self, frame: FrameBatch, cur: PreparedFrame) -> StepResult:
        """First frame: every sequence takes it as its model; the world is the first camera."""
        B, dev = frame.rgb.shape[0], frame.rgb.device
        eye = torch.eye(4, dtype=torch.float64, device=dev).expand(B, 4, 4).clone()
        zero = torch.zeros(B, 6, dtype=torch.float64, device=dev)
        count = torch.zeros(B, dtype=torch.long, device=dev)
        s = TrackerState(timestamp=frame.timestamp, T_cam_obj=eye, T_world_obj=eye.clone(), velocity=zero,
                         since_landmarks=count, reacquired_total=count.clone())  # fmt: skip
        self.keyframes.reset(B, dev)
        self.backend.start()  # a tracker can run again: nothing of the last run carries over
        if self.landmarks is not None:
            self.landmarks.reset()
        if self.relocaliser is not None:
            self.relocaliser.reset(B, self.keyframes.slots)
        everyone = torch.ones(B, dtype=torch.bool, device=dev)
        self.state, model_T_cam_obj = self._new_model(s, frame, cur, everyone)
        return _result(self.state, None, None, everyone, model_T_cam_obj=model_T_cam_obj)

    def _new_model(
        self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, mask: Tensor, fusion: FrameFusion | None = None
    ):
        """The state ``s`` after the sequences in ``mask`` (B,) took the current frame as their model: the features
        kept (survivors, re-acquired landmarks), then new PCM features (eq. 9), pose and chain; the back end starts
        over there. Returns (the new state, the pose (B, 4, 4) the
        back end was reset to, meaningful where ``mask``)."""
        kept, n_found, s = self._kept(s, frame, cur, mask, fusion)  # may correct T_world_obj (the landmarks' re-fit)
        roi = self.reselect.roi(cur.depth)
        feats = self.reselect.select(cur.gray, cur.depth, frame.K, roi=roi, sim=cur.sim)  # eq. (9)
        pixels, cornerness = feats.pixels, torch.stack([feats.cornerness_int, feats.cornerness_sim], -1)
        points_d, has_depth = measure_points(cur.depth, frame.K, frame.T_color_depth, pixels)
        valid = feats.valid & has_depth
        age, info = torch.zeros_like(valid, dtype=torch.long), None
        if kept is not None:
            pixels, points_d, valid, age, cornerness, info = self.reselect.merge(
                kept, pixels, points_d, valid, cornerness, n_found, s.pixels.shape[1]
            )
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        points_obj = torch.where(valid[..., None], points_d - centroid[:, None], torch.zeros_like(points_d))
        eye = torch.eye(3, dtype=torch.float64, device=centroid.device).expand(len(mask), 3, 3)
        T_cam_obj = make_T(eye, centroid.double())
        new = dict(pixels=pixels, valid=valid, points_obj=points_obj, age=age, cornerness=cornerness)
        if self.reselect.estimates_points:  # the model frame is the camera's, moved: the information is not rotated
            if info is None:  # new points: the birth sample alone
                info = torch.zeros(*valid.shape, 3, 3, dtype=torch.float64, device=valid.device)
            new |= dict(points_mean=points_obj.double(), points_info=info)
        if s.pixels is not None:  # selections differ in size: pad both to the larger N; old rows outside mask
            n = max(s.pixels.shape[1], valid.shape[1])
            new = {k: where_rows(mask, pad_to(v, n), pad_to(getattr(s, k), n)) for k, v in new.items()}
        m3 = mask[:, None, None]
        n_model = new["valid"].sum(1)
        T_cam_obj = torch.where(m3, T_cam_obj, s.T_cam_obj)
        state = replace(
            s, prev=cur, **new, T_cam_obj=T_cam_obj,
            T_world_obj=torch.where(m3, s.T_world_depth @ T_cam_obj, s.T_world_obj),
            n_model=n_model if s.n_model is None else torch.where(mask, n_model, s.n_model),
        )  # fmt: skip
        residuals = feature_residuals(frame.K, frame.T_color_depth, T_cam_obj, state.points_obj, state.pixels,
                                      state.valid)  # fmt: skip  # in the new layout: the next frame's prev_reproj cue
        state = replace(state, residuals=residuals)
        self.backend.reset(T_cam_obj, mask)
        return replace(state, since_landmarks=torch.where(mask, 0, state.since_landmarks)), T_cam_obj

    def _kept(
        self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, mask: Tensor, fusion: FrameFusion | None = None
    ):
        """What a re-selection of the sequences in ``mask`` (B,) keeps before it selects new features, in the current
        camera: the survivors (``reselect.keep_survivors``; their model points moved into the camera by the current
        pose, so that the new model frame sees them where the old one did) and then the re-acquired landmarks (their
        stored world positions moved into the camera by the camera pose, corrected first where the landmarks re-fit
        it). Returns (the kept features or None on the first frame or with neither, the re-acquired count (B,) or None
        without landmarks, ``s`` with the landmarks' correction of ``T_world_obj`` and count)."""
        if s.pixels is None or not (self.reselect.keep_survivors or self.landmarks is not None):
            return None, None, s
        keep = self.reselect.survivors(s.valid, mask)
        if s.points_mean is None:
            kept = Kept(s.pixels, transform_points(s.T_cam_obj.float(), s.points_obj.float()), keep, s.age,
                        s.cornerness)  # fmt: skip
        else:  # survivors carry their estimates, in the camera
            R = s.T_cam_obj[:, None, :3, :3]
            kept = Kept(s.pixels, transform_points(s.T_cam_obj, s.points_mean).float(), keep, s.age, s.cornerness,
                        R @ s.points_info @ R.transpose(-1, -2))  # fmt: skip
        if self.landmarks is None:
            return kept, None, s
        fused = fusion is not None and s.mean_var is not None  # the back end fuses them; else the re-fit (correct)
        acq = self.landmarks.reacquire_into(self.keyframes, self.flow, cur, frame.K, frame.T_color_depth, s, keep, mask,
                                            fused=fused)  # fmt: skip
        if fused:  # the frame's update redone with the landmarks as more of its features (without a frame update to
            # redo, a relocalisation's new model, or a back end that does not fuse: the re-fit above, ``correct``)
            found = acq.valid & mask[:, None]
            lm_var = landmark_variances(acq.points_cam, s.mean_var)
            lm_obs = acq._replace(valid=found).observation(s.T_world_obj, fusion.obs.dt, frame.K, frame.T_color_depth)
            upd = joint_update(self.backend, fusion, lm_obs, lm_var)
            s = replace(s, T_cam_obj=torch.where(mask[:, None, None], upd.T_cam_obj.to(s.T_cam_obj.dtype), s.T_cam_obj))
            acq = acq._replace(valid=acq.valid & (upd.used | ~upd.updated[:, None]), T_world_depth=s.T_world_depth)
        if self.landmarks.refiner is not None and s.mean_var is not None:  # the keyframe window
            s, acq = self._refined(s, acq, frame, cur, keep, mask)
        T_world_depth = torch.where(mask[:, None, None], acq.T_world_depth, s.T_world_depth)
        found = acq.valid & mask[:, None]
        n_found = found.sum(1)
        s = replace(s, T_world_obj=T_world_depth @ s.T_cam_obj, reacquired_total=s.reacquired_total + n_found)
        points = transform_points(T_inv(T_world_depth), acq.points_world).float()  # the ORIGINAL world positions
        return kept.cat(Kept(acq.pixels, points, found, torch.zeros_like(found, dtype=torch.long), acq.cornerness)), \
            n_found, s  # fmt: skip

    def _refined(self, s: TrackerState, acq, frame: FrameBatch, cur: PreparedFrame, keep: Tensor, mask: Tensor):
        """``s`` and ``acq`` after the keyframe window's refinement (:mod:`torchtrack.pipeline.landmark_window`): the
        refined camera becomes the back end's pose (``set_pose``), the re-acquired landmarks take their refined
        positions and inliers."""
        v_pix, v_xyz = s.mean_var.unbind(1)
        X_tr, has = measure_points(cur.depth, frame.K, frame.T_color_depth, s.pixels)
        world = transform_points(s.T_world_obj, s.points_obj.double())
        cov = self.backend.pose_covariance() if self.landmarks.window_prior else None
        k = self.backend.measurement_scale()  # the window weighs the measurements by the filter's R: k R0
        if k is not None:
            v_pix, v_xyz = v_pix * k[:, 0].to(v_pix.dtype), v_xyz * k[:, 1].to(v_xyz.dtype)
        ref = refine_at_reselection(self.landmarks, self.keyframes, self.landmarks.refiner, acq, s.pixels, keep & has,
                                    X_tr, world, self.landmarks.survivor_ident, s.T_world_depth, v_pix, v_xyz, frame.K,
                                    frame.T_color_depth, mask, self.landmarks.max_correction_m,
                                    self.landmarks.max_correction_rad, camera_cov=cov,
                                    xyz_scale=None if k is None else k[:, 1])  # fmt: skip
        # projected onto SE(3): a product with T_world_obj's round-off, fed back through T_inv at every window, grew
        # 7x per re-selection (a 0.4 m jump after ~20 windows on 7-Scenes)
        T_cam_obj = torch.where(ref.used[:, None, None], rigid(T_inv(ref.T_world_depth) @ s.T_world_obj), s.T_cam_obj)
        self.backend.set_pose(T_cam_obj, ref.used)
        s = replace(s, T_cam_obj=T_cam_obj)
        return s, acq._replace(points_world=ref.points_world, valid=ref.valid, T_world_depth=s.T_world_depth)

    def _relocalised(self, frame: FrameBatch, cur: PreparedFrame, res: StepResult, dec: Relocalisation) -> StepResult:
        """Apply the relocaliser's decision: the sequences it relocalised take the current frame as a new model at the
        camera pose it found (its features are dropped first: they followed the wrong motion, so no survivor carries
        over; the motion estimate restarts at zero, so the next frame's LK is not started along it). Returns ``res``
        with their new pose."""
        s, mask = self.state, dec.relocalised
        m3 = mask[:, None, None]
        T_world_obj = torch.where(m3, dec.T_world_depth.double() @ s.T_cam_obj, s.T_world_obj)
        velocity = torch.where(mask[:, None], 0.0, s.velocity)  # the lost frame's motion was the wrong one
        s = replace(s, valid=s.valid & ~mask[:, None], T_world_obj=T_world_obj, velocity=velocity)
        self.backend.reset(s.T_cam_obj, mask)  # the lost filter's posterior is no prior of the new model (its window)
        self.state, T_model = self._new_model(s, frame, cur, mask)
        model = T_model if res.model_T_cam_obj is None else torch.where(m3, T_model, res.model_T_cam_obj)
        return replace(
            res, T_world_depth=torch.where(m3, self.state.T_world_depth, res.T_world_depth),
            reselected=res.reselected | mask, model_T_cam_obj=model,
        )  # fmt: skip

    def _keyframe(self, frame: FrameBatch, cur: PreparedFrame, due: Tensor, reselected: Tensor) -> None:
        """The current frame of the sequences in ``due`` (B,) becomes a keyframe at the camera pose of the state (where
        ``reselected`` (B,) a model keyframe, with the new model's features; the landmarks' re-fit included); the
        landmarks (model keyframes) and the relocaliser (every keyframe) attach their content to it."""
        if not due.any():
            return
        s = self.state
        slot = self.keyframes.add(frame.timestamp, s.T_world_depth, due, reselected)
        if self.landmarks is not None:  # a model keyframe's features are landmarks at their world positions
            world = transform_points(s.T_world_obj, s.points_obj.double())
            model_slot = torch.where(reselected, slot, -1)
            var_xyz = None if s.mean_var is None else s.mean_var[:, 1]  # the keyframe's (its window's) 3D variance
            self.landmarks.add(self.keyframes, model_slot, cur, s.pixels, world, s.cornerness, s.valid, var_xyz)
        if self.relocaliser is not None:
            self.relocaliser.add(slot, frame, cur, s.T_world_depth)


# ---------------------------------------------------------------------------------------------- helpers
def _flow_args(with_cues: bool, init: Tensor | None) -> dict:
    args = dict(with_residual=True) if with_cues else {}  # the LK residual is a cue
    return args if init is None else {**args, "init": init}


def _gather_padded(x: Tensor, order: Tensor, fill: float) -> Tensor:
    """(B, N') ``x`` (B, N) taken in ``order`` (B, N') of indices into x's features followed by new ones (``fill``)."""
    extra = max(int(order.max()) + 1 - x.shape[1], 0) if order.numel() else 0
    return torch.cat([x, x.new_full((x.shape[0], extra), fill)], 1).gather(1, order)


def _result(s: TrackerState, winner: Tensor | None, d_tim: Tensor | None, reselected: Tensor, **extra) -> StepResult:
    """The frame's result from the state ``s`` (``extra``: StepResult's optional fields)."""
    res = torch.where(s.valid, s.residuals, torch.zeros_like(s.pixels[..., 0]))
    err = res.sum(1) / s.valid.sum(1).clamp_min(1)  # mean reprojection error, eq. (16)
    return StepResult(
        T_cam_obj=s.T_cam_obj,
        T_world_depth=s.T_world_depth,
        pixels=s.pixels,
        valid=s.valid,
        winner=winner if winner is not None else torch.full_like(s.valid, -1, dtype=torch.long),
        points_obj=s.points_obj,
        reprojection_error=err,
        n_features=s.valid.sum(1),
        reselected=reselected,
        d_tim=d_tim if d_tim is not None else torch.zeros_like(s.pixels[..., 0]),
        **extra,
    )


__all__ = ["FEATURE_FIELDS", "StepResult", "Tracker", "TrackerState"]
