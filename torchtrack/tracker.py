"""The torchtrack pipeline: select -> track -> weight -> update -> (re-select), batched over B sequences.

Frames. ``cam`` is the depth camera. The object frame ``obj`` is the model frame's depth camera moved
to the centroid of the selected features (so rotations about it stay well-conditioned); the model
points X_o live in it. The tracker estimates ``T_cam_obj`` per frame; with the object static in the
world (scene tracking, or a camera moving around an object), the camera pose follows as
``T_world_cam = T_world_obj @ inv(T_cam_obj)``. A re-selection makes the current frame the new model
frame and chains ``T_world_obj`` through the current estimate, so the trajectory stays continuous.

References:
    O. S. Gedik, A. A. Alatan, "Fusing 2D and 3D Clues for 3D Tracking Using Visual and Range Data",
    FUSION 2013.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from torchtrack.data.frame import FrameBatch
from torchtrack.estimation import Observation, PoseBackend
from torchtrack.estimators.base import masked_mean
from torchtrack.filter.weighting import Variances, WeightingInputs
from torchtrack.frontend import FrontEnd, PreparedFrame, measure_points, smooth_depth_mask
from torchtrack.geometry import T_inv, make_T, sample_depth, transform_points
from torchtrack.image.flow import TrackResult
from torchtrack.learn.cues import stack_cues
from torchtrack.metrics import reprojection_errors


@dataclass
class StepResult:
    """Per-frame outputs, each batched over B.

    Attributes:
        T_cam_obj: (B, 4, 4) float64 object pose in the depth camera.
        T_world_cam: (B, 4, 4) float64 camera pose (camera-to-world) for a static object/scene.
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
    """

    T_cam_obj: Tensor
    T_world_cam: Tensor
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


def pad_to(x: Tensor, n: int) -> Tensor:
    """Pad (or keep) the feature dimension (dim 1) of x to n with zeros (False for masks)."""
    if x.shape[1] >= n:
        return x
    pad = torch.zeros(x.shape[0], n - x.shape[1], *x.shape[2:], dtype=x.dtype, device=x.device)
    return torch.cat([x, pad], dim=1)


class Tracker:
    """Model-free RGB-D rigid tracker (paper §III), batched over B sequences in lockstep.

    Args:
        frontend: per-frame preparation (registered depth, SIM, pyramids).
        region: ``region(depth (B,1,H,W)) -> (B,1,H,W) bool`` region of interest of the model
            (object by depth thresholding, or the whole frame).
        select: ``select(gray, depth, K, roi=, sim=) -> Features``, spatio-textural selection (eq. 9).
        flow: combined LK + TIM tracker (eq. 10), ``flow(prev, next, pixels, valid) -> TrackResult``.
        weighting: per-feature noise variances (eqs. 11-14).
        backend: the pose estimator (fusion EKF or a registration baseline).
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
        record: compute the per-feature cues (:mod:`torchtrack.learn.cues`) of every frame into
            ``StepResult.cues`` even when the weighting does not need them (for the observation cache). Poses are
            the same with and without; a weighting with ``needs_cues = True`` gets them in any case.

    Per-feature state, (B, N) like ``pixels``/``valid``: ``age`` (frames since selection) and ``cornerness``
    (B, N, 2) (intensity and SIM cornerness of eq. (9) at selection); survivors of a re-selection keep theirs.
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
        reselect_fraction: float = 0.5,
        min_features: int = 12,
        edge_step: float | None = None,
        max_residual_px: float | None = None,
        keep_survivors: bool = False,
        min_separation_px: float = 8.0,
        record: bool = False,
    ) -> None:
        if not 0.0 <= reselect_fraction < 1.0:
            raise ValueError(f"reselect_fraction must be in [0, 1), got {reselect_fraction}")
        self.frontend, self.region, self.select = frontend, region, select
        self.flow, self.weighting, self.backend = flow, weighting, backend
        self.reselect_fraction, self.min_features = reselect_fraction, min_features
        self.edge_step, self.max_residual_px = edge_step, max_residual_px
        self.keep_survivors, self.min_separation_px = keep_survivors, min_separation_px
        self.record = record
        self.prev: PreparedFrame | None = None

    @property
    def wants_cues(self) -> bool:
        """Whether this frame's cues are computed: when recording, or for a weighting with ``needs_cues``."""
        return self.record or bool(getattr(self.weighting, "needs_cues", False))

    def step(self, frame: FrameBatch) -> StepResult:
        """Process one frame of every sequence; reads like the paper's algorithm."""
        cur = self.frontend(frame)  # depth in the colour camera, SIM (eq. 8), LK pyramids
        if self.prev is None:
            return self._start(frame, cur)
        want_cues = self.wants_cues
        flow_args = dict(with_residual=True) if want_cues else {}  # the LK residual is a cue
        track = self.flow(self.prev.flow, cur.flow, self.pixels, self.valid, **flow_args)  # §III-C, eq. (10)
        points_d, has_depth = measure_points(cur, frame, track.points)  # X_d of eq. (6)
        valid = track.valid & has_depth & frame.active[:, None]
        cues = self._cues(frame, cur, track, points_d, valid) if want_cues else None
        inputs = WeightingInputs(track.d_tim, points_d[..., 2], points_d, valid, frame.K_depth[:, 0, 0], cues=cues)
        var = self.weighting(inputs)
        dt = (frame.timestamp - self.timestamp).to(points_d.dtype).clamp_min(1e-3)
        obs = Observation(dt, self.points_obj, points_d, track.points, valid, frame.K, frame.T_color_depth)
        T_cam_obj = self.backend(obs, var).double()  # eqs. (2)-(7), (15)
        self._advance(frame, track.points, valid, T_cam_obj)
        n = self.valid.sum(1)
        reselect = frame.active & ((n < self.reselect_fraction * self.n_model) | (n < self.min_features))
        result = self._result(frame, track.winner, track.d_tim, reselect, observation=obs, variances=var, cues=cues)
        if reselect.any():
            result = replace(result, model_T_cam_obj=self._new_model(frame, cur, reselect))  # §III re-selection
        self.prev = cur
        return result

    def _cues(self, frame: FrameBatch, cur: PreparedFrame, track: TrackResult, points_d: Tensor, valid: Tensor):
        """(B, N, C) cues of the tracked features (:data:`torchtrack.learn.cues.CUE_NAMES`), zeros where not valid."""
        H, W = cur.gray.shape[-2:]
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        sim = sample_depth(cur.sim.si, track.points) if cur.sim is not None else torch.full_like(track.d_tim, 0.5)
        cues = stack_cues(
            d_tim_int=track.d_tim_int, d_tim_sim=track.d_tim_sim, sim_won=track.winner == 1,
            lk_residual=track.residual, depth=points_d[..., 2],
            centroid_dist=torch.linalg.vector_norm(points_d - centroid[:, None], dim=-1),
            cornerness_int=self.cornerness[..., 0], cornerness_sim=self.cornerness[..., 1],
            sim_value=sim,  # nearest pixel of the SI map: masked (planar, no depth) pixels carry its fill value
            track_age=self.age + 1,
            prev_reproj=torch.where(self.age > 0, self.residuals, 0.0),  # a new feature has no previous frame
            u_norm=track.points[..., 0] / W, v_norm=track.points[..., 1] / H,
        )  # fmt: skip
        return torch.where(valid[..., None], cues, 0.0)

    def _advance(self, frame: FrameBatch, pixels: Tensor, valid: Tensor, T_cam_obj: Tensor) -> None:
        """Keep the new pose and tracks (ended sequences keep theirs); drop features that do not fit the pose."""
        self.T_cam_obj = torch.where(frame.active[:, None, None], T_cam_obj, self.T_cam_obj)
        self.pixels, self.valid, self.timestamp = pixels, valid, frame.timestamp
        self.age = self.age + 1
        self.residuals = self._residuals(frame)  # computed once: for the drop and for eq. (16)
        if self.max_residual_px is not None:
            self.valid = valid & (self.residuals <= self.max_residual_px)

    # ----------------------------------------------------------------------------------------------
    def _start(self, frame: FrameBatch, cur: PreparedFrame) -> StepResult:
        B = frame.rgb.shape[0]
        self.T_world_cam0 = torch.where(
            frame.gt_valid[:, None, None], frame.T_world_cam_gt, torch.eye(4, dtype=torch.float64).expand(B, 4, 4)
        )
        self.T_cam_obj = torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone()
        self.T_world_obj = torch.eye(4, dtype=torch.float64).expand(B, 4, 4).clone()
        self.timestamp = frame.timestamp
        self.pixels = self.valid = self.points_obj = self.n_model = self.age = self.cornerness = None
        everyone = torch.ones(B, dtype=torch.bool)
        model_T_cam_obj = self._new_model(frame, cur, everyone)
        self.prev = cur
        return self._result(frame, None, None, everyone, model_T_cam_obj=model_T_cam_obj)

    def _new_model(self, frame: FrameBatch, cur: PreparedFrame, mask: Tensor) -> Tensor:
        """Take the current frame as the model of the sequences in ``mask`` (B,): PCM features, pose, chain.

        Returns the pose (B, 4, 4) the back end is reset to (meaningful where ``mask``)."""
        roi = self.region(cur.depth)
        if self.edge_step is not None:
            roi = roi & smooth_depth_mask(cur.depth, self.edge_step)
        feats = self.select(cur.gray, cur.depth, frame.K, roi=roi, sim=cur.sim)  # eq. (9)
        pixels, cornerness = feats.pixels, torch.stack([feats.cornerness_int, feats.cornerness_sim], -1)
        points_d, has_depth = measure_points(cur, frame, pixels)
        valid = feats.valid & has_depth
        age = torch.zeros_like(valid, dtype=torch.long)
        if self.keep_survivors and self.pixels is not None:
            pixels, points_d, valid, age, cornerness = self._with_survivors(pixels, points_d, valid, cornerness, mask)
        centroid = masked_mean(points_d, valid.to(points_d.dtype))
        points_obj = torch.where(valid[..., None], points_d - centroid[:, None], torch.zeros_like(points_d))
        T_cam_obj = make_T(torch.eye(3, dtype=torch.float64).expand(len(mask), 3, 3), centroid.double())
        if self.pixels is None:  # first frame: the world is where the first camera is
            T_world_cam = self.T_world_cam0
        else:
            T_world_cam = self.T_world_obj @ T_inv(self.T_cam_obj)
        m3, m2 = mask[:, None, None], mask[:, None]
        if self.pixels is not None:  # selections differ in size: pad old and new to the larger N
            n = max(self.pixels.shape[1], valid.shape[1])
            self.pixels, self.valid, self.points_obj, self.age, self.cornerness = (
                pad_to(t, n) for t in (self.pixels, self.valid, self.points_obj, self.age, self.cornerness)
            )
            pixels, valid, points_obj = pad_to(pixels, n), pad_to(valid, n), pad_to(points_obj, n)
            age, cornerness = pad_to(age, n), pad_to(cornerness, n)
        self.T_world_obj = torch.where(m3, T_world_cam @ T_cam_obj, self.T_world_obj)
        self.T_cam_obj = torch.where(m3, T_cam_obj, self.T_cam_obj)
        self.pixels = pixels if self.pixels is None else torch.where(m2[..., None], pixels, self.pixels)
        self.valid = valid if self.valid is None else torch.where(m2, valid, self.valid)
        self.points_obj = points_obj if self.points_obj is None else torch.where(m3, points_obj, self.points_obj)
        self.age = age if self.age is None else torch.where(m2, age, self.age)
        self.cornerness = cornerness if self.cornerness is None else torch.where(m3, cornerness, self.cornerness)
        n = valid.sum(1)
        self.n_model = n if self.n_model is None else torch.where(mask, n, self.n_model)
        self.residuals = self._residuals(frame)  # in the new layout: the next frame's prev_reproj cue
        self.backend.reset(self.T_cam_obj, mask)
        return self.T_cam_obj

    def _with_survivors(self, pixels: Tensor, points_d: Tensor, valid: Tensor, cornerness: Tensor, mask: Tensor):
        """Keep the tracked features of the sequences in ``mask``, add the new ones (B, M) that are at least
        ``min_separation_px`` from all of them, up to the larger of M and the current model's width (a poor
        selection never cuts survivors). Survivors come first; their model points are moved into the camera by
        the current pose, so that the new model frame sees them where the old one did; they keep their age and
        cornerness (B, M, 2 for the new ones).
        Returns (pixels (B, W, 2), points in the camera (B, W, 3), valid (B, W), age (B, W), cornerness (B, W, 2))."""
        keep = self.valid & mask[:, None]
        old_points = transform_points(self.T_cam_obj.to(points_d.dtype), self.points_obj)
        gap = torch.cdist(pixels, self.pixels).masked_fill(~keep[:, None, :], float("inf")).amin(2)
        ok = torch.cat([keep, valid & (gap >= self.min_separation_px)], 1)
        width = max(valid.shape[1], self.pixels.shape[1])
        order = torch.sort((~ok).to(torch.uint8), dim=1, stable=True).indices[:, :width]  # valid first
        rows = torch.arange(ok.shape[0])[:, None]
        ok = ok[rows, order]
        pixels = torch.cat([self.pixels, pixels], 1)[rows, order]
        points = torch.cat([old_points, points_d], 1)[rows, order]
        age = torch.cat([self.age, torch.zeros_like(valid, dtype=torch.long)], 1)[rows, order]
        cornerness = torch.cat([self.cornerness, cornerness], 1)[rows, order]
        ok3 = ok[..., None]
        return (
            torch.where(ok3, pixels, 0.0), torch.where(ok3, points, 0.0), ok, torch.where(ok, age, 0),
            torch.where(ok3, cornerness, 0.0),
        )  # fmt: skip

    def _residuals(self, frame: FrameBatch) -> Tensor:
        """(B, N) reprojection error of each feature (eq. 16) under the current pose; inf where undefined."""
        T_color_obj = frame.T_color_depth.double() @ self.T_cam_obj
        err = reprojection_errors(frame.K, T_color_obj, self.points_obj, self.pixels, self.valid).float()
        return torch.nan_to_num(err, nan=float("inf"))

    def _result(
        self, frame: FrameBatch, winner: Tensor | None, d_tim: Tensor | None, reselected: Tensor, **extra
    ) -> StepResult:
        """The frame's result from the current state (``extra``: StepResult's optional fields)."""
        B, N = self.valid.shape
        res = torch.where(self.valid, self.residuals, torch.zeros_like(self.pixels[..., 0]))
        err = res.sum(1) / self.valid.sum(1).clamp_min(1)  # mean reprojection error, eq. (16)
        return StepResult(
            T_cam_obj=self.T_cam_obj,
            T_world_cam=self.T_world_obj @ T_inv(self.T_cam_obj),
            pixels=self.pixels,
            valid=self.valid,
            winner=winner if winner is not None else torch.full((B, N), -1, dtype=torch.long),
            points_obj=self.points_obj,
            reprojection_error=err,
            n_features=self.valid.sum(1),
            reselected=reselected,
            d_tim=d_tim if d_tim is not None else torch.zeros(B, N),
            **extra,
        )
