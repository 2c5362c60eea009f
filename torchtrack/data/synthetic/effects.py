"""Real-sensor effects on rendered frames (:class:`~torchtrack.data.synthetic.config.SensorEffects`): depth-colour
misregistration, flying pixels at depth edges, motion blur and lighting change. Each is a pure function of its
inputs, batched over leading dimensions; the writer applies them per frame.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.data.synthetic.config import SensorEffects
from torchtrack.data.synthetic.motion import SequencePoses, sequence_poses


def shift_depth(depth: Tensor, dx: int, dy: int) -> Tensor:
    """depth (..., H, W) -> the same image moved by (dx, dy) whole pixels: ``out[v, u] = depth[v - dy, u - dx]``,
    0 (no measurement) where that falls outside."""
    H, W = depth.shape[-2:]
    out = torch.zeros_like(depth)
    if abs(dx) >= W or abs(dy) >= H:
        return out
    src = depth[..., max(0, -dy) : H - max(0, dy), max(0, -dx) : W - max(0, dx)]
    out[..., max(0, dy) : H - max(0, -dy), max(0, dx) : W - max(0, -dx)] = src
    return out


def light_gain(t: float, e: SensorEffects) -> float:
    """The colour gain at time t seconds: ``1 + A sin(2 pi t / period)``."""
    return 1.0 + e.light_gain_amplitude * math.sin(2 * math.pi * t / e.light_period_s)


def edge_range(clean: Tensor, jump_m: float) -> tuple[Tensor, Tensor, Tensor]:
    """clean depth (B, 1, H, W) (0 = no surface) -> (edge, lo, hi), each (B, 1, H, W): the smallest and largest
    surface depth of the 3 x 3 neighbourhood and ``edge = hi - lo > jump_m`` (empty space mixes with nothing: a
    silhouette against it is no edge here)."""
    hi = F.max_pool2d(clean, 3, stride=1, padding=1)
    inf = torch.full_like(clean, float("inf"))
    lo = -F.max_pool2d(-torch.where(clean > 0, clean, inf), 3, stride=1, padding=1)
    edge = (hi > 0) & (hi - lo > jump_m)
    return edge, torch.where(edge, lo, clean), hi


def flying_pixels(depth: Tensor, clean: Tensor, prob: float, jump_m: float, generator: torch.Generator) -> Tensor:
    """depth (B, 1, H, W) measured, clean (B, 1, H, W) exact -> depth where each pixel at an edge of the clean depth
    (:func:`edge_range`; its holes included) reads ``lo + a (hi - lo)``, a ~ U(0, 1), with probability ``prob`` (one uniform draw per
    pixel for the choice, one for a, in that order)."""
    edge, lo, hi = edge_range(clean, jump_m)
    pick = torch.rand(depth.shape, generator=generator, dtype=depth.dtype) < prob
    a = torch.rand(depth.shape, generator=generator, dtype=depth.dtype)
    return torch.where(edge & pick, lo + a * (hi - lo), depth)


def blur_offsets(e: SensorEffects) -> list[float]:
    """The sub-exposure times (s, relative to the frame's) whose colour renders are averaged: ``blur_samples``
    evenly spaced over ``[-e / 2, e / 2]``; [0.0] without blur."""
    n = e.blur_samples if e.blur_exposure_s > 0 else 1
    if n == 1:
        return [0.0]
    return [e.blur_exposure_s * (k / (n - 1) - 0.5) for k in range(n)]


def effect_poses(cfg) -> tuple[list[SequencePoses], SequencePoses]:
    """The poses the colour is rendered at (one SequencePoses per :func:`blur_offsets` time) and those of the depth
    (at ``depth_time_offset_s``), for every frame of ``cfg`` (a SyntheticConfig)."""
    e = cfg.effects
    colour = [sequence_poses(cfg, dt) for dt in blur_offsets(e)]
    return colour, sequence_poses(cfg, e.depth_time_offset_s)
