"""LK started at the constant-velocity prediction (``pipeline.predict_init``): oracles are closed forms of the
tracker's own pose history and OpenCV's projection of the same points."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from test_tracker import make_tracker, synth  # noqa: F401  (fixture)

from torchtrack.config import CONF_DIR
from torchtrack.data import iterate_batched
from torchtrack.geometry import T_inv, se3_log

# the landmarks' re-tracking from keyframes (landmarks=default) calls the flow too: these tests spy on the tracking
# the dense map moves the model in the world (a correction, not motion): off, so that the differences of T_world_depth
# are the tracked motion the prediction extrapolates
NO_LANDMARKS = ("landmarks=none", "dense=none")


class SpyFlow:
    """Wraps the tracker's flow and records the ``init`` of every call (None when not given)."""

    def __init__(self, flow) -> None:
        self.flow, self.inits = flow, []

    def __call__(self, *args, init=None, **kwargs):
        self.inits.append(init)
        return self.flow(*args, init=init, **kwargs)


def fast(synth, frames=7):  # noqa: F811
    return synth(seed=5, frames=frames, trans_step_m=0.03, rot_step_deg=2.5)


def test_init_is_the_constant_velocity_projection(synth):  # noqa: F811
    """init(t) = projection (cv2.projectPoints) of the model points under inv(T_wc(t-1)) T_wc(t-2) T_cam_obj: the
    last camera motion applied once more (equal time steps), re-selections included."""
    seq = fast(synth)
    tracker = make_tracker("data=tum", "pipeline.predict_init=true", "reselect.fraction=0.9", *NO_LANDMARKS)
    spy = tracker.flow = SpyFlow(tracker.flow)
    T_wc, checked, reselected = [], 0, []
    for frame in iterate_batched([seq], prefetch=False):
        s = tracker.state
        if len(T_wc) >= 2:
            T_pred = (T_inv(T_wc[-1]) @ T_wc[-2] @ s.T_cam_obj)[0].numpy()
            pts = s.points_obj[0][s.valid[0]].double().numpy()
            rvec, _ = cv2.Rodrigues(T_pred[:3, :3])
            expected, _ = cv2.projectPoints(pts, rvec, T_pred[:3, 3], frame.K[0].double().numpy(), None)
        res = tracker.step(frame)
        if len(T_wc) >= 2:
            got = spy.inits[-1][0][s.valid[0]].double().numpy()
            np.testing.assert_allclose(got, expected[:, 0], atol=1e-3)
            checked += 1
        T_wc.append(res.T_world_depth)
        reselected.append(bool(res.reselected[0]))
    assert checked == len(seq) - 2 and len(spy.inits) == len(seq) - 1
    assert any(reselected[1:-1])  # a prediction right after a re-selection was checked too


def test_velocity_is_the_camera_motion_and_survives_reselection(synth):  # noqa: F811
    """state.velocity = se3_log(inv(T_world_depth(t)) T_world_depth(t-1)) / dt at every frame, a re-selection included
    (the camera-frame motion does not depend on the model frame)."""
    seq = fast(synth, frames=8)
    tracker = make_tracker("data=tum", "pipeline.predict_init=true", "reselect.fraction=0.95", *NO_LANDMARKS)
    prev, reselections = None, 0
    for frame in iterate_batched([seq], prefetch=False):
        res = tracker.step(frame)
        if prev is not None:
            dt = float(frame.timestamp[0] - prev[1][0])
            expected = se3_log(T_inv(res.T_world_depth) @ prev[0]) / dt
            torch.testing.assert_close(tracker.state.velocity, expected, atol=1e-9, rtol=1e-6)
            reselections += int(res.reselected[0])
        prev = (res.T_world_depth, frame.timestamp)
    assert reselections >= 1  # the property was checked across a re-selection


@pytest.mark.parametrize("overrides", [["pipeline.predict_init=false", *NO_LANDMARKS], ["+experiment=paper"]])
def test_paper_and_switch_off_start_at_the_previous_pixel(synth, overrides):  # noqa: F811
    seq = fast(synth, frames=3)
    tracker = make_tracker("data=tum", *overrides)
    spy = tracker.flow = SpyFlow(tracker.flow)
    for frame in iterate_batched([seq], prefetch=False):
        tracker.step(frame)
    assert spy.inits == [None, None]


def test_the_default_predicts():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        assert compose("config").pipeline.predict_init is True
        assert compose("config", overrides=["+experiment=paper"]).pipeline.predict_init is False
