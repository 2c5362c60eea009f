"""Re-acquired keyframe landmarks as measurements of the filter (issue 24): one estimator owns the pose.

A landmark found again in the current frame gives the same two measurements as a tracked feature (eqs. 6-7): its 3D
point read from depth and its colour pixel, predicted from its stored world position moved into the current model
frame, ``X_o = T_world_obj^-1 X_w``. The landmarks are re-acquired at a re-selection, after the frame's update (they
are searched for around the updated pose); :func:`joint_update` then redoes that update from the same start with the
landmarks as more features of the frame. So there is one prediction and one update per frame, the landmarks and the
model's features are weighed against each other by their variances, and the gate and the refit judge both alike.

Their variances (:func:`landmark_variances`). The paper's filter takes model points as exact: a model point was
measured from depth once, at its model frame, like a landmark at its keyframe, and its error is not in R. A landmark
is treated alike, with this frame's mean variances of the tracked features (the weighting's, eqs. 11-14, times the
online noise scale inside the update when that is on).

Retired (measured worse; RESULTS, issue 24):
- a second update of the frame with ``dt = 0`` after the first (the landmarks fused into the frame's posterior, whose
  covariance, after hundreds of features, is ~100x tighter than the pose's real error, so that the landmarks barely
  moved it: 7-Scenes 70.0 mm ATE against 60.0 with the outside re-fit);
- ``landmarks.position_variance``: the stored position's own variance (its keyframe's mean 3D variance) added to the
  landmark's, ``var_xyz + var_world`` and ``var_pix + (f / z)^2 var_world``. The landmarks then weigh several times
  less than the model's own points: 7-Scenes 71.0 [65.7-80.4] mm against 63.9 [56.9-67.6] without it, and 65.6
  [58.4-67.8] against 48.4 [46.3-53.9] with the noise scale on.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.backends import BackendSnapshot, EKFBackend, Observation
from torchtrack.filter.weighting import Variances


def landmark_variances(points_cam: Tensor, mean_var: Tensor) -> Variances:
    """(B, C) variances of the re-acquired landmarks ``points_cam`` (B, C, 3) as measurements: the frame's mean
    (pixel px^2, 3D m^2) variances ``mean_var`` (B, 2) of its tracked features (:func:`mean_variances`), as the model's
    own points (module docstring)."""
    v = mean_var.to(points_cam.dtype)
    shape = points_cam.shape[:2]
    return Variances(v[:, :1].expand(shape), v[:, 1:].expand(shape))


def mean_variances(var: Variances, valid: Tensor) -> Tensor:
    """(B, 2) the mean pixel and 3D variance of the valid (B, N) features of ``var`` (B, N): what a frame's
    re-acquired landmarks and keyframe window take as its noise level."""
    w = valid.to(var.var_pix.dtype)
    n = w.sum(1).clamp_min(1.0)
    return torch.stack([(var.var_pix * w).sum(1) / n, (var.var_xyz * w).sum(1) / n], 1)


class LandmarkUpdate(NamedTuple):
    """T_cam_obj: (B, 4, 4) the back end's pose after :func:`joint_update` (the frame's own update where no landmark
    was given); used: (B, C) bool, the landmarks the update kept (the gate's and refit's choice); updated: (B,) bool,
    where landmarks were given."""

    T_cam_obj: Tensor
    used: Tensor
    updated: Tensor


class FrameFusion(NamedTuple):
    """A frame's update, kept until its re-acquired landmarks are known (a re-selection re-acquires them after the
    update): ``before`` the back end's :meth:`~torchtrack.estimators.backends.EKFBackend.snapshot` from before it,
    the frame's ``obs`` (N features) and ``var`` (B, N), and ``active`` (B,)."""

    before: BackendSnapshot
    obs: Observation
    var: Variances
    active: Tensor


def _cat_obs(a: Observation, b: Observation) -> Observation:
    """The features of ``a`` then those of ``b`` (same frame: a's dt, K, T_color_depth)."""

    def cat(x: Tensor, y: Tensor) -> Tensor:
        return torch.cat([x, y.to(x.dtype)], 1)

    return Observation(a.dt, cat(a.points_obj, b.points_obj), cat(a.points_d, b.points_d), cat(a.pixels, b.pixels),
                       torch.cat([a.valid, b.valid], 1), a.K, a.T_color_depth)  # fmt: skip


def joint_update(backend: EKFBackend, fusion: FrameFusion, landmarks: Observation, var: Variances) -> LandmarkUpdate:
    """The frame's update redone from the same start (``fusion.before``) with the landmarks (B, C) as more features
    of the frame: one prediction, one update, the features' and the landmarks' measurements weighed by their
    variances alike, the gate and the refit judging both (:func:`~torchtrack.estimators.backends.ekf_frame`).
    Sequences without a valid landmark keep the frame's update as it was.

    Args:
        backend: the :class:`~torchtrack.estimators.backends.EKFBackend` right after the frame's update.
        fusion: that update's start, observation (N features) and variances.
        landmarks: the landmarks' :class:`Observation` (:meth:`~torchtrack.pipeline.landmarks.Reacquired.observation`,
            same frame); var: their (B, C) :func:`landmark_variances`.
    Returns: the pose (B, 4, 4), the landmarks the update kept (B, C) and where any was given (B,).
    """
    N = fusion.obs.valid.shape[1]
    run = landmarks.valid.any(1) & fusion.active
    if not bool(run.any()):
        return LandmarkUpdate(backend.state.T_cam_obj, torch.zeros_like(landmarks.valid), run)
    obs = _cat_obs(fusion.obs, landmarks)
    both = Variances(*(torch.cat([a, b.to(a.dtype)], 1) for a, b in zip(fusion.var, var, strict=True)))
    backend.restore(fusion.before, run)
    est = backend.step(obs, both, active=run)  # the other sequences keep their state: the frame's update
    used = getattr(est, "used_xyz", obs.valid)[:, N:] & landmarks.valid & run[:, None]
    return LandmarkUpdate(backend.state.T_cam_obj, used, run)
