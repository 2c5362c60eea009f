"""Data: TUM-layout RGB-D reader, camera presets, lockstep batching of B sequences (FrameBatch)."""

from torchtrack.data.batching import RGBDSequence, SequenceBatch, iterate_batched
from torchtrack.data.cameras import CAMERAS, TUM_DEPTH_SCALE, CameraPreset, get_camera
from torchtrack.data.errors import DataError
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import (
    RGBDFrame,
    Trajectory,
    TumSequence,
    associate,
    load_depth,
    load_rgb,
    nearest_within,
    read_list_file,
    read_tum_trajectory,
    write_tum_trajectory,
)

__all__ = [
    "CAMERAS", "TUM_DEPTH_SCALE", "CameraPreset", "DataError", "FrameBatch", "RGBDFrame", "RGBDSequence",
    "SequenceBatch", "Trajectory", "TumSequence", "associate", "get_camera", "iterate_batched", "load_depth",
    "load_rgb", "nearest_within", "read_list_file", "read_tum_trajectory", "write_tum_trajectory",
]  # fmt: skip
