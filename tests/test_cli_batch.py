"""A batch loses only what failed, at load too; a listed frame whose file is missing is a dropped frame.

The ``torchtrack`` console script runs in subprocesses (exit codes and error lines are part of the contract) on
copies of one small synthetic sequence (exact ground truth): a healthy copy, one whose depth image of frame 3 is
missing, and three that fail their load checks (a broken groundtruth.txt, a bad intrinsics.txt, an empty rgb.txt).
"""

from __future__ import annotations

import json
import shutil
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from test_cli import read_tum_strict, run_cli
from tolerances import TRAJ

from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

FRAMES = 8
MISSING = 3  # the frame whose depth file is deleted


def _listed(root: Path, listing: str) -> list[str]:
    return [ln.split()[1] for ln in (root / listing).read_text().splitlines() if ln.strip() and not ln.startswith("#")]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("cli_batch")
    synth = ensure_sequence(SyntheticConfig(width=160, height=120, frames=FRAMES, seed=2, noise="none"), base / "cache")
    roots = {name: base / name for name in ("healthy", "missing_depth", "broken_gt", "bad_intrinsics", "empty_list")}
    for root in roots.values():
        shutil.copytree(synth, root)
    (roots["missing_depth"] / _listed(synth, "depth.txt")[MISSING]).unlink()
    (roots["broken_gt"] / "groundtruth.txt").write_text("0.0 1 2 3 nan 0 0 1\n")
    (roots["bad_intrinsics"] / "intrinsics.txt").write_text("-100 100 80 60 5000\n")
    (roots["empty_list"] / "rgb.txt").write_text("# no frames\n")
    common = ["data=tum", "plots=false", "data.max_frames=20"]
    batch = "[" + ",".join(str(r) for r in roots.values()) + "]"
    jobs = {
        "batch": [*common, f"data.root={batch}"],
        "healthy": [*common, f"data.root={roots['healthy']}"],
        "missing_alone": [*common, f"data.root={roots['missing_depth']}"],
        "missing_strict": [*common, f"data.root={roots['missing_depth']}", "data.on_bad_frame=error"],
        "broken_alone": [*common, f"data.root={roots['broken_gt']}"],
    }
    with ThreadPoolExecutor(len(jobs)) as pool:
        futures = {k: pool.submit(run_cli, [*a, f"hydra.run.dir={base / 'out' / k}"], base / "cache", base)
                   for k, a in jobs.items()}  # fmt: skip
        return {k: (f.result(), base / "out" / k) for k, f in futures.items()}


def _metrics(out: Path, name: str) -> dict:
    return json.loads((out / name / "metrics.json").read_text())


def _failed_lines(proc) -> list[str]:
    return [ln for ln in (proc.stdout + proc.stderr).splitlines() if "FAILED" in ln]


def test_missing_file_is_a_dropped_frame(runs):
    proc, out = runs["missing_alone"]
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = _metrics(out, "missing_depth")
    assert m["complete"] and m["frames"] == FRAMES - 1 and m["dropped_frames"] == 1
    assert m["dropped_timestamps"] == pytest.approx([MISSING / 30.0], abs=1e-6)
    t, _ = read_tum_strict(out / "missing_depth" / "trajectory.txt")
    assert len(t) == FRAMES - 1 and not np.any(np.isclose(t, MISSING / 30.0, atol=1e-6))
    text = proc.stdout + proc.stderr
    assert "depth image not found" in text and "frame 3 dropped" in text and "Traceback" not in text


def test_missing_file_with_on_bad_frame_error_stops_before_tracking(runs):
    proc, out = runs["missing_strict"]
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1, lines
    assert "listed in depth.txt not found" in lines[0] and not (out / "missing_depth").exists()


def test_a_single_sequence_that_fails_to_load_keeps_its_one_line(runs):
    proc, out = runs["broken_alone"]
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "groundtruth.txt" in lines[0], lines
    assert not (out / "broken_gt").exists()


def test_batch_loses_only_what_failed_at_load(runs):
    proc, out = runs["batch"]
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")) == [
        "healthy",
        "missing_depth",
    ]
    failed = _failed_lines(proc)
    assert len(failed) == 3, failed
    for name, what in (
        ("broken_gt", "groundtruth.txt"),
        ("bad_intrinsics", "intrinsics.txt"),
        ("empty_list", "rgb.txt"),
    ):
        (line,) = [ln for ln in failed if f"FAILED {name} at load" in ln]
        assert what in line
    assert "Traceback" not in proc.stderr
    assert _metrics(out, "healthy")["complete"] and _metrics(out, "healthy")["frames"] == FRAMES
    m = _metrics(out, "missing_depth")
    assert m["complete"] and m["frames"] == FRAMES - 1 and m["dropped_frames"] == 1


@pytest.mark.equivalence
def test_batch_trajectory_equals_the_single_run_within_float_error(runs):
    """B=2 (the healthy and the missing-depth copies) vs B=1: other shapes, other summation orders (tolerances.TRAJ)."""
    (_, batch), (proc, alone) = runs["batch"], runs["healthy"]
    assert proc.returncode == 0
    t_b, T_b = read_tum_strict(batch / "healthy" / "trajectory.txt")
    t_a, T_a = read_tum_strict(alone / "healthy" / "trajectory.txt")
    np.testing.assert_array_equal(t_b, t_a)
    np.testing.assert_allclose(T_b[:, :3, 3], T_a[:, :3, 3], rtol=0, atol=TRAJ)
    np.testing.assert_allclose(T_b[:, :3, :3], T_a[:, :3, :3], rtol=0, atol=TRAJ)
