"""The tracker on synthetic sequences with exact ground truth (oracle: the renderer's poses)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.cli import build_tracker
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.geometry import T_inv, rotation_angle

CONF = Path(__file__).resolve().parents[1] / "conf"


def make_tracker(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return build_tracker(compose("config", overrides=list(overrides)))


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    """Noise-free synthetic sequences; small images keep the suite fast where accuracy is not the point."""
    root = tmp_path_factory.mktemp("synth")

    def get(mode="scene", seed=0, frames=8, noise="none", size=(320, 240)):
        cfg = SyntheticConfig(width=size[0], height=size[1], frames=frames, seed=seed, mode=mode, noise=noise)
        return TumSequence(ensure_sequence(cfg, root))

    return get


def track(tracker, sequences):
    poses, results = [], []
    for frame in iterate_batched(sequences, prefetch=False):
        res = tracker.step(frame)
        poses.append(res.T_world_cam.clone())
        results.append(res)
    return torch.stack(poses, 1), results  # B,F,4,4


def pose_errors(T_est: torch.Tensor, T_gt: np.ndarray) -> tuple[float, float]:
    """Max translation (m) and rotation (deg) error of camera poses, no alignment (both start at GT)."""
    E = T_inv(torch.as_tensor(T_gt)) @ T_est
    return float(E[:, :3, 3].norm(dim=-1).max()), float(rotation_angle(E[:, :3, :3]).max().rad2deg())


@pytest.mark.parametrize("mode", ["scene", "object"])
def test_noise_free_tracking_is_exact(synth, mode):
    seq = synth(mode=mode, size=(640, 480))  # full resolution: LK drift is ~0.07 px per frame here
    region = "region=object" if mode == "object" else "region=scene"
    poses, results = track(make_tracker(region), [seq])
    trans, rot = pose_errors(poses[0], seq.groundtruth)
    assert trans < 1e-3, f"{mode}: max translation error {trans * 1000:.3f} mm"
    assert rot < 0.1, f"{mode}: max rotation error {rot:.4f} deg"
    assert int(results[-1].n_features[0]) >= 12


def test_batched_equals_looped(synth):
    a, b = synth(seed=1, frames=8), synth(seed=2, frames=6)  # different lengths: b ends early
    batched, _ = track(make_tracker(), [a, b])
    alone_a, _ = track(make_tracker(), [a])
    alone_b, _ = track(make_tracker(), [b])
    torch.testing.assert_close(batched[0], alone_a[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(batched[1, :6], alone_b[0], atol=1e-5, rtol=0)


def test_reselection_keeps_trajectory_continuous(synth):
    """Re-selecting at every frame chains the poses without a jump and stays accurate."""
    seq = synth(seed=3, frames=8)
    tracker = make_tracker("tracker.reselect_fraction=0.999")
    for frame in iterate_batched([seq], prefetch=False):
        res = tracker.step(frame)
        assert bool(res.reselected[0])
        after = tracker.T_world_obj @ T_inv(tracker.T_cam_obj.double())  # pose under the new model
        torch.testing.assert_close(after, res.T_world_cam, atol=1e-9, rtol=0)
    trans, rot = pose_errors(res.T_world_cam, seq.groundtruth[-1:])
    assert trans < 2e-3 and rot < 0.2


@pytest.mark.parametrize("tracker", ["horn", "icp", "cpd"])
def test_baselines_share_the_front_end(synth, tracker):
    """Noise-free 3D-3D correspondences: Horn is exact; ICP/CPD start at the previous pose and stay close."""
    seq = synth(seed=4, frames=6)
    poses, _ = track(make_tracker(f"tracker={tracker}"), [seq])
    trans, rot = pose_errors(poses[0], seq.groundtruth)
    bound = 1e-3 if tracker == "horn" else 2e-2
    assert trans < bound, f"{tracker}: {trans * 1000:.2f} mm"
