"""Batched EKF with autograd Jacobians, the paper's motion/measurement models, measurement weighting."""

from torchtrack.filter.ekf import Prediction, Update, linearize, predict, symmetrize, update
from torchtrack.filter.fusion import FilterState, FusionEKF, fuse
from torchtrack.filter.models import (
    Linearization,
    MotionModel,
    constant_velocity,
    euler_velocity,
    measure_analytic,
    measure_single,
    pose_to_state,
    state_to_pose,
)
from torchtrack.filter.noise_scale import NoiseScale, ScaleState
from torchtrack.filter.weighting import FixedWeighting, PaperWeighting, Variances, WeightingInputs, paper_variances

__all__ = [
    "FilterState", "FixedWeighting", "FusionEKF", "Linearization", "MotionModel", "NoiseScale", "PaperWeighting",
    "Prediction", "ScaleState", "Update", "Variances", "WeightingInputs", "constant_velocity", "euler_velocity", "fuse",
    "linearize", "measure_analytic", "measure_single", "paper_variances", "pose_to_state", "predict",
    "state_to_pose", "symmetrize", "update",
]  # fmt: skip
