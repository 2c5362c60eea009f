"""The RGB-D rig: a colour camera and a depth camera one rigid extrinsic ``T_color_depth`` apart.

The tracker estimates the DEPTH camera's pose (its 3D measurements live there, eq. (6)); its world is its first depth
camera. Ground truth and written trajectories are the COLOUR camera's (TUM convention). These helpers are the one
place that converts between the two; every writer (run outputs, panorama, observation cache) goes through them. The
extrinsic is rigid, so the lever arm between the cameras rotates with the rig: a trajectory of the wrong camera is
off by a pose-dependent offset that an aligned ATE partly hides.

For registered depth (``T_color_depth`` = I, every TUM sequence) the two cameras coincide.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry.se3 import T_inv


def T_world_color_from_depth(T_world_depth: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) colour-camera poses from depth-camera poses (..., 4, 4) of the same rig, in float64."""
    return T_world_depth.double() @ T_inv(T_color_depth.double())


def T_world_depth_from_color(T_world_color: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) depth-camera poses from colour-camera poses (..., 4, 4) of the same rig, in float64."""
    return T_world_color.double() @ T_color_depth.double()


def tracker_world(T_world_color_gt: Tensor, gt_valid: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) float64 ``T_world_tracker``: the tracker's world (its first depth camera) in ground truth's world,
    from the first frame's ground-truth colour pose ``T_world_color_gt`` (..., 4, 4) where ``gt_valid`` (...,); where
    there is none, the first colour camera is the world. Then ``T_world_depth = T_world_tracker @ T_tracker_depth``
    and the written pose is :func:`T_world_color_from_depth` of it, comparable with ground truth unaligned."""
    eye = torch.eye(4, dtype=torch.float64, device=T_world_color_gt.device).expand_as(T_world_color_gt)
    T_world_color0 = torch.where(gt_valid[..., None, None], T_world_color_gt.double(), eye)
    return T_world_depth_from_color(T_world_color0, T_color_depth)


def color_poses(T_world_tracker: Tensor, T_tracker_depth: Tensor, T_color_depth: Tensor) -> Tensor:
    """(..., 4, 4) float64 ``T_world_color``: the tracker's depth-camera poses ``T_tracker_depth`` (..., 4, 4) as the
    colour camera's poses in ground truth's world (``T_world_tracker`` from :func:`tracker_world`)."""
    return T_world_color_from_depth(T_world_tracker.double() @ T_tracker_depth.double(), T_color_depth)
