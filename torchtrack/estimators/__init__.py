"""Pose from 3D-3D points, batched with masks: Horn (quaternion), ICP, rigid CPD (the paper's baselines, §IV).

Every method is a pure function in its module (``horn.horn``, ``icp.icp``, ``cpd.cpd_rigid``) plus an estimator
class with the common interface the tracker uses, ``estimator(points_obj, points_d, valid, T_prev, weights=None)
-> T_cam_obj``. The package exports the classes and result types only: re-exporting the functions ``horn`` and
``icp`` here would shadow the submodules of the same name (``torchtrack.estimators.horn.HornEstimator`` would
then fail to resolve, e.g. as a Hydra ``_target_``).

The tracker's pose back ends (the fusion EKF and the registration baselines behind one interface) are in
:mod:`torchtrack.estimators.backends`, not imported here (they need :mod:`torchtrack.filter`).
"""

from torchtrack.estimators.base import RigidFit
from torchtrack.estimators.cpd import CPDEstimator, CPDResult
from torchtrack.estimators.horn import HornEstimator
from torchtrack.estimators.icp import ICPEstimator, ICPResult

__all__ = ["CPDEstimator", "CPDResult", "HornEstimator", "ICPEstimator", "ICPResult", "RigidFit"]
