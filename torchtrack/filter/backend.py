"""The fusion EKF as the tracker's pose back end: the one owner of the filter state between frames.

Each frame runs the pure :func:`~torchtrack.filter.frame.ekf_frame` once; a re-selection starts the filter over at the
new model's pose (:meth:`EKFBackend.reset`). It follows the pose back end protocol of
:class:`torchtrack.estimators.backends.PoseBackend` (``start``, ``reset``, ``set_pose``, ``step``).
"""

from __future__ import annotations

import logging

import torch
from torch import Tensor

from torchtrack.filter.frame import FrameUpdate, Observation, ekf_frame
from torchtrack.filter.fusion import FilterState, FusionEKF
from torchtrack.filter.noise_scale import ScaleState
from torchtrack.filter.weighting import Variances

log = logging.getLogger(__name__)


class EKFBackend:
    """The paper's fusion EKF as a tracker back end: owns the filter state, runs :func:`ekf_frame` once per frame with
    the filter's settings (``ekf``: a :class:`~torchtrack.filter.fusion.FusionEKF`, its parameters; its gate, refit and
    online noise scale among them). The back end owns the noise scales k (B, 2); a re-selection (:meth:`reset`) keeps
    them (the sensor did not change)."""

    def __init__(self, ekf: FusionEKF) -> None:
        self.ekf = ekf
        self.state: FilterState | None = None
        self.scale_state: ScaleState | None = None  # the online noise scale's, (B, 2) each

    def start(self) -> None:
        """A new run: the filter state and the noise scales are forgotten (the scales are the sensor's within a run, a
        re-selection keeps them; a new run starts them at 1 again)."""
        self.state, self.scale_state = None, None

    def reset(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Start the sequences in ``mask`` (B,) over at ``T_cam_obj`` (B, 4, 4), zero velocity, initial covariance.
        The noise scales are kept (they start at 1 after :meth:`start` or with a new batch size)."""
        init = self.ekf.initial_state(T_cam_obj)
        if self.state is None or self.state.mean.shape[0] != T_cam_obj.shape[0]:
            if not bool(mask.all()):
                raise ValueError(
                    "EKFBackend.reset: the first reset (after start, or a new batch size) must cover every sequence"
                )
            self.state = init
            B = T_cam_obj.shape[0]
            self.scale_state = None if self.ekf.noise is None else self.ekf.noise.initial(B, device=T_cam_obj.device)
            return
        self.state = init.select(mask, self.state)
        if self.scale_state is not None and self.scale_state.last_ok is not None:
            self.scale_state = self.scale_state._replace(last_ok=self.scale_state.last_ok & ~mask[:, None, None])

    def set_pose(self, T_cam_obj: Tensor, mask: Tensor) -> None:
        """Move the pose to ``T_cam_obj`` (B, 4, 4) where ``mask`` (B,) is True, keeping velocity and covariance (a
        pose corrected outside the filter is taken as its new mean, not fused as a measurement)."""
        if self.state is None:
            raise ValueError("EKFBackend: call reset(T_cam_obj, mask) before set_pose")
        self.state = self.ekf.with_pose(self.state, T_cam_obj, mask)

    def step(self, obs: Observation, var: Variances, active: Tensor | None = None) -> FrameUpdate:
        """One frame: the named result of :func:`ekf_frame`; the posterior becomes the state of the sequences where
        ``active`` (B,) is True (default: all); ended sequences keep theirs (no prediction runs on without them), and
        their noise scales (the result's ``noise`` is the back end's after the frame)."""
        if self.state is None:
            raise ValueError("EKFBackend: call reset(T_cam_obj, mask) before the first frame")
        ekf = self.ekf
        out = ekf_frame(ekf, self.state, obs, var, gate=ekf.gate, refit=ekf.refit, noise_scale=ekf.noise,
                        scale_state=self.scale_state)  # fmt: skip
        self.state = out.posterior if active is None else out.posterior.select(active, self.state)
        if out.noise is not None:
            out = out._replace(noise=_kept(out.noise, self.scale_state, active))
            self.scale_state = out.noise
        near = out.mean[:, 1].abs() > 1.4  # only the sequences this step updated
        if self.ekf.euler and bool((near if active is None else near & active).any()):
            log.warning("EKFBackend: |theta| > 80 deg, near the Euler singularity; re-select the model frame")
        return out


def _kept(new: ScaleState, old: ScaleState | None, active: Tensor | None) -> ScaleState:
    """A running scale after a frame: ``new`` where ``active`` (B,) is True (default: all), ``old`` elsewhere."""
    if active is None or old is None:
        return new
    out = []
    for n, o in zip(new, old, strict=True):
        if n is None or o is None or n.shape != o.shape:
            out.append(n)
        else:
            out.append(torch.where(active.view(-1, *[1] * (n.dim() - 1)), n, o))
    return ScaleState(*out)
