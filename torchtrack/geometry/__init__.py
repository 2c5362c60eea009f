"""Geometry: SO(3)/SE(3), Euler angles, quaternions, pinhole camera. See each module's conventions."""

from torchtrack.geometry.camera import (
    backproject,
    backproject_depth,
    depth_along_rays,
    intrinsics_matrix,
    pixel_grid,
    project,
    sample_depth,
    sample_depth_bilinear,
    warp_depth,
)
from torchtrack.geometry.rotation import (
    euler_to_matrix,
    hat,
    matrix_to_euler,
    matrix_to_quat_xyzw,
    quat_xyzw_to_matrix,
    rotation_angle,
    so3_exp,
    so3_exp_and_left_jacobian,
    so3_left_jacobian,
    so3_log,
    vee,
)
from torchtrack.geometry.se3 import (
    T_inv,
    make_T,
    point_jacobian,
    pose_from_euler,
    rigid,
    se3_exp,
    se3_log,
    transform_points,
)

__all__ = [
    "T_inv", "backproject", "backproject_depth", "depth_along_rays", "euler_to_matrix", "hat", "intrinsics_matrix",
    "make_T", "matrix_to_euler", "matrix_to_quat_xyzw", "pixel_grid", "point_jacobian", "pose_from_euler", "project",
    "quat_xyzw_to_matrix", "rigid", "rotation_angle", "sample_depth", "sample_depth_bilinear", "se3_exp", "se3_log", "so3_exp",
    "so3_exp_and_left_jacobian", "so3_left_jacobian", "so3_log", "transform_points", "vee", "warp_depth",
]  # fmt: skip
