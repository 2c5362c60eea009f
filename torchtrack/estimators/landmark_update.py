"""Re-acquired keyframe landmarks as measurements of the filter (issue 24): one estimator owns the pose.

A landmark found again in the current frame gives the same two measurements as a tracked feature (eqs. 6-7): its 3D
point read from depth and its colour pixel, predicted from its stored world position moved into the current model
frame, ``X_o = T_world_obj^-1 X_w``. The stored position is itself uncertain (it was measured from depth at its
keyframe, with the keyframe's 3D variance ``var_world``, isotropic), so each measurement's variance is the filter's
variance for a feature now plus that of the prediction it is compared with:

    var_xyz = v_xyz + var_world,        var_pix = v_pix + (f / z)^2 var_world,

(the position's error moves the projection by f / z per metre across the ray), with ``v_xyz``, ``v_pix`` this
frame's mean variances of the tracked features (the weighting's, eqs. 11-14: their mean is the nominal one). The
landmarks enter the back end as a second update of the same frame, ``dt = 0``: the constant-velocity prediction over
zero time is the identity with zero process noise, so the update fuses them with the frame's posterior (the gate and
the refit drop the landmarks that disagree with it, as they drop features).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.backends import Observation
from torchtrack.filter.weighting import Variances
from torchtrack.geometry import T_inv, transform_points


def landmark_variances(points_cam: Tensor, var_world: Tensor, mean_var: Tensor, K: Tensor) -> Variances:
    """(B, C) variances of re-acquired landmarks as measurements (module docstring).

    Args:
        points_cam: (B, C, 3) their points measured from depth now (depth camera; z sets the pixel term).
        var_world: (B, C) m^2 per coordinate, the variance of their stored world positions.
        mean_var: (B, 2) the frame's mean (pixel px^2, 3D m^2) variance of its tracked features
            (:func:`mean_variances`).
        K: (B, 3, 3) colour intrinsics (its focal length).
    """
    f = K[:, 0, 0, None].to(points_cam.dtype)
    z = points_cam[..., 2].clamp_min(1e-3)
    vw = var_world.to(points_cam.dtype)
    v = mean_var.to(vw.dtype)
    return Variances(v[:, :1] + (f / z) ** 2 * vw, v[:, 1:] + vw)


def mean_variances(var: Variances, valid: Tensor) -> Tensor:
    """(B, 2) the mean pixel and 3D variance of the valid (B, N) features of ``var`` (B, N): what a frame's
    re-acquired landmarks and keyframe window take as its noise level."""
    w = valid.to(var.var_pix.dtype)
    n = w.sum(1).clamp_min(1.0)
    return torch.stack([(var.var_pix * w).sum(1) / n, (var.var_xyz * w).sum(1) / n], 1)


class LandmarkUpdate(NamedTuple):
    """T_cam_obj: (B, 4, 4) the back end's pose after the landmarks' update (unchanged where none was used);
    used: (B, C) bool, the landmarks the update kept (the gate's and refit's choice; all given ones for a back end
    that reports none); updated: (B,) bool."""

    T_cam_obj: Tensor
    used: Tensor
    updated: Tensor


def landmark_update(backend, T_cam_obj: Tensor, T_world_obj: Tensor, points_world: Tensor, points_cam: Tensor,
                    pixels: Tensor, valid: Tensor, var: Variances, K: Tensor, T_color_depth: Tensor) -> LandmarkUpdate:  # fmt: skip
    """Fuse the landmarks (B, C) into ``backend``'s state of the current frame: an update with ``dt = 0``.

    Args:
        backend: the pose back end (:class:`~torchtrack.estimators.backends.EKFBackend`), already updated with this
            frame's features; T_cam_obj: (B, 4, 4) its pose now; T_world_obj: (B, 4, 4) the current model frame.
        points_world: (B, C, 3) the landmarks' stored positions; points_cam: (B, C, 3) measured now (depth camera);
            pixels: (B, C, 2) tracked now; valid: (B, C); var: their :func:`landmark_variances`.
        K: (B, 3, 3); T_color_depth: (B, 4, 4).
    """
    B = valid.shape[0]
    run = valid.any(1)
    if not bool(run.any()):
        return LandmarkUpdate(T_cam_obj, valid, run)
    dtype = points_cam.dtype
    points_obj = transform_points(T_inv(T_world_obj.double()), points_world.double()).to(dtype)
    ok = valid[..., None]
    obs = Observation(torch.zeros(B, dtype=dtype, device=valid.device), torch.where(ok, points_obj, 0.0),
                      torch.where(ok, points_cam, 0.0), torch.where(ok, pixels.to(dtype), 0.0), valid, K,
                      T_color_depth)  # fmt: skip
    est = backend.step(obs, var, active=run)
    used = getattr(est, "used_xyz", valid) & valid
    T_new = torch.where(run[:, None, None], est.T_cam_obj.to(T_cam_obj.dtype), T_cam_obj)
    return LandmarkUpdate(T_new, used, run)
