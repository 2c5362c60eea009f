"""Tracking loss and relocalisation: PnP on a known pose, and a synthetic sequence with a block of frames removed
(a jump of 3.6 cm and 8.4 degrees) whose ATE must stay that of the full sequence."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, read_tum_trajectory
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.geometry import T_inv, make_T, rotation_angle, so3_exp
from torchtrack.pipeline.relocalise import pnp_pose
from torchtrack.run import run_tracker

GAP = (10, 20)  # frames removed


def test_pnp_pose_recovers_a_known_pose_among_outliers():
    rng = np.random.default_rng(0)
    T_cam_world = make_T(so3_exp(torch.tensor([0.1, -0.3, 0.2], dtype=torch.float64)), torch.tensor([0.2, -0.1, 0.5]))
    T_cam_world = T_cam_world.double().numpy()
    cam = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(1, 4, 200)]  # in front of the camera
    world = (cam - T_cam_world[:3, 3]) @ T_cam_world[:3, :3]  # inverse transform, row vectors
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    pixels = cam[:, :2] / cam[:, 2:] * 525.0 + [319.5, 239.5]
    pixels[:60] = rng.uniform(0, 640, (60, 2))  # 30 % outliers
    T, n = pnp_pose(world, pixels, K, reprojection_px=2.0)
    assert n == 140 and np.allclose(T, T_cam_world, atol=1e-6)
    assert pnp_pose(world[:5], pixels[:5], K, 2.0) == (None, 0)


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """(full, jump): a noisy synthetic scene of 30 frames, and a copy without frames GAP[0]..GAP[1]-1."""
    base = tmp_path_factory.mktemp("reloc")
    full = ensure_sequence(SyntheticConfig(width=320, height=240, frames=30, seed=0, noise="kinect"), base / "cache")
    jump = shutil.copytree(full, base / "jump")
    for name in ("rgb.txt", "depth.txt"):
        lines = (full / name).read_text().splitlines()
        rows = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")]
        gone = set(rows[GAP[0] : GAP[1]])
        (jump / name).write_text("\n".join(ln for i, ln in enumerate(lines) if i not in gone) + "\n")
    return full, jump


def track(root, out, *overrides, min_inliers: int | None = None):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        tracker = build_tracker(compose("config", overrides=list(overrides)))
    if min_inliers is not None:  # a threshold of the relocaliser, not a key
        tracker.relocaliser.min_inliers = min_inliers
    (m,) = run_tracker(tracker, [TumSequence(root)], out, plots=False)
    rows = [ln.split(",") for ln in (out / root.name / "frames.csv").read_text().splitlines()]
    csv = {k: [r[i] for r in rows[1:]] for i, k in enumerate(rows[0])}
    return m, csv


@pytest.mark.slow
def test_the_jump_is_large(sequences):
    seq = TumSequence(sequences[0])
    E = T_inv(torch.as_tensor(seq.groundtruth[GAP[0] - 1])) @ torch.as_tensor(seq.groundtruth[GAP[1]])
    assert float(E[:3, 3].norm()) > 0.03 and float(rotation_angle(E[:3, :3]).rad2deg()) > 8


@pytest.mark.slow
def test_jump_is_detected_and_recovered(sequences, tmp_path):
    full, jump = sequences
    m_full, csv_full = track(full, tmp_path / "full")
    m, csv = track(jump, tmp_path / "jump")
    assert m_full["lost_frames"] == 0 and set(csv_full["lost"]) == {"False"}
    lost = [i for i, v in enumerate(csv["lost"]) if v == "True"]
    assert lost == [GAP[0]] and csv["relocalised"][GAP[0]] == "True" and set(csv["interrupted"]) == {"False"}
    assert m["lost_frames"] == 1 and m["relocalisations"] == 1 and m["complete"]
    assert m["ate_rmse_m"] < m_full["ate_rmse_m"] + 0.002  # close to the full sequence's (4.4 mm), not offset
    m_off, csv_off = track(jump, tmp_path / "off", "relocalise.recover=false")  # the paper: marked, not recovered
    assert m_off["lost_frames"] == 1 and csv_off["lost"][GAP[0]] == "True" and m_off["relocalisations"] == 0
    assert m_off["ate_rmse_m"] > 10 * m_full["ate_rmse_m"]  # the offset the relocalisation removes


def test_failed_relocalisation_interrupts_the_trajectory(sequences, tmp_path):
    _, jump = sequences
    m, csv = track(jump, tmp_path / "out", min_inliers=100000)  # nothing can verify
    n = 30 - (GAP[1] - GAP[0])
    assert csv["interrupted"] == ["False"] * GAP[0] + ["True"] * (n - GAP[0])  # retried every frame, never resumed
    assert m["interrupted_frames"] == n - GAP[0] and m["frames"] == n and m["relocalisations"] == 0
    t, _ = read_tum_trajectory(tmp_path / "out" / jump.name / "trajectory.txt")
    assert np.array_equal(t, TumSequence(jump).timestamps[: GAP[0]])  # untrusted poses are not written
    assert json.loads((tmp_path / "out" / jump.name / "metrics.json").read_text()) == m
