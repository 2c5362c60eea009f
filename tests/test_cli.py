"""Integration tests of the ``torchtrack`` CLI contract (README, "What a run writes"), run as a user runs it.

The console script runs in a subprocess (its exit code and its error output are part of the contract) on a
10-frame synthetic sequence (exact ground truth, rendered into a temporary ``TORCHTRACK_CACHE``) and on 10
frames of ``../shared/data/visp_castle_simu`` (skipped when absent). Files are read back with independent
parsers (numpy + scipy's quaternion convention), and metrics.json is re-computed from the written files.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tolerances import TRAJ

from torchtrack.metrics import trajectory_metrics

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CASTLE = DATA / "visp_castle_simu"
FRAMES = 10
METRIC_KEYS = ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg", "frames", "fps")
# The default synthetic scene (Kinect v1 noise model: sigma(z) = 1.2 mm + 1.9e-3 (z - 0.4)^2 plus 1/8-px disparity
# steps, i.e. ~5 mm per point at 2.5 m; ~230 features; ~1 cm and ~1 deg per frame), 10 frames. Measured ATE:
# 1.6 mm (2026-11, fusion EKF); averaging ~5 mm point noise over ~230 features gives ~0.3 mm per frame, which
# accumulates over the frames. Bound: 3x the measurement, and 4x below the ATE of a camera frozen at the first
# pose (19.6 mm on these frames), so that a tracker that does not follow the motion fails.
SYNTH_ATE_BOUND_M = 0.005
# Values the data schema refuses when composing (types) or validating (ranges): exit code 2, one line naming the key.
BAD_VALUES = {"depth_scale": "abc", "max_frames": -1, "stride": 0, "root": "[]"}
FRAMES_CSV_COLUMNS = ["frame", "timestamp", "features", "sim_wins", "reprojection_px", "mean_tim_px", "reselected"]
FRAMES_CSV_COLUMNS += ["noise_scale_pix", "noise_scale_xyz"]  # the online noise scale (on by default; 1.0 when off)
FRAMES_CSV_COLUMNS += ["lost", "relocalised", "interrupted"]  # the loss check (torchtrack.pipeline.relocalise)
# The runs a test needs where that is fewer than all of them: when only such tests are selected (``pytest -m
# equivalence``) the module starts only their runs; any other test selected starts them all.
RUNS_OF_TEST = {
    "test_batch_with_a_broken_sequence_writes_the_healthy_one_and_exits_non_zero": {"castle", "broken_batch"}
}


def cli_command() -> list[str]:
    script = Path(sys.executable).with_name("torchtrack")
    return [str(script)] if script.is_file() else [sys.executable, "-m", "torchtrack.cli"]


def run_cli(args: list[str], cache: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "TORCHTRACK_CACHE": str(cache)}
    env.pop("HYDRA_FULL_ERROR", None)  # the one-line error is what a user sees by default
    return subprocess.run(cli_command() + args, capture_output=True, text=True, env=env, cwd=cwd, timeout=300)


def read_tum_strict(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """TUM trajectory -> (timestamps (F,), T_world_cam (F, 4, 4)); asserts 8 numbers a line and unit quaternions."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    assert all(len(r) == 8 for r in rows), f"{path}: every line must have 8 fields"
    v = np.array(rows, dtype=np.float64)
    np.testing.assert_allclose(np.linalg.norm(v[:, 4:8], axis=1), 1.0, atol=1e-6)
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = Rotation.from_quat(v[:, 4:8]).as_matrix()  # scipy: (x, y, z, w), as TUM
    T[:, :3, 3] = v[:, 1:4]
    return v[:, 0], T


def sequence_dirs(out: Path) -> list[Path]:
    return sorted(p for p in out.iterdir() if p.is_dir() and not p.name.startswith("."))


