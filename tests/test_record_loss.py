"""Recording through a tracking loss: a synthetic sequence with a block of frames removed (the camera jumps; the
loss check fires and relocalisation takes a new model), recorded with ``torchtrack-record``'s function.

Oracles: the tracker run without recording (its relocalised frame and the pose its back end was reset to), and the
back end replayed on the recorded observations, which must reproduce the recorded estimates at every frame —
after the relocalisation too, which holds only when the cache's ``model_T_cam_obj`` is the relocalised model's.
"""

from __future__ import annotations

import shutil

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.learn.cache import load_observations
from torchtrack.learn.record import record_sequences

pytestmark = pytest.mark.slow  # recording observations of whole sequences

GAP = (10, 20)  # frames removed: a jump of 3.6 cm and 8.4 degrees (tests/test_relocalise.py)
# Recording and a plain run do the same arithmetic on the same shapes; the replay repeats the back end's update on
# the recorded float32 inputs in float64: 1e-9 (m and rotation entries) is float64 round-off over ~20 updates.
POSE_TOL = 1e-9


def config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.fixture(scope="module")
def jump(tmp_path_factory) -> TumSequence:
    base = tmp_path_factory.mktemp("loss")
    full = ensure_sequence(SyntheticConfig(width=320, height=240, frames=30, seed=0, noise="kinect"), base / "cache")
    root = shutil.copytree(full, base / "jump")
    for name in ("rgb.txt", "depth.txt"):
        lines = [ln for ln in (root / name).read_text().splitlines() if ln and not ln.startswith("#")]
        (root / name).write_text("\n".join(ln for i, ln in enumerate(lines) if not GAP[0] <= i < GAP[1]) + "\n")
    return TumSequence(root)


@pytest.fixture(scope="module")
def plain(jump):
    """Per frame of a run without recording: (relocalised, T_cam_obj as tracked, the back end's pose after the
    frame)."""
    tracker, out = build_tracker(config()), []
    with torch.inference_mode():
        for frame in iterate_batched([jump], prefetch=False):
            res = tracker.step(frame)
            out.append((bool(res.loss.relocalised[0]), res.T_cam_obj[0].clone(), tracker.state.T_cam_obj[0].clone()))
    return out


@pytest.fixture(scope="module")
def recorded(jump, tmp_path_factory):
    (path,) = record_sequences(config(), [jump], tmp_path_factory.mktemp("rec"), progress=False)
    return load_observations(path)


def test_the_loss_is_relocalised(plain):
    reloc = [t for t, (r, _, _) in enumerate(plain) if r]
    assert reloc and reloc[0] == GAP[0], reloc  # the first frame after the jump


def test_recorded_reset_is_the_relocalised_model(plain, recorded):
    assert recorded.frames == len(plain)
    for t, (reloc, T_tracked, T_backend) in enumerate(plain):
        torch.testing.assert_close(recorded.T_cam_obj_est[t], T_tracked.double(), atol=POSE_TOL, rtol=0)
        if reloc:
            assert bool(recorded.reselected[t])
            torch.testing.assert_close(recorded.model_T_cam_obj[t], T_backend.double(), atol=POSE_TOL, rtol=0)


def test_replay_through_the_loss_reproduces_the_tracker(recorded):
    backend = build_tracker(config()).backend
    backend.reset(recorded.model_T_cam_obj[:1], torch.ones(1, dtype=torch.bool))
    for t in range(1, recorded.frames):
        T = backend.step(recorded.observation(t), recorded.variances(t)).T_cam_obj.double()
        torch.testing.assert_close(T[0], recorded.T_cam_obj_est[t], atol=POSE_TOL, rtol=0, msg=f"frame {t}")
        if recorded.reselected[t]:
            backend.reset(recorded.model_T_cam_obj[t : t + 1], torch.ones(1, dtype=torch.bool))
