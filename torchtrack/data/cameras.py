"""Named pinhole camera presets (colour intrinsics and depth scale).

The TUM RGB-D values are the published colour-camera calibrations of the three Kinects
(https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats, "Intrinsic Camera Calibration of the Kinect").
TUM depth is registered to colour by the OpenNI driver, so one K serves both; TUM depth PNGs store metres * 5000.
The fr1/fr2 lenses also have radial distortion (not modelled here, as in most RGB-D trackers).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torchtrack.data.errors import DataError
from torchtrack.geometry import intrinsics_matrix

TUM_DEPTH_SCALE = 5000.0


@dataclass(frozen=True)
class CameraPreset:
    """Pinhole intrinsics in pixels and the depth PNG scale (stored value per metre)."""

    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = TUM_DEPTH_SCALE

    @property
    def K(self) -> Tensor:
        """(3, 3) float32 intrinsics matrix."""
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy, dtype=torch.float32)


CAMERAS: dict[str, CameraPreset] = {
    "fr1": CameraPreset(517.3, 516.5, 318.6, 255.3),
    "fr2": CameraPreset(520.9, 521.0, 325.1, 249.7),
    "fr3": CameraPreset(535.4, 539.2, 320.1, 247.6),
    # ROS/OpenNI default Kinect calibration (TUM's "ROS default" row).
    "kinect_default": CameraPreset(525.0, 525.0, 319.5, 239.5),
}
_ALIASES = {"freiburg1": "fr1", "freiburg2": "fr2", "freiburg3": "fr3", "tum_fr1": "fr1", "tum_fr2": "fr2"}
_ALIASES |= {"tum_fr3": "fr3", "ros_default": "kinect_default"}


def get_camera(name: str) -> CameraPreset:
    """Preset by name (case-insensitive; 'freiburg1' etc. are aliases). DataError for unknown names."""
    key = name.strip().lower()
    key = _ALIASES.get(key, key)
    if key not in CAMERAS:
        raise DataError(f"unknown camera preset {name!r}; known: {', '.join(sorted(CAMERAS))}")
    return CAMERAS[key]