def broken_copies(base: Path) -> tuple[Path, Path]:
    """Copies of the castle sequence: one with a corrupt colour frame 6, one with a NaN in its ground truth."""
    broken, nan_gt = base / "castle_broken", base / "castle_nan_gt"
    for root in (broken, nan_gt):
        shutil.copytree(CASTLE, root)
    rgb = [ln.split()[1] for ln in (broken / "rgb.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    (broken / rgb[6]).write_bytes(b"corrupt")
    lines = (nan_gt / "groundtruth.txt").read_text().splitlines()
    k = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
    lines[k + 2] = " ".join(lines[k + 2].split()[:4] + ["nan"] + lines[k + 2].split()[5:])
    (nan_gt / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    return broken, nan_gt


@pytest.fixture(scope="module")
def runs(request, tmp_path_factory) -> Iterator[dict[str, Future]]:
    """The CLI runs the selected tests of this module need, started together (each pays the CLI's start-up; they
    overlap).

    Each future gives (process, run folder, ground-truth file or None).
    """
    base = tmp_path_factory.mktemp("cli")
    cache = base / "cache"
    jobs = {
        "synthetic": [f"data.scene.frames={FRAMES}"],
        "missing_root": ["data=tum", f"data.root={base / 'no_such_sequence'}"],
        "empty_root": ["data=tum", f"data.root={base / 'empty'}"],  # a folder without rgb.txt
        "unknown_key": ["data.no_such_key=1"],
        "unknown_group": ["tracker=no_such_tracker"],
        **{f"bad_{k}": ["data=tum", f"data.{k}={v}"] for k, v in BAD_VALUES.items()},
    }
    if (CASTLE / "rgb.txt").is_file():
        jobs["castle"] = ["data=tum", f"data.root={CASTLE}", f"data.max_frames={FRAMES}", "plots=false"]
        broken, nan_gt = broken_copies(base)
        jobs["broken_batch"] = ["data=tum", f"data.root=[{CASTLE},{broken}]", f"data.max_frames={FRAMES}", "plots=false",
                                "data.on_bad_frame=error"]  # fmt: skip
        jobs["nan_gt"] = ["data=tum", f"data.root={nan_gt}", f"data.max_frames={FRAMES}", "plots=false"]
    selected = [item.originalname for item in request.session.items if item.module is request.module]
    needed = set().union(*(RUNS_OF_TEST.get(name, set(jobs)) for name in selected))
    jobs = {name: args for name, args in jobs.items() if name in needed}
    cache.mkdir()
    (base / "empty").mkdir()

    def job(name: str, args: list[str]):
        out = base / name
        proc = run_cli([*args, f"hydra.run.dir={out}"], cache, base)
        gts = sorted(cache.rglob("groundtruth.txt")) if name == "synthetic" else [CASTLE / "groundtruth.txt"]
        return proc, out, gts[0] if len(gts) == 1 else None

    with ThreadPoolExecutor(len(jobs)) as pool:
        yield {name: pool.submit(job, name, args) for name, args in jobs.items()}


def result(runs: dict[str, Future], name: str):
    if name not in runs and not (CASTLE / "rgb.txt").is_file():
        pytest.skip(f"{CASTLE} not available")
    assert name in runs, f"the run {name!r} was not started: list it in RUNS_OF_TEST"
    return runs[name].result()


@pytest.fixture(params=["synthetic", "castle"])
def any_run(request, runs):
    return result(runs, request.param)


def test_run_succeeds_and_writes_the_contract(any_run):
    proc, out, gt = any_run
    assert proc.returncode == 0, proc.stderr[-2000:]
    (seq,) = sequence_dirs(out)
    for name in ("trajectory.txt", "metrics.json", "frames.csv"):
        assert (seq / name).is_file(), f"{seq / name} missing"
    assert (out / ".hydra" / "config.yaml").is_file()
    assert gt is not None and gt.is_file()


def test_trajectory_is_tum_and_starts_at_ground_truth(any_run):
    _, out, gt = any_run
    (seq,) = sequence_dirs(out)
    ts, T = read_tum_strict(seq / "trajectory.txt")
    ts_gt, T_gt = read_tum_strict(gt)
    assert len(ts) == FRAMES
    np.testing.assert_allclose(ts, ts_gt[:FRAMES], atol=1e-6)  # one pose per frame, the frames' timestamps
    np.testing.assert_allclose(T[0], T_gt[0], atol=1e-6)
    np.testing.assert_allclose(
        T[:, :3, :3] @ T[:, :3, :3].transpose(0, 2, 1), np.broadcast_to(np.eye(3), (FRAMES, 3, 3)), atol=1e-6
    )


def test_metrics_json_equals_metrics_of_the_written_files(any_run):
    _, out, gt = any_run
    (seq,) = sequence_dirs(out)
    metrics = json.loads((seq / "metrics.json").read_text())
    assert set(METRIC_KEYS) <= set(metrics)
    assert metrics["frames"] == FRAMES and metrics["fps"] > 0
    ts, T = read_tum_strict(seq / "trajectory.txt")
    _, T_gt = read_tum_strict(gt)
    expect = trajectory_metrics(ts, T, T_gt[:FRAMES])  # the file has 9 decimals: agreement to ~1e-8
    for k in ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg"):
        assert metrics[k] == pytest.approx(expect[k], rel=1e-4, abs=1e-7), k


def test_synthetic_run_writes_pictures_and_resolved_config(runs):
    _, out, _ = result(runs, "synthetic")
    (seq,) = sequence_dirs(out)
    assert (seq / "trajectory.png").stat().st_size > 0 and (seq / "features.png").stat().st_size > 0
    config = (out / ".hydra" / "config.yaml").read_text()
    assert f"frames: {FRAMES}" in config


def test_synthetic_ate_is_small(runs):
    _, out, gt = result(runs, "synthetic")
    (seq,) = sequence_dirs(out)
    metrics = json.loads((seq / "metrics.json").read_text())
    assert metrics["ate_rmse_m"] < SYNTH_ATE_BOUND_M
    ts, T_gt = read_tum_strict(gt)
    frozen = np.repeat(T_gt[:1], FRAMES, axis=0)
    assert trajectory_metrics(ts[:FRAMES], frozen, T_gt[:FRAMES])["ate_rmse_m"] > 2 * SYNTH_ATE_BOUND_M  # a real test


@pytest.mark.parametrize("name", ["missing_root", "empty_root"])
def test_bad_root_fails_with_one_line_error(name, runs):
    proc, out, _ = result(runs, name)
    text = (proc.stdout + proc.stderr).strip()
    assert proc.returncode != 0
    assert "Traceback" not in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1, text
    root = out.parent / "no_such_sequence" if name == "missing_root" else out.parent / "empty"
    assert str(root) in lines[0]


@pytest.mark.parametrize("name", ["unknown_key", "unknown_group"])
def test_unknown_config_key_fails_clearly(name, runs):
    proc, out, _ = result(runs, name)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0
    assert "Traceback" not in text, text
    assert "no_such" in text
    assert not out.exists()  # refused before anything ran


@pytest.mark.parametrize("key", sorted(BAD_VALUES))
def test_bad_data_values_fail_when_composing_with_one_line(key, runs):
    proc, out, _ = result(runs, f"bad_{key}")
    text = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 2, text
    assert "Traceback" not in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1 and f"data.{key}" in lines[0], text
    assert not out.exists()  # refused before anything ran


def read_frames_csv(path: Path) -> dict[str, np.ndarray]:
    header, *rows = [line.split(",") for line in path.read_text().splitlines()]
    assert header == FRAMES_CSV_COLUMNS
    cols = {k: [r[i] for r in rows] for i, k in enumerate(header)}
    flags = ("reselected", "lost", "relocalised", "interrupted")
    assert all(set(cols[k]) <= {"True", "False"} for k in flags)
    out = {k: np.array(v, dtype=np.float64) for k, v in cols.items() if k not in flags}
    out.update({k: np.array([v == "True" for v in cols[k]]) for k in flags})
    return out


def test_frames_csv_contents(any_run):
    """Every column of frames.csv: one row per frame, the trajectory's timestamps, counts and errors in range."""
    _, out, gt = any_run
    (seq,) = sequence_dirs(out)
    f = read_frames_csv(seq / "frames.csv")
    ts, _ = read_tum_strict(seq / "trajectory.txt")
    ts_gt, _ = read_tum_strict(gt)
    np.testing.assert_array_equal(f["frame"], np.arange(FRAMES))
    np.testing.assert_allclose(f["timestamp"], ts, atol=1e-6)
    np.testing.assert_allclose(f["timestamp"], ts_gt[:FRAMES], atol=1e-6)
    assert (f["features"] == np.round(f["features"])).all() and (f["features"] >= 12).all()  # min_features
    assert (f["sim_wins"] == np.round(f["sim_wins"])).all() and (0 <= f["sim_wins"]).all()
    assert (f["sim_wins"] <= f["features"]).all()
    assert f["reselected"][0], "the first frame takes the first model"
    assert f["sim_wins"][0] == 0 and f["mean_tim_px"][0] == 0 and f["reprojection_px"][0] < 0.05  # nothing tracked yet
    assert (f["mean_tim_px"][1:] > 0).all() and (f["mean_tim_px"] <= 1.0).all()  # d_TIM threshold 1 px
    assert (f["reprojection_px"][1:] > 0).all() and (f["reprojection_px"] < 3.0).all()  # max_residual_px


def test_metrics_json_every_field(any_run):
    """Every field of metrics.json, recomputed from frames.csv and trajectory.txt (and ground truth)."""
    _, out, gt = any_run
    (seq,) = sequence_dirs(out)
    m = json.loads((seq / "metrics.json").read_text())
    f = read_frames_csv(seq / "frames.csv")
    ts, T = read_tum_strict(seq / "trajectory.txt")
    _, T_gt = read_tum_strict(gt)
    expect = {
        "sequence": seq.name,
        "frames": FRAMES,
        "reselections": int(f["reselected"][1:].sum()),
        "mean_reprojection_px": float(f["reprojection_px"].mean()),
        "mean_features": float(f["features"].mean()),
        **trajectory_metrics(ts, T, T_gt[:FRAMES]),
    }
    faults = {
        "complete",
        "dropped_frames",
        "dropped_timestamps",
        "lost_frames",
        "relocalisations",
        "interrupted_frames",
    }
    assert set(m) == set(expect) | {"fps"} | faults
    assert m["complete"] is True and m["dropped_frames"] == 0 and m["dropped_timestamps"] == []
    assert m["lost_frames"] == f["lost"].sum() == 0 and m["relocalisations"] == m["interrupted_frames"] == 0
    assert 0 < m["fps"] < 1e4
    assert m["frames_with_gt"] == FRAMES
    for k, v in expect.items():
        if isinstance(v, float):
            assert m[k] == pytest.approx(v, rel=1e-4, abs=1e-7), k
        else:
            assert m[k] == v, k


@pytest.mark.equivalence
def test_batch_with_a_broken_sequence_writes_the_healthy_one_and_exits_non_zero(runs):
    """The healthy sequence of a batch of two gets the trajectory it gets alone, within TRAJ (a batch of two runs
    other kernels than a batch of one, on 10 frames: measured 1e-8 m), read back as numbers (not as text: the 9th
    decimal may differ)."""
    proc, out, _ = result(runs, "broken_batch")
    healthy, broken = (
        json.loads((out / name / "metrics.json").read_text()) for name in ("visp_castle_simu", "castle_broken")
    )
    _, alone, _ = result(runs, "castle")
    assert proc.returncode == 1
    assert healthy["complete"] and healthy["frames"] == FRAMES
    t_batch, T_batch = read_tum_strict(out / "visp_castle_simu" / "trajectory.txt")
    t_alone, T_alone = read_tum_strict(alone / "visp_castle_simu" / "trajectory.txt")
    np.testing.assert_array_equal(t_batch, t_alone)  # the input's timestamps, written by the same code
    np.testing.assert_allclose(T_batch, T_alone, rtol=0, atol=TRAJ)
    assert not broken["complete"] and broken["frames"] == 6 and "corrupt colour image" in broken["error"]
    assert len(read_tum_strict(out / "castle_broken" / "trajectory.txt")[0]) == 6
    failed = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "FAILED" in ln]
    assert len(failed) == 1 and "castle_broken after 6 frames" in failed[0] and "Traceback" not in proc.stderr


def test_nan_in_groundtruth_is_a_clear_error_before_tracking(runs):
    proc, out, _ = result(runs, "nan_gt")
    text = (proc.stdout + proc.stderr).strip()
    assert proc.returncode == 2 and "Traceback" not in text, text
    lines = [line for line in text.splitlines() if line.strip()]
    assert len(lines) == 1 and "castle_nan_gt/groundtruth.txt:" in lines[0] and "non-finite value" in lines[0], text
    assert not (out / "castle_nan_gt").exists()
