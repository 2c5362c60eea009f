"""Smooth random rigid motion with exact poses: camera motion (scene mode) or object motion (object mode).

Translation and rotation vector are each a sum of low-frequency sinusoids (periods 60-180 frames,
random amplitudes and phases, zero at frame 0), scaled so that the RMS step per frame equals the
configured ``trans_step_m`` and ``rot_step_deg`` (Kinect-handheld-like defaults: 1 cm, 1 deg). The
scale is computed from the sinusoids, not from the frames drawn, so a shorter sequence is a prefix
of a longer one with the same seed.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.data.synthetic.config import SyntheticConfig
from torchtrack.data.synthetic.scene import pose
from torchtrack.geometry import make_T, so3_exp

_MOTION_SEED_OFFSET = 7_919
HARMONICS = 3
PERIODS = (60.0, 180.0)


class SequencePoses(NamedTuple):
    """Ground truth of a sequence, float64.

    T_world_cam: (F, 4, 4) camera-to-world. T_world_obj: (F, 4, 4) pose of the moving object (object
    mode) or None (scene mode). In object mode T_cam_obj = inv(T_world_cam) @ T_world_obj.
    """

    T_world_cam: Tensor
    T_world_obj: Tensor | None

    @property
    def T_cam_obj(self) -> Tensor | None:
        if self.T_world_obj is None:
            return None
        from torchtrack.geometry import T_inv

        return T_inv(self.T_world_cam) @ self.T_world_obj


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> Tensor:
    """(4, 4) float64 T_world_cam of a camera at eye looking at target (z forward, y down, x right)."""
    e, c, u = (torch.tensor(v, dtype=torch.float64, device="cpu") for v in (eye, target, up))
    z = (c - e) / (c - e).norm()
    x = torch.linalg.cross(z, u)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    return make_T(torch.stack([x, y, z], dim=-1), e)


def smooth_curve(frames: int, rms_step: float, gen: torch.Generator, offset: float = 0.0) -> Tensor:
    """(frames, 3) float64 smooth curve starting at 0 whose RMS change per frame is rms_step, sampled at the frame
    times ``i + offset`` (fractional frames: the same curve between its frames)."""
    amp = torch.randn(3, HARMONICS, generator=gen, dtype=torch.float64)
    period = PERIODS[0] + (PERIODS[1] - PERIODS[0]) * torch.rand(3, HARMONICS, generator=gen, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(3, HARMONICS, generator=gen, dtype=torch.float64)
    w = 2 * math.pi / period
    t = (torch.arange(frames, dtype=torch.float64, device=amp.device) + offset)[:, None, None]
    x = (amp * (torch.sin(w * t + phase) - torch.sin(phase))).sum(-1)  # F,3
    rms_speed = ((amp * w) ** 2).sum().div(2).sqrt()  # time-average of |dx/dt| squared, incommensurate harmonics
    return x * (rms_step / rms_speed)


def _moving(T0: Tensor, frames: int, cfg: SyntheticConfig, gen: torch.Generator, offset: float = 0.0) -> Tensor:
    """(F, 4, 4): T0 translated in its parent frame and rotated about its own origin, at frames ``i + offset``."""
    dx = smooth_curve(frames, cfg.trans_step_m, gen, offset)
    dw = smooth_curve(frames, math.radians(cfg.rot_step_deg), gen, offset)
    return make_T(T0[:3, :3] @ so3_exp(dw), T0[:3, 3] + dx)


# Default viewpoints (world z up): the room corner from 2.3 m, and the object from 0.9 m, looking down.
SCENE_EYE, SCENE_TARGET = (0.7, -2.1, 1.35), (0.0, 0.1, 0.3)
OBJECT_EYE, OBJECT_CENTRE = (0.0, -0.85, 1.3), (0.0, 0.0, 1.0)
SMALL_OBJECT_DISTANCE = 0.55  # m, the small object's default camera distance (same viewing direction)


def object_eye(cfg: SyntheticConfig) -> tuple[float, float, float]:
    """The static camera's centre in object mode: on the line from OBJECT_CENTRE to OBJECT_EYE, at
    ``cfg.object_distance_m`` (default: OBJECT_EYE for the compound object, 0.55 m for the small one)."""
    d = cfg.object_distance_m
    if d is None and cfg.object == "compound":
        return OBJECT_EYE
    d = SMALL_OBJECT_DISTANCE if d is None else d
    ray = [e - c for e, c in zip(OBJECT_EYE, OBJECT_CENTRE, strict=True)]
    n = math.sqrt(sum(v * v for v in ray))
    return tuple(c + d * v / n for c, v in zip(OBJECT_CENTRE, ray, strict=True))


def sequence_poses(cfg: SyntheticConfig, offset_s: float = 0.0) -> SequencePoses:
    """Exact per-frame poses of the sequence described by cfg (deterministic from cfg.seed), at the frame times
    ``i / fps + offset_s`` (the same smooth motion between frames: motion blur, unsynchronised depth)."""
    gen = torch.Generator().manual_seed(int(cfg.seed) + _MOTION_SEED_OFFSET)
    offset = offset_s * cfg.fps
    if cfg.mode == "scene":
        return SequencePoses(_moving(look_at(SCENE_EYE, SCENE_TARGET), cfg.frames, cfg, gen, offset), None)
    T_world_cam = look_at(object_eye(cfg), OBJECT_CENTRE).expand(cfg.frames, 4, 4).clone()
    T_world_obj = _moving(pose(OBJECT_CENTRE, (0.0, 0.0, 30.0)), cfg.frames, cfg, gen, offset)
    return SequencePoses(T_world_cam, T_world_obj)
