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
from dataclasses import dataclass

import torch
from torch import Tensor

from torchtrack.data.frame import FrameBatch
from torchtrack.estimation import Observation, PoseBackend
from torchtrack.estimators.base import masked_mean
from torchtrack.filter.weighting import WeightingInputs
from torchtrack.frontend import FrontEnd, PreparedFrame, measure_points, smooth_depth_mask
from torchtrack.geometry import T_inv, make_T, transform_points
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
    ) -> None:
        if not 0.0 <= reselect_fraction < 1.0:
            raise ValueError(f"reselect_fraction must be in [0, 1), got {reselect_fraction}")
        self.frontend, self.region, self.select = frontend, region, select
        self.flow, self.weighting, self.backend = flow, weighting, backend
        self.reselect_fraction, self.min_features = reselect_fraction, min_features
        self.edge_step, self.max_residual_px = edge_step, max_residual_px
        self.keep_survivors, self.min_separation_px = keep_survivors, min_separation_px
        self.prev: PreparedFrame | None = None

    def step(self, frame: FrameBatch) -> StepResult:
        """Process one frame of every sequence; reads like the paper's algorithm."""
        cur = self.frontend(frame)  # depth in the colour camera, SIM (eq. 8), LK pyramids
        if self.prev is None:
            return self._start(frame, cur)
        track = self.flow(self.prev.flow, cur.flow, self.pixels, self.valid)  # §III-C, eq. (10)
        points_d, has_depth = measure_points(cur, frame, track.points)  # X_d of eq. (6)
        valid = track.valid & has_depth & frame.active[:, None]
        var = self.weighting(WeightingInputs(track.d_tim, points_d[..., 2], points_d, valid, frame.K_depth[:, 0, 0]))
        dt = (frame.timestamp - self.timestamp).to(points_d.dtype).clamp_min(1e-3)
        obs = Observation(dt, self.points_obj, points_d, track.points, valid, frame.K, frame.T_color_depth)
        T_cam_obj = self.backend(obs, var).double()  # eqs. (2)-(7), (15)
        self._advance(frame, track.points, valid, T_cam_obj)
        result = self._result(frame, track.winner, track.d_tim)
        n = self.valid.sum(1)
        reselect = frame.active & ((n < self.reselect_fraction * self.n_model) | (n < self.min_features))
        if reselect.any():
            self._new_model(frame, cur, reselect)  # §III model re-selection
            result.reselected = reselect
        self.prev = cur
        return result

    def _advance(self, frame: FrameBatch, pixels: Tensor, valid: Tensor, T_cam_obj: Tensor) -> None:
        """Keep the new pose and tracks (ended sequences keep theirs); drop features that do not fit the pose."""
        self.T_cam_obj = torch.where(frame.active[:, None, None], T_cam_obj, self.T_cam_obj)
        self.pixels, self.valid, self.timestamp = pixels, valid, frame.timestamp
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
        self.pixels = self.valid = self.points_obj = self.n_model = None
        everyone = torch.ones(B, dtype=torch.bool)
        self._new_model(frame, cur, everyone)
        self.prev = cur
        self.residuals = self._residuals(frame)
        result = self._result(frame, None, None)
        result.reselected = everyone
        return result

    def _new_model(self, frame: FrameBatch, cur: PreparedFrame, mask: Tensor) -> None:
        """Take the current frame as the model of the sequences in ``mask`` (B,): PCM features, pose, chain."""
        roi = self.region(cur.depth)
        if self.edge_step is not None:
            roi = roi & smooth_depth_mask(cur.depth, self.edge_step)
        feats = self.select(cur.gray, cur.depth, frame.K, roi=roi, sim=cur.sim)  # eq. (9)
        pixels = feats.pixels
        points_d, has_depth = measure_points(cur, frame, pixels)
        valid = feats.valid & has_depth
        if self.keep_survivors and self.pixels is not None:
            pixels, points_d, valid = self._with_survivors(pixels, points_d, valid, mask)
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
            self.pixels, self.valid, self.points_obj = (
                pad_to(t, n) for t in (self.pixels, self.valid, self.points_obj)
            )
            pixels, valid, points_obj = pad_to(pixels, n), pad_to(valid, n), pad_to(points_obj, n)
        self.T_world_obj = torch.where(m3, T_world_cam @ T_cam_obj, self.T_world_obj)
        self.T_cam_obj = torch.where(m3, T_cam_obj, self.T_cam_obj)
        self.pixels = pixels if self.pixels is None else torch.where(m2[..., None], pixels, self.pixels)
        self.valid = valid if self.valid is None else torch.where(m2, valid, self.valid)
        self.points_obj = points_obj if self.points_obj is None else torch.where(m3, points_obj, self.points_obj)
        n = valid.sum(1)
        self.n_model = n if self.n_model is None else torch.where(mask, n, self.n_model)
        self.backend.reset(self.T_cam_obj, mask)

    def _with_survivors(self, pixels: Tensor, points_d: Tensor, valid: Tensor, mask: Tensor):
        """Keep the tracked features of the sequences in ``mask``, add the new ones (B, M) that are at least
        ``min_separation_px`` from all of them, up to the larger of M and the current model's width (a poor
        selection never cuts survivors). Survivors come first; their model points are moved into the camera by
        the current pose, so that the new model frame sees them where the old one did.
        Returns (pixels (B, W, 2), points in the camera (B, W, 3), valid (B, W))."""
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
        return torch.where(ok[..., None], pixels, 0.0), torch.where(ok[..., None], points, 0.0), ok

    def _residuals(self, frame: FrameBatch) -> Tensor:
        """(B, N) reprojection error of each feature (eq. 16) under the current pose; inf where undefined."""
        T_color_obj = frame.T_color_depth.double() @ self.T_cam_obj
        err = reprojection_errors(frame.K, T_color_obj, self.points_obj, self.pixels, self.valid).float()
        return torch.nan_to_num(err, nan=float("inf"))

    def _result(self, frame: FrameBatch, winner: Tensor | None, d_tim: Tensor | None) -> StepResult:
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
            reselected=torch.zeros(B, dtype=torch.bool),
            d_tim=d_tim if d_tim is not None else torch.zeros(B, N),
        )
