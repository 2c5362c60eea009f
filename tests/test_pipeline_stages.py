"""The tracker's stage interfaces: a back end's ``set_pose``, the relocaliser's decision applied by the
tracker, and re-acquired landmarks stated as back-end measurements. Oracles: the pose that was set or decided, and
exact world positions."""

from __future__ import annotations

import math

import pytest
import torch
from test_tracker import make_tracker, synth  # noqa: F401  (fixture)
from tolerances import F64_UNIT

from torchtrack.data import iterate_batched
from torchtrack.estimators.backends import RegistrationBackend
from torchtrack.estimators.horn import HornEstimator
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.frame import Observation
from torchtrack.filter.fusion import FusionEKF
from torchtrack.filter.weighting import Variances
from torchtrack.geometry import make_T, so3_exp
from torchtrack.pipeline.relocalise import LossCheck, Relocalisation, Relocaliser


def _pose(yaw_deg: float, t) -> torch.Tensor:
    R = so3_exp(torch.tensor([0.0, 0.0, math.radians(yaw_deg)], dtype=torch.float64))
    return make_T(R, torch.tensor(t, dtype=torch.float64))


def _empty_observation(B: int) -> tuple[Observation, Variances]:
    z = torch.zeros(B, 3, 3, dtype=torch.float64)
    K = torch.tensor([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]], dtype=torch.float64).expand(B, 3, 3)
    obs = Observation(torch.full((B,), 1 / 30, dtype=torch.float64), z + 0.1, z + 0.1, torch.zeros(B, 3, 2,
                      dtype=torch.float64), torch.zeros(B, 3, dtype=torch.bool), K, torch.eye(4, dtype=torch.float64)
                      .expand(B, 4, 4))  # fmt: skip
    ones = torch.ones(B, 3, dtype=torch.float64)
    return obs, Variances(ones, ones * 1e-4)


@pytest.mark.parametrize("state", ["se3", "euler"])
def test_ekf_set_pose_moves_the_mean_pose_of_the_masked_sequences_only(state):
    """After set_pose a step with no features (zero velocity: the prediction stays) returns the pose that was set,
    also across the Euler angles' wrap at 180 degrees (the paper's state); the other sequence and the covariance are
    untouched."""
    backend = EKFBackend(FusionEKF(state=state))
    T0 = torch.stack([_pose(179.0, [0.1, 0.0, 1.0]), _pose(10.0, [0.0, 0.2, 2.0])])
    backend.reset(T0, torch.ones(2, dtype=torch.bool))
    cov = backend.state.cov.clone()
    T1 = torch.stack([_pose(-179.0, [0.12, -0.01, 1.03]), _pose(-50.0, [5.0, 5.0, 5.0])])
    backend.set_pose(T1, torch.tensor([True, False]))
    assert torch.equal(backend.state.cov, cov)
    out = backend.step(*_empty_observation(2)).T_cam_obj
    torch.testing.assert_close(out[0], T1[0], atol=F64_UNIT, rtol=0)
    torch.testing.assert_close(out[1], T0[1], atol=F64_UNIT, rtol=0)


def test_registration_set_pose_is_the_next_start():
    backend = RegistrationBackend(HornEstimator())
    T0 = torch.stack([_pose(0.0, [0, 0, 1]), _pose(5.0, [0, 0, 2])])
    backend.reset(T0, torch.ones(2, dtype=torch.bool))
    T1 = torch.stack([_pose(30.0, [1, 0, 1]), _pose(-5.0, [0, 1, 2])])
    backend.set_pose(T1, torch.tensor([False, True]))
    assert torch.equal(backend.T_prev[0], T0[0]) and torch.equal(backend.T_prev[1], T1[1])


class Decides(Relocaliser):
    """A relocaliser whose check finds sequence 0 lost at frame ``at`` and relocalised at the camera pose ``T``."""

    def __init__(self, at: int, T: torch.Tensor) -> None:
        super().__init__()
        self.at, self.T, self.frames = at, T, 0

    def check(self, store, frame, cur, result, n_prev) -> Relocalisation:
        hit = torch.tensor([self.frames == self.at])
        self.frames += 1
        zero = torch.zeros(1)
        loss = LossCheck(hit, hit, torch.zeros(1, dtype=torch.bool), zero.long(), None)
        return Relocalisation(torch.where(hit[:, None, None], self.T, result.T_world_depth), hit, loss)


def test_the_tracker_applies_the_relocalisers_decision(synth):  # noqa: F811
    """At the decided frame the camera pose is the decided one exactly, a new model is taken there, and that frame
    (trusted: relocalised) becomes a keyframe at that pose."""
    seq = synth(seed=2, frames=5)
    T = _pose(20.0, [0.3, -0.2, 0.1])[None]
    tracker = make_tracker("data=tum")
    tracker.relocaliser = Decides(3, T)
    for k, frame in enumerate(iterate_batched([seq], prefetch=False)):
        res = tracker.step(frame)
        if k == 3:
            torch.testing.assert_close(res.T_world_depth, T, atol=F64_UNIT, rtol=0)
            torch.testing.assert_close(tracker.state.T_world_depth, T, atol=F64_UNIT, rtol=0)
            assert bool(res.reselected[0]) and bool(res.loss.relocalised[0])
            newest = tracker.keyframes.newest_first(0)[0]
            torch.testing.assert_close(tracker.keyframes.T_world_kf[0, newest], T[0], atol=F64_UNIT, rtol=0)
            assert float(tracker.keyframes.time[0, newest]) == float(frame.timestamp[0])
            assert not tracker.state.velocity.any()  # the lost frame's motion is not carried into the next start
        elif k == 2:
            assert tracker.state.velocity.abs().sum() > 0  # a moving camera: the zero above is the reset


def test_a_tracker_run_again_gives_the_same_trajectory(synth):  # noqa: F811
    """After ``reset`` the first frame starts everything anew, the back end's noise scales included (they adapt during a
    run): a second run of the same tracker on the same frames is the first run again (the same computation: exactly)."""
    seq = synth(seed=2, frames=6)
    tracker, runs = make_tracker("data=tum", "filter.noise_scale=true"), []
    for _ in range(2):
        tracker.reset()
        runs.append([tracker.step(f).T_world_depth for f in iterate_batched([seq], prefetch=False)])
    assert float(tracker.backend.scale_state.scale.sub(1).abs().max()) > 1e-3  # the scales did move in a run
    for a, b in zip(*runs, strict=True):
        assert torch.equal(a, b)
