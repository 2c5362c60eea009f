"""Faults cost only what failed: dropped frames, a failing sequence in a lockstep batch, an unwritable output folder,
a failing tracker step, file modes. Oracles: the same sequences tracked without the fault."""

from __future__ import annotations

import json
import shutil
import stat

import cv2
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from tolerances import TRAJ

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, read_tum_trajectory
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.io import FILE_MODE
from torchtrack.run import run_tracker

pytestmark = pytest.mark.slow  # the runner end to end on broken inputs


def make_tracker():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return build_tracker(compose("config"))


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    cfg = SyntheticConfig(width=160, height=120, frames=10, seed=3, mode="scene", noise="none")
    return ensure_sequence(cfg, tmp_path_factory.mktemp("synth"))


@pytest.fixture
def copies(rendered, tmp_path):
    def get(n: int, **kw) -> list[TumSequence]:
        return [TumSequence(shutil.copytree(rendered, tmp_path / f"seq{k}"), **kw) for k in range(n)]

    return get


def outputs(out, name):
    metrics = json.loads((out / name / "metrics.json").read_text())
    t, T = (
        read_tum_trajectory(out / name / "trajectory.txt") if (out / name / "trajectory.txt").exists() else (None,) * 2
    )
    return metrics, t, T


@pytest.mark.equivalence
def test_one_failing_sequence_costs_only_itself(copies, tmp_path):
    """Poses within TRAJ of the run without the fault: once seq1 fails the batch tracks other shapes."""
    seqs = copies(2, on_bad_frame="error")
    results = run_tracker(make_tracker(), seqs, tmp_path / "alone", plots=False)
    assert all(r["complete"] for r in results)
    _, _, T_alone = outputs(tmp_path / "alone", "seq0")
    seqs[1].depth_paths[6].write_bytes(b"corrupt")
    results = run_tracker(make_tracker(), seqs, tmp_path / "out", plots=False)
    healthy, t0, T0 = outputs(tmp_path / "out", "seq0")
    broken, t1, T1 = outputs(tmp_path / "out", "seq1")
    assert results == [healthy, broken]
    assert healthy["complete"] and healthy["frames"] == 10
    np.testing.assert_allclose(T0, T_alone, rtol=0, atol=TRAJ)
    assert not broken["complete"] and broken["frames"] == 6 and len(t1) == 6
    assert broken["error"].startswith(f"{seqs[1].depth_paths[6]}: ") and "corrupt depth" in broken["error"]
    assert np.array_equal(t1, seqs[1].timestamps[:6])
    np.testing.assert_allclose(T1, T_alone[:6], rtol=0, atol=TRAJ)
    assert (tmp_path / "out" / "seq1" / "frames.csv").read_text().count("\n") == 7


def test_dropped_frame_is_counted_and_predicted_through(copies, tmp_path):
    (seq,) = copies(1)
    full = run_tracker(make_tracker(), [seq], tmp_path / "full", plots=False)[0]
    cv2.imwrite(str(seq.depth_paths[4]), np.zeros((120, 160), np.uint16))
    (m,) = run_tracker(make_tracker(), [seq], tmp_path / "out", plots=False)
    _, t, _ = outputs(tmp_path / "out", seq.name)
    assert m["complete"] and m["frames"] == 9 and m["dropped_frames"] == 1
    assert m["dropped_timestamps"] == [float(seq.timestamps[4])]
    assert np.array_equal(t, np.delete(seq.timestamps, 4))
    assert m["ate_rmse_m"] < full["ate_rmse_m"] + 2e-3  # a noise-free scene: the gap costs (almost) nothing


def test_unwritable_output_is_found_before_tracking(copies, tmp_path):
    (seq,) = copies(1)
    blocker = tmp_path / "file"
    blocker.write_text("")
    tracker = make_tracker()
    tracker.step = lambda frame: pytest.fail("tracked before checking the output folder")
    with pytest.raises(OSError, match=f"^{blocker / 'seq0'}: output folder not writable"):
        run_tracker(tracker, [seq], blocker, plots=False)


def test_failing_step_keeps_what_was_tracked(copies, tmp_path):
    seqs = copies(2)
    tracker = make_tracker()
    step, calls = tracker.step, []

    def failing(frame):
        calls.append(1)
        if len(calls) == 4:
            raise RuntimeError("boom")
        return step(frame)

    tracker.step = failing
    results = run_tracker(tracker, seqs, tmp_path / "out", plots=False)
    for r, s in zip(results, seqs, strict=True):
        m, t, _ = outputs(tmp_path / "out", s.name)
        assert m == r and not m["complete"] and m["frames"] == 3 and len(t) == 3
        assert m["error"] == "tracking failed at step 3: RuntimeError: boom"


def test_outputs_have_the_normal_file_mode(copies, tmp_path):
    (seq,) = copies(1)
    run_tracker(make_tracker(), [seq], tmp_path / "out", plots=True)
    files = sorted((tmp_path / "out" / seq.name).iterdir())
    assert {f.name for f in files} == {"trajectory.txt", "metrics.json", "frames.csv", "trajectory.png", "features.png"}
    assert {stat.S_IMODE(f.stat().st_mode) for f in files} == {FILE_MODE}
