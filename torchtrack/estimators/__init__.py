"""Pose from 3D-3D points, batched with masks: Horn (quaternion), ICP, rigid CPD (the paper's baselines, §IV).

Every method is a pure function (``horn``, ``icp``, ``cpd_rigid``) plus an estimator class with the common
interface the tracker uses, ``estimator(points_obj, points_d, valid, T_prev, weights=None) -> T_cam_obj``.
"""

from torchtrack.estimators.base import PoseEstimate
from torchtrack.estimators.cpd import CPDEstimator, CPDResult, cpd_rigid
from torchtrack.estimators.horn import HornEstimator, horn
from torchtrack.estimators.icp import ICPEstimator, ICPResult, icp

__all__ = [
    "CPDEstimator", "CPDResult", "HornEstimator", "ICPEstimator", "ICPResult", "PoseEstimate", "cpd_rigid",
    "horn", "icp",
]  # fmt: skip
