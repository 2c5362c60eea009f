"""Pose back ends behind one protocol, so that trackers differ only in how the pose is estimated.

The fusion EKF (paper §III-A; :class:`torchtrack.filter.backend.EKFBackend`) and the registration baselines (Horn,
ICP, CPD; paper §IV; :class:`RegistrationBackend`) all take the same per-frame
:class:`~torchtrack.filter.frame.Observation` of tracked features and return ``T_cam_obj`` (B, 4, 4).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from torchtrack.filter.frame import Observation
from torchtrack.filter.weighting import Variances


class BackendResult(Protocol):
    @property
    def T_cam_obj(self) -> Tensor:
        """(B, 4, 4) the frame's object pose in the depth camera."""


class PoseBackend(Protocol):
    """A pose estimator that owns its state (the filter's, or the previous pose) between frames. The tracker calls
    :meth:`start` once per run, :meth:`reset` at every new model (the first frame, a re-selection, a relocalisation)
    and :meth:`step` once per frame; nothing else moves its pose."""

    def start(self) -> None:
        """A new run (the tracker's first frame): forget everything; the next :meth:`reset` covers every sequence."""

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Start over at pose ``T_cam_obj`` (B, 4, 4) for the sequences where ``mask`` (B,) is True."""

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Move the current pose to ``T_cam_obj`` (B, 4, 4) where ``mask`` (B,), keeping the rest of the state."""

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> BackendResult:
        """One frame: observation and per-feature variances in, a named result with ``T_cam_obj`` (B, 4, 4) out.
        Sequences where ``active`` (B,) is False (ended) keep their state."""


class Registration(NamedTuple):
    """One frame of a :class:`RegistrationBackend`, batched over B.

    Attributes:
        T_cam_obj: (B, 4, 4) the registered object pose in the depth camera.
        used: (B, N) bool, the 3D-3D correspondences it was given (the observation's valid features).
        weights: (B, N) the per-correspondence weights (``1 / var_xyz``), or None when unweighted.
    """

    T_cam_obj: Tensor
    used: Tensor
    weights: Tensor | None


class RegistrationBackend:
    """A 3D-3D registration baseline (Horn, ICP or CPD) started from the previous pose (paper §IV).

    ``estimator(points_obj, points_d, valid, T_prev, weights)`` returns ``T_cam_obj`` (B, 4, 4).
    With ``weighted`` the 3D variances of eq. (14) become weights ``1 / var_xyz``. Owns the previous pose.
    """

    def __init__(self, estimator, weighted: bool = False) -> None:
        self.estimator = estimator
        self.weighted = weighted
        self.T_prev: Tensor | None = None

    def start(self) -> None:
        """A new run: no previous pose."""
        self.T_prev = None

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        if self.T_prev is None:
            self.T_prev = T_cam_obj.clone()
        self.T_prev = torch.where(mask[:, None, None], T_cam_obj, self.T_prev)

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """The previous pose of the sequences in ``mask`` (B,) becomes ``T_cam_obj`` (B, 4, 4) (no other state)."""
        if self.T_prev is None:
            raise ValueError("RegistrationBackend: call reset(T_cam_obj, mask) before set_pose")
        self.T_prev = torch.where(mask[:, None, None], T_cam_obj.to(self.T_prev.dtype), self.T_prev)

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> Registration:
        """One frame; the result becomes the previous pose of the sequences where ``active`` (B,) is True."""
        if self.T_prev is None:
            raise ValueError("RegistrationBackend: call reset(T_cam_obj, mask) before the first frame")
        weights = 1.0 / var.var_xyz.clamp_min(1e-12) if self.weighted else None
        T_prev = self.T_prev.to(obs.points_obj.dtype)
        T = self.estimator(obs.points_obj, obs.points_d, obs.valid_xyz, T_prev, weights)
        self.T_prev = T if active is None else torch.where(active[:, None, None], T, T_prev)
        return Registration(T, obs.valid_xyz, weights)


__all__ = ["BackendResult", "Observation", "PoseBackend", "Registration", "RegistrationBackend"]
