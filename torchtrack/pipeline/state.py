"""What the tracker carries from frame to frame (:class:`TrackerState`) and what it returns per frame
(:class:`StepResult`), both batched over B sequences; helpers for the per-feature (B, N, ...) layout."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.backends import BackendResult
from torchtrack.estimators.base import masked_mean
from torchtrack.filter.cues import stack_cues, window_cues
from torchtrack.filter.frame import Observation
from torchtrack.filter.models import measure_points
from torchtrack.filter.weighting import Variances
from torchtrack.frontend import PreparedFrame
from torchtrack.geometry import (
    T_inv,
    backproject,
    depth_along_rays,
    sample_depth,
    sample_depth_bilinear,
    transform_points,
)
from torchtrack.image.flow import TrackResult


class Measure(NamedTuple):
    """The one measurement of a feature's 3D point in a frame, eq. (6): ``measure(pixels)`` reads the depth registered
    to colour at colour pixels (B, N, 2) and back-projects it into the depth camera; returns (X_d (B, N, 3), has_depth
    (B, N)). The tracker makes one per frame; every stage that needs a point of this frame calls it.

    depth: (B, 1, H, W) registered depth, m; K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4). With a separate
    depth camera (``raw``: its (B, 1, H_d, W_d) image, ``K_depth`` its intrinsics) each pixel's ray is intersected with
    the surface the depth camera sees (:func:`~torchtrack.geometry.depth_along_rays`, from the registered depth), not
    read from the forward warp: the warp puts the wrong surface's depth beside edges and is half a pixel off on slopes.
    """

    depth: Tensor
    K: Tensor
    T_color_depth: Tensor
    raw: Tensor | None = None
    K_depth: Tensor | None = None

    def __call__(self, pixels: Tensor) -> tuple[Tensor, Tensor]:
        if self.raw is None:
            return measure_points(self.depth, self.K, self.T_color_depth, pixels)
        z0 = sample_depth_bilinear(self.depth, pixels)
        z = depth_along_rays(self.raw, self.K_depth, self.K, self.T_color_depth, pixels, z0)
        points = transform_points(T_inv(self.T_color_depth), backproject(self.K, pixels, z))
        return points, z > 0

    def row(self, b: int) -> Measure:
        """The measurement of sequence b alone (B = 1)."""
        return Measure(*(None if x is None else x[b : b + 1] for x in self))


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
            ``pixels``/``valid`` BEFORE the outlier drop (``outliers.max_residual_px``); a re-selection comes after.
        variances: the weighting's output that went with ``observation`` (None on the first frame).
        cues: (B, N, C) float32 cues (:data:`torchtrack.filter.cues.CUE_NAMES`) of the observation's features,
            zeros where not valid; only where the weighting or an observer of the step asks for them (else None).
        model_T_cam_obj: (B, 4, 4) float64, where ``reselected``: the pose the back end was reset to when the new
            model was taken at the end of this frame (other rows: the current pose); None when no re-selection.
        estimate: the back end's result for this frame (None on the first frame): the loss check reads it.
        loss: the loss check's :class:`torchtrack.pipeline.relocalise.LossCheck` (None without a relocaliser).
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
    The tracker is its only owner and the stages return values and never write it.

    Attributes:
        prev: the previous frame as the front end prepared it; timestamp (B,) its time stamps.
        pixels: (B, N, 2) the model's features, tracked to the previous frame (colour pixels); valid (B, N).
        points_obj: (B, N, 3) their model points X_o (object frame).
        points_mean: (B, N, 3) float64 each model point's estimate and points_info (B, N, 3, 3) float64 its information
            (:class:`~torchtrack.pipeline.reselect.PointEstimate`; zeros: the birth sample, not yet weighed), both in
            the object frame; None with ``reselect.point_mean=off`` (the paper: a model point is its one sample).
        age: (B, N) frames since selection; cornerness (B, N, 2) intensity and SIM cornerness of eq. (9) at selection.
        residuals: (B, N) reprojection error (eq. 16) of each feature under ``T_cam_obj``; inf where undefined.
        n_model: (B,) features of the current model when it was taken (the re-selection criterion).
        T_cam_obj: (B, 4, 4) float64 current object pose in the depth camera.
        T_world_obj: (B, 4, 4) float64 the model frame in the tracker's world (first camera = identity).
        velocity: (B, 6) float64 twist per second (v, omega) of the last frame-to-frame motion of the object in the
            camera, ``se3_log(T_cam_obj(t) inv(T_cam_obj(t-1))) / dt``: independent of the model frame, so it
            survives a re-selection (the EKF's velocity restarts at zero there). Zero before the second frame.
        reacquired_total: (B,) long, landmarks re-acquired so far.
    """

    prev: PreparedFrame | None = None
    timestamp: Tensor | None = None
    pixels: Tensor | None = None
    valid: Tensor | None = None
    points_obj: Tensor | None = None
    points_mean: Tensor | None = None
    points_info: Tensor | None = None
    age: Tensor | None = None
    cornerness: Tensor | None = None
    residuals: Tensor | None = None
    n_model: Tensor | None = None
    T_cam_obj: Tensor | None = None
    T_world_obj: Tensor | None = None
    velocity: Tensor | None = None
    reacquired_total: Tensor | None = None

    @property
    def started(self) -> bool:
        return self.prev is not None

    @property
    def T_world_depth(self) -> Tensor:
        """(B, 4, 4) the current depth camera in the tracker's world (static object/scene)."""
        return self.T_world_obj @ T_inv(self.T_cam_obj)


FEATURE_FIELDS = ("pixels", "valid", "points_obj", "points_mean", "points_info", "age", "cornerness")  # (B, N, ...)


def pad_to(x: Tensor, n: int) -> Tensor:
    """Pad (or keep) the feature dimension (dim 1) of x to n with zeros (False for masks)."""
    if x.shape[1] >= n:
        return x
    pad = torch.zeros(x.shape[0], n - x.shape[1], *x.shape[2:], dtype=x.dtype, device=x.device)
    return torch.cat([x, pad], dim=1)


def where_rows(mask: Tensor, new: Tensor, old: Tensor) -> Tensor:
    """Rows of ``new`` where ``mask`` (B,), else of ``old``; any trailing shape."""
    return torch.where(mask.view(-1, *([1] * (new.dim() - 1))), new, old)


def valid_first(valid: Tensor, width: int) -> Tensor:
    """(B, width) indices that put the True entries of ``valid`` (B, N) first, in order (a stable sort)."""
    return torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices[:, :width]


def frame_cues(s: TrackerState, cur: PreparedFrame, track: TrackResult, points_d: Tensor, valid: Tensor) -> Tensor:
    """(B, N, C) cues of the features ``track`` followed from the state ``s`` into ``cur`` (:data:`torchtrack.filter.cues.CUE_NAMES`), zeros where not valid."""
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
