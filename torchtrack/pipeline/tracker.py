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

from torchtrack.data.frame import FrameBatch
from torchtrack.estimators.backends import PoseBackend
from torchtrack.estimators.base import masked_mean
from torchtrack.filter.frame import Observation
from torchtrack.filter.weighting import Variances, WeightingInputs, pixel_only_variances
from torchtrack.frontend import FrontEnd, PreparedFrame, is_registered
from torchtrack.geometry import T_inv, make_T, project, se3_exp, se3_log, transform_points
from torchtrack.image.flow import TrackResult
from torchtrack.map.dense_map import DenseMap
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.landmarks import LandmarkMap
from torchtrack.pipeline.outliers import ResidualDrop, feature_residuals
from torchtrack.pipeline.relocalise import Relocaliser
from torchtrack.pipeline.reselect import Kept, PointEstimate, Reselection
from torchtrack.pipeline.state import FEATURE_FIELDS, Measure, StepResult, TrackerState, frame_cues, pad_to, where_rows


class Tracker:
    """Model-free RGB-D rigid tracker (paper §III), batched over B sequences in lockstep, composed of stages.

    Args:
        frontend: per-frame preparation (registered depth, SIM, pyramids).
        flow: combined LK + TIM tracker (eq. 10), ``flow(prev, next, pixels, valid) -> TrackResult``.
        weighting: per-feature noise variances (eqs. 11-14), ``weighting(WeightingInputs) -> Variances``.
        backend: the pose estimator (fusion EKF or a registration baseline), :class:`PoseBackend`.
        reselect: the model stage (:class:`~torchtrack.pipeline.reselect.Reselection`): its region of interest and
            spatio-textural selection (eq. 9) take a model's features; when too few survive it takes a new one, and
            what the new model keeps.
        outliers: which features leave the model after the update (:class:`~torchtrack.pipeline.outliers.ResidualDrop`).
        keyframes: the one keyframe store (:class:`~torchtrack.pipeline.keyframes.KeyframeStore`; None: a default
            one): a model frame, or a tracked frame every ``keyframes.every`` frames, with a trusted pose becomes a
            keyframe; the landmarks and the relocaliser attach their content to it.
        landmarks: improvement (None = paper): model points that outlive their model
            (:class:`~torchtrack.pipeline.landmarks.LandmarkMap`): at a re-selection the visible landmarks of the
            keyframes are re-tracked and join the new model at their ORIGINAL world positions, after the survivors and
            before new features; with ``landmarks.correct`` the camera the new model is anchored at is first re-fitted
            to them. With a dense map, only where its alignment of that frame did not apply: where it did, the model
            is placed against all the camera saw, and the landmarks' older, chained anchors would pull it off.
        relocaliser: improvement (None = no loss check): after each frame, the loss check
            (:class:`~torchtrack.pipeline.relocalise.Relocaliser`) against the keyframes' ORB descriptors; the
            relocalised sequences take a new model at the camera pose it found.
        predict_init: improvement (False = paper): each feature's LK starts where the model point projects under the
            constant-velocity prediction of the pose (``TrackerState.velocity``), not at its previous pixel: under
            fast motion the displacement left to LK is the prediction's error, not the whole motion.
        pixel_only: improvement (False = paper): a tracked feature without depth at its pixel this frame (a hole, an
            edge, a band a separate depth camera does not see) stays in the model and measures its pixel only (eq. 7);
            a re-selection counts the features measured with depth. The paper drops it (eq. 6 needs the depth).

    Observers: ``tracker.observers.append(fn)`` registers ``fn(frame, result)``, called after every step with its
    :class:`StepResult` (the observation cache records it, :mod:`torchtrack.learn.record`). The per-feature cues
    (:mod:`torchtrack.filter.cues`) are computed where the weighting is called, when the weighting or an observer
    asks for them with ``needs_cues = True``; they arrive in ``WeightingInputs.cues`` and ``StepResult.cues``. Poses
    are the same with and without them.

    One owner per piece of state: the tracker's model and last estimate live in ``self.state``
    (:class:`TrackerState`), which only :meth:`step` replaces; the back end owns the filter, the landmarks their
    keyframes' features, the relocaliser its descriptors. The back end's pose moves by its ``step`` once per frame and
    by ``reset`` where a new model is taken (:meth:`_new_model`, the one place that also places the model in the
    world, ``T_world_obj``).
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
        dense: DenseMap | None = None,
        predict_init: bool = True,
        pixel_only: bool = True,
    ) -> None:
        self.frontend, self.flow, self.weighting, self.backend = frontend, flow, weighting, backend
        self.reselect = reselect
        self.outliers = outliers if outliers is not None else ResidualDrop()
        self.keyframes = keyframes if keyframes is not None else KeyframeStore()
        self.landmarks, self.relocaliser, self.dense = landmarks, relocaliser, dense
        self.predict_init, self.pixel_only = predict_init, pixel_only
        self.observers: list[Callable[[FrameBatch, StepResult], None]] = []
        self.state = TrackerState()

    def reset(self) -> None:
        """Forget the run: the next :meth:`step` is a first frame (new sequences, any batch size), and every stage
        starts anew there (the back end's noise scales included)."""
        self.state = TrackerState()

    def step(self, frame: FrameBatch) -> StepResult:
        """One frame of every sequence, in the paper's order (§III); then each of ``observers`` sees the result."""
        s, region = self.state, _once(lambda: self._map_region(frame))  # the model's region: computed on first use
        cur = self.frontend(frame)  # prepare: depth in the colour camera, SIM (eq. 8), LK pyramids
        measure = _measure(frame, cur)  # a pixel's 3D point, eq. (6)
        if not s.started:
            res, held = self._start(frame, cur, measure), None  # the first model: features selected (§III-B, eq. 9)
        else:
            track = self._tracked(s, frame, cur)  # LK on intensity and on the SIM, the TIM check (§III-C, eq. 10)
            obs = self._observed(s, frame, track, measure)  # each feature's 3D point, eq. (6), and pixel, eq. (7)
            var, cues = self._weighted(s, frame, cur, track, obs)  # §III-D, eqs. (11)-(14)
            est = self.backend.step(obs, var, active=frame.active)  # the EKF (§III-A, eqs. 2-7, 15)
            tracked = self._advanced(s, frame, cur, obs, var, est.T_cam_obj.double())  # outliers, eq. (16)
            reselect = self.reselect.needed(tracked.valid & obs.valid_xyz, tracked.n_model, frame.active)  # few left
            tracked, held = self._placed(tracked, frame, reselect, region)  # the model's world pose, on the dense map
            self.state, model = self._reselected(tracked, frame, cur, measure, reselect, held)  # a new model, §III-B
            res = _result(tracked, track.winner, track.d_tim, reselect, observation=obs, variances=var, cues=cues,
                          model_T_cam_obj=model, estimate=est)  # fmt: skip
        res, trusted = self._loss_check(frame, cur, measure, res, s, held)
        due = self.keyframes.due(res.reselected, frame.active) & trusted
        self._keyframe(frame, cur, measure, due, res.reselected, region)
        for observe in self.observers:
            observe(frame, res)
        return res

    # ---------------------------------------------------------------------------------------------- per frame
    def _tracked(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame) -> TrackResult:
        """The model's features tracked from the previous frame into ``cur`` (eq. 10), LK started at their previous
        pixels or (``predict_init``) at the model points' projections under the predicted pose; with the LK residual
        where the cues are asked for (it is one)."""
        args = dict(with_residual=True) if _cues_asked(self) else {}
        if self.predict_init:
            args["init"] = self._predicted_pixels(s, frame, _dt(frame, s))
        return self.flow(s.prev.flow, cur.flow, s.pixels, s.valid, **args)

    def _observed(self, s: TrackerState, frame: FrameBatch, track: TrackResult, measure: Measure) -> Observation:
        """What the back end measures of the tracked features: their 3D points where the depth has them (eq. 6) and
        their pixels (eq. 7): where tracked (``pixel_only``), else only where the depth has them too (the paper)."""
        points_d, has_depth = measure(track.points)  # eq. (6)
        valid = track.valid & frame.active[:, None]
        valid = valid if self.pixel_only else valid & has_depth
        return Observation(_dt(frame, s).to(points_d.dtype), s.points_obj, points_d, track.points, valid, frame.K,
                           frame.T_color_depth, has_depth=has_depth)  # fmt: skip

    def _weighted(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, track: TrackResult,
                  obs: Observation) -> tuple[Variances, Tensor | None]:  # fmt: skip
        """The features' variances (eqs. 11-14; a pixel-only feature's 3D variance left out), and their cues (B, N, C)
        where the weighting or an observer of the step asks for them (``needs_cues = True``), else None."""
        valid_xyz = obs.valid_xyz
        cues = frame_cues(s, cur, track, obs.points_d, valid_xyz) if _cues_asked(self) else None
        var = self.weighting(WeightingInputs(track.d_tim, obs.points_d[..., 2], obs.points_d, valid_xyz,
                                             frame.K_depth[:, 0, 0], cues=cues))  # fmt: skip
        return pixel_only_variances(var, obs.valid, valid_xyz), cues

    @staticmethod
    def _predicted_pixels(s: TrackerState, frame: FrameBatch, dt: Tensor) -> Tensor:
        """(B, N, 2) colour pixels of the model points under the constant-velocity pose prediction over ``dt`` (B,)
        seconds, ``T_pred = exp(xi dt) T_cam_obj``; the previous pixel where the prediction does not project."""
        T_pred = se3_exp(s.velocity * dt[:, None]) @ s.T_cam_obj
        points_c = transform_points(frame.T_color_depth.double() @ T_pred, s.points_obj.double())
        pix = project(frame.K.double(), points_c)
        ok = (points_c[..., 2] > 1e-3) & torch.isfinite(pix).all(-1) & s.valid
        return torch.where(ok[..., None], pix.to(s.pixels.dtype), s.pixels)

    def _advanced(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, obs: Observation, var: Variances,
                  T_cam_obj: Tensor) -> TrackerState:  # fmt: skip
        """The state after this frame's update to ``T_cam_obj`` (B, 4, 4): the new pose (ended sequences keep theirs)
        and the observed tracks, one frame older; features that do not fit the pose dropped (eq. 16, the outlier
        stage); with ``reselect.point_mean`` the kept features' measured 3D points fused into their model points'
        estimates."""
        T_cam_obj = torch.where(frame.active[:, None, None], T_cam_obj, s.T_cam_obj)
        velocity = se3_log(T_cam_obj @ T_inv(s.T_cam_obj)) / _dt(frame, s)[:, None]  # this frame's motion, per second
        velocity = torch.where(frame.active[:, None], velocity, s.velocity)
        residuals = feature_residuals(frame.K, frame.T_color_depth, T_cam_obj, s.points_obj, obs.pixels, obs.valid)
        s = replace(s, prev=cur, timestamp=frame.timestamp, pixels=obs.pixels, valid=self.outliers(residuals, obs.valid),
                    age=s.age + 1, residuals=residuals, T_cam_obj=T_cam_obj, velocity=velocity)  # fmt: skip
        if not self.reselect.estimates_points:
            return s
        est = PointEstimate(s.points_mean, s.points_info)
        est = self.reselect.fused(est, T_cam_obj, obs.points_d, var.var_xyz, s.valid & obs.valid_xyz)
        return replace(s, points_mean=est.mean, points_info=est.info)

    def _placed(self, s: TrackerState, frame: FrameBatch, reselect: Tensor,
                region: Callable[[], Tensor | None]) -> tuple[TrackerState, Tensor | None]:  # fmt: skip
        """``s`` with the model moved in the world (``T_world_obj``) so that the camera is where the dense map puts it
        (:meth:`DenseMap.align`, in the model's ``region()``), in the sequences it is due for (a re-selection anchors
        the new model there); the model's pose in the camera, hence the features and the filter, unchanged. Returns
        (that state, where the alignment applied (B,), None where it did not run)."""
        if self.dense is None:
            return s, None
        due = self.dense.due(reselect, frame.active)
        if not due.any():
            return s, None
        al = self.dense.align(frame.depth, frame.K_depth, s.T_world_depth, due, region())
        # only where applied: elsewhere a round trip through the camera would move the model by round-off
        placed = torch.where(al.applied[:, None, None], al.T_world_cam @ s.T_cam_obj, s.T_world_obj)
        return replace(s, T_world_obj=placed), al.applied

    def _map_region(self, frame: FrameBatch) -> Tensor | None:
        """(B, 1, H, W) bool the model's region (the object, or the scene) in the depth as the depth camera took it (its
        own grid: a separate depth camera's frames are not warped into the colour camera's, whose resampling errors
        would enter the map): what the dense map holds (a moving object's background must not pull its pose). The step
        computes it once per frame, on first use (the alignment and a keyframe's fusion share it); None where it is
        every pixel with depth."""
        if getattr(self.reselect.region, "all_depth", False):  # a custom region callable: computed
            return None
        return self.reselect.region(frame.depth)

    def _loss_check(self, frame: FrameBatch, cur: PreparedFrame, measure: Measure, res: StepResult,
                    before: TrackerState, held: Tensor | None) -> tuple[StepResult, Tensor]:  # fmt: skip
        """The relocaliser's loss check of this frame (``before``: the state the frame was tracked from) and its
        decision applied: the relocalised sequences take the current frame as a new model at the camera pose it found
        (their features followed the wrong motion, so none carries over, and the motion estimate restarts at zero;
        ``held``: where this frame's dense alignment placed the model). Returns ``res`` with their new pose, and which
        sequences' poses are trusted (B,)."""
        if self.relocaliser is None:
            return res, frame.active
        n_prev = before.valid.sum(1) if before.started else None
        dec = self.relocaliser.check(self.keyframes, frame, cur, res, n_prev)
        lost = dec.relocalised
        if lost.any():
            s = self.state
            s = replace(s, valid=s.valid & ~lost[:, None], velocity=torch.where(lost[:, None], 0.0, s.velocity))
            self.state, T_model = self._new_model(s, frame, cur, measure, lost, dec.T_world_depth.double(), held=held)
            m3 = lost[:, None, None]
            model = T_model if res.model_T_cam_obj is None else torch.where(m3, T_model, res.model_T_cam_obj)
            res = replace(res, T_world_depth=torch.where(m3, self.state.T_world_depth, res.T_world_depth),
                          reselected=res.reselected | lost, model_T_cam_obj=model)  # fmt: skip
        return replace(res, loss=dec.loss), frame.active & self.relocaliser.trusted(dec)

    # ---------------------------------------------------------------------------------------------- the model
    def _reselected(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, measure: Measure, mask: Tensor,
                    held: Tensor | None) -> tuple[TrackerState, Tensor | None]:  # fmt: skip
        """``s`` after the sequences in ``mask`` (B,) took a new model (:meth:`_new_model`; ``held``: where the dense
        map placed it), and the pose the back end was reset to; ``s`` and None where none did."""
        return self._new_model(s, frame, cur, measure, mask, held=held) if mask.any() else (s, None)

    def _start(self, frame: FrameBatch, cur: PreparedFrame, measure: Measure) -> StepResult:
        """First frame: every sequence takes it as its model; the world is the first camera."""
        B, dev = frame.rgb.shape[0], frame.rgb.device
        eye = torch.eye(4, dtype=torch.float64, device=dev).expand(B, 4, 4).clone()
        zero = torch.zeros(B, 6, dtype=torch.float64, device=dev)
        s = TrackerState(timestamp=frame.timestamp, T_cam_obj=eye, T_world_obj=eye.clone(), velocity=zero,
                         reacquired_total=torch.zeros(B, dtype=torch.long, device=dev))  # fmt: skip
        self.keyframes.reset(B, dev)
        self.backend.start()  # a tracker can run again: nothing of the last run carries over
        if self.landmarks is not None:
            self.landmarks.reset()
        if self.relocaliser is not None:
            self.relocaliser.reset(B, self.keyframes.slots, dev)
        if self.dense is not None:
            self.dense.reset(B, dev)
        everyone = torch.ones(B, dtype=torch.bool, device=dev)
        self.state, model_T_cam_obj = self._new_model(s, frame, cur, measure, everyone)
        return _result(self.state, None, None, everyone, model_T_cam_obj=model_T_cam_obj)

    def _new_model(self, s: TrackerState, frame: FrameBatch, cur: PreparedFrame, measure: Measure, mask: Tensor,
                   T_world_depth: Tensor | None = None, *,
                   held: Tensor | None = None) -> tuple[TrackerState, Tensor]:  # fmt: skip
        """§III re-selection: the state ``s`` after the sequences in ``mask`` (B,) took the current frame as their
        model, anchored at the camera ``T_world_depth`` (B, 4, 4; default: the state's): the features it keeps
        (survivors, re-acquired landmarks, which may correct that camera), then new features (eq. 9) away from them.
        The model frame is the camera moved to the features' centroid; the back end starts over there. ``held`` (B,):
        where this frame's dense alignment placed the model (no landmarks re-acquired there). Returns (the new state,
        the pose (B, 4, 4) the back end was reset to, meaningful where ``mask``)."""
        T_world_depth = s.T_world_depth if T_world_depth is None else T_world_depth
        kept, n_found, T_world_depth = self._anchors(s, cur, measure, mask, T_world_depth, held)
        feats = self.reselect.select(cur.gray, cur.depth, frame.K, roi=self.reselect.roi(cur.depth), sim=cur.sim)
        pixels, cornerness = feats.pixels, torch.stack([feats.cornerness_int, feats.cornerness_sim], -1)
        points_d, has_depth = measure(pixels)  # eq. (6)
        valid = feats.valid & has_depth
        age, info = torch.zeros_like(valid, dtype=torch.long), None
        if kept is not None:
            pixels, points_d, valid, age, cornerness, info = self.reselect.merge(
                kept, pixels, points_d, valid, cornerness, n_found, s.pixels.shape[1]
            )
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        points_obj = torch.where(valid[..., None], points_d - centroid[:, None], torch.zeros_like(points_d))
        eye = torch.eye(3, dtype=torch.float64, device=centroid.device).expand(len(mask), 3, 3)
        new = dict(pixels=pixels, valid=valid, points_obj=points_obj, age=age, cornerness=cornerness)
        if self.reselect.estimates_points:  # the model frame is the camera's, moved: the information is not rotated
            if info is None:  # new points: the birth sample alone
                info = torch.zeros(*valid.shape, 3, 3, dtype=torch.float64, device=valid.device)
            new |= dict(points_mean=points_obj.double(), points_info=info)
        if s.pixels is not None:  # selections differ in size: pad both to the larger N; old rows outside mask
            n = max(s.pixels.shape[1], valid.shape[1])
            new = {k: where_rows(mask, pad_to(v, n), pad_to(getattr(s, k), n)) for k, v in new.items()}
        m3, n_model = mask[:, None, None], new["valid"].sum(1)
        T_cam_obj = torch.where(m3, make_T(eye, centroid.double()), s.T_cam_obj)
        s = replace(
            s, prev=cur, **new, T_cam_obj=T_cam_obj,
            T_world_obj=torch.where(m3, T_world_depth @ T_cam_obj, s.T_world_obj),
            n_model=n_model if s.n_model is None else torch.where(mask, n_model, s.n_model),
            reacquired_total=s.reacquired_total + (0 if n_found is None else n_found),
        )  # fmt: skip
        residuals = feature_residuals(frame.K, frame.T_color_depth, T_cam_obj, s.points_obj, s.pixels,
                                      s.valid)  # fmt: skip  # in the new layout: the next frame's prev_reproj cue
        self.backend.reset(T_cam_obj, mask)
        return replace(s, residuals=residuals), T_cam_obj

    def _anchors(self, s: TrackerState, cur: PreparedFrame, measure: Measure, mask: Tensor, T_world_depth: Tensor,
                 held: Tensor | None) -> tuple[Kept | None, Tensor | None, Tensor]:  # fmt: skip
        """What a new model of the sequences in ``mask`` (B,) keeps before it selects new features, in the current
        camera ``T_world_depth`` (B, 4, 4): the survivors (``reselect.keep_survivors``; their model points moved into
        the camera by the current pose, so that the new model frame sees them where the old one did) and then the
        re-acquired landmarks (their stored world positions moved into the camera). Returns (the kept features, None
        on the first frame or with neither; the re-acquired count (B,), None without landmarks; the camera, re-fitted
        to the landmarks where ``landmarks.correct`` applies)."""
        if s.pixels is None or not (self.reselect.keep_survivors or self.landmarks is not None):
            return None, None, T_world_depth
        keep = self.reselect.survivors(s.valid, mask)
        if s.points_mean is None:
            kept = Kept(s.pixels, transform_points(s.T_cam_obj.float(), s.points_obj.float()), keep, s.age,
                        s.cornerness)  # fmt: skip
        else:  # survivors carry their estimates, in the camera
            R = s.T_cam_obj[:, None, :3, :3]
            kept = Kept(s.pixels, transform_points(s.T_cam_obj, s.points_mean).float(), keep, s.age, s.cornerness,
                        R @ s.points_info @ R.transpose(-1, -2))  # fmt: skip
        if self.landmarks is None:
            return kept, None, T_world_depth
        world = transform_points(s.T_world_obj, s.points_obj.double())  # the kept features' prior in the re-fit
        if held is not None:  # where the dense map placed the model, it already holds what was seen
            mask = mask & ~held
        acq = self.landmarks.reacquire(self.keyframes, self.flow, cur, measure, T_world_depth, s.pixels, keep, mask,
                                       tracked_world=world)  # fmt: skip
        T_world_depth = torch.where(mask[:, None, None], acq.T_world_depth, T_world_depth)
        found = acq.valid & mask[:, None]
        points = transform_points(T_inv(T_world_depth), acq.points_world).float()  # the ORIGINAL world positions
        landmarks = Kept(acq.pixels, points, found, torch.zeros_like(found, dtype=torch.long), acq.cornerness)
        return kept.cat(landmarks), found.sum(1), T_world_depth

    def _keyframe(self, frame: FrameBatch, cur: PreparedFrame, measure: Measure, due: Tensor, reselected: Tensor,
                  region: Callable[[], Tensor | None]) -> None:  # fmt: skip
        """The current frame of the sequences in ``due`` (B,) becomes a keyframe at the camera pose of the state (where
        ``reselected`` (B,) a model keyframe, with the new model's features); the landmarks (model keyframes), the
        relocaliser (every keyframe) and the dense map (the model's ``region()`` of its depth) attach their content."""
        if not due.any():
            return
        s = self.state
        slot = self.keyframes.add(frame.timestamp, s.T_world_depth, due, reselected)
        if self.landmarks is not None:  # a model keyframe's features are landmarks at their world positions
            world = transform_points(s.T_world_obj, s.points_obj.double())
            self.landmarks.add(self.keyframes, torch.where(reselected, slot, -1), cur, s.pixels, world, s.cornerness,
                               s.valid)  # fmt: skip
        if self.relocaliser is not None:
            self.relocaliser.add(slot, cur, measure, s.T_world_depth)
        if self.dense is not None:
            self.dense.add(frame.depth, frame.K_depth, s.T_world_depth, due, region())


# ---------------------------------------------------------------------------------------------- helpers
def _measure(frame: FrameBatch, cur: PreparedFrame) -> Measure:
    """The frame's measurement of a pixel's 3D point (eq. 6); with a separate depth camera, along its rays."""
    raw = None if is_registered(frame) else frame.depth
    return Measure(cur.depth, frame.K, frame.T_color_depth, raw, frame.K_depth)


def _cues_asked(tracker: Tracker) -> bool:
    """Whether the tracker's weighting or one of its observers asks for the features' cues (``needs_cues``)."""
    return any(getattr(x, "needs_cues", False) for x in (tracker.weighting, *tracker.observers))


def _once(compute: Callable[[], Tensor | None]) -> Callable[[], Tensor | None]:
    """``compute`` called on the first call only; later calls return its value."""
    box = []
    return lambda: box[0] if box else (box.append(compute()) or box[0])


def _dt(frame: FrameBatch, s: TrackerState) -> Tensor:
    """(B,) float64 seconds since the previous frame (at least 1 ms: repeated time stamps)."""
    return (frame.timestamp - s.timestamp).double().clamp_min(1e-3)


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
