"""The frame batch that every stage consumes: B sequences in lockstep, one frame each."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor


@dataclass
class FrameBatch:
    """One frame of each of B sequences.

    Attributes:
        rgb: (B, 3, H, W) float32 colour in [0, 1].
        depth: (B, 1, H, W) float32 metres in the depth camera's pixel grid, 0 = no measurement.
        K: (B, 3, 3) float32 colour intrinsics.
        K_depth: (B, 3, 3) float32 depth intrinsics (equal to K for registered depth).
        T_color_depth: (B, 4, 4) float32 depth-to-colour extrinsic (identity when registered).
        timestamp: (B,) float64 seconds.
        T_world_color_gt: (B, 4, 4) float64 ground truth: the colour camera's pose, camera-to-world (identity where absent).
        gt_valid: (B,) bool, ground truth present for this frame.
        active: (B,) bool, False for sequences that already ended (their tensors repeat the last frame).
        index: (B,) int64 frame index within each sequence.
    """

    rgb: Tensor
    depth: Tensor
    K: Tensor
    K_depth: Tensor
    T_color_depth: Tensor
    timestamp: Tensor
    T_world_color_gt: Tensor
    gt_valid: Tensor
    active: Tensor
    index: Tensor

    @property
    def gray(self) -> Tensor:
        """(B, 1, H, W) luminance (ITU-R BT.601 weights, as OpenCV's RGB2GRAY): kornia's."""
        return rgb_to_grayscale(self.rgb)

    def to(self, device: str | torch.device) -> FrameBatch:
        """This batch on ``device`` (the same object where it is there already)."""
        if self.rgb.device == torch.device(device):
            return self
        return FrameBatch(**{f.name: getattr(self, f.name).to(device) for f in fields(self)})
