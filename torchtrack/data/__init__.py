"""Data: TUM-layout RGB-D reader, camera presets, lockstep batching of B sequences (FrameBatch), depth alignment."""

from torchtrack.data.alignment import ShiftEstimate, colour_intrinsics, depth_intrinsics, estimate_depth_shift
from torchtrack.data.batching import DroppedFrame, FrameCursor, RGBDSequence, SequenceBatch, iterate_batched
from torchtrack.data.cameras import CAMERAS, TUM_DEPTH_SCALE, CameraPreset, get_camera
from torchtrack.data.errors import DataError
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import RGBDFrame, TumSequence
from torchtrack.data.tum_io import (
    Trajectory,
    associate,
    load_depth,
    load_rgb,
    nearest_within,
    read_list_file,
    read_tum_trajectory,
    write_tum_trajectory,
)

__all__ = [
    "CAMERAS", "TUM_DEPTH_SCALE", "CameraPreset", "DataError", "DroppedFrame", "FrameBatch", "FrameCursor", "RGBDFrame", "RGBDSequence",
    "SequenceBatch", "ShiftEstimate", "Trajectory", "TumSequence", "associate", "colour_intrinsics",
    "depth_intrinsics", "estimate_depth_shift", "get_camera", "iterate_batched", "load_depth", "load_rgb",
    "nearest_within", "read_list_file", "read_tum_trajectory", "write_tum_trajectory",
]  # fmt: skip
