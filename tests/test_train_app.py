"""``torchtrack-train`` end to end, as a user runs it: record the tiny synthetic set, train two epochs, export the best
checkpoint, and track with it through ``torchtrack weighting=learned weighting.checkpoint=...``."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate
from test_dataset import tiny_config

from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import load_checkpoint
from torchtrack.learn.dataset import build_synthetic_set
from torchtrack.learn.rollout import rollout
from torchtrack.learn.train import sequence_windows


def script(name: str, module: str) -> list[str]:
    path = Path(sys.executable).with_name(name)
    return [str(path)] if path.is_file() else [sys.executable, "-m", module]


def run(cmd: list[str], cache: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "TORCHTRACK_CACHE": str(cache)}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def test_train_export_and_track(tmp_path):
    cache, run_dir, model = tmp_path / "cache", tmp_path / "run", tmp_path / "model.pt"
    run(script("torchtrack-train", "torchtrack.learn.train_app") + [
        "dataset=synthetic_tiny", "train.epochs=2", "train.window=3", "train.stride=1", "val_fraction=0.5",
        f"export={model}", f"hydra.run.dir={run_dir}",
    ], cache, tmp_path)  # fmt: skip
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    assert all(float(r["val_trans_mm"]) >= 0 for r in rows)
    assert (run_dir / "loss.png").stat().st_size > 0
    net, meta = load_checkpoint(model)
    assert sorted(meta["train_sequences"] + meta["val_sequences"]) == [
        "object_bare-medium-kinect-seed0", "scene-medium-kinect-seed0"
    ]  # fmt: skip
    assert set(meta["train_sequences"]).isdisjoint(meta["val_sequences"])
    # the exported model tracks through the CLI
    track_dir = tmp_path / "track"
    run(script("torchtrack", "torchtrack.cli") + [
        "weighting=learned", f"weighting.checkpoint={model}", "data.scene.frames=6", "data.scene.width=160",
        "data.scene.height=120", "plots=false", f"hydra.run.dir={track_dir}",
    ], cache, tmp_path)  # fmt: skip
    (metrics,) = [json.loads(p.read_text()) for p in track_dir.glob("*/metrics.json")]
    assert metrics["frames"] == 6 and metrics["ate_rmse_m"] < 0.05


def test_replay_of_a_recording_equals_the_tracker(tmp_path):
    """The rollout of a recorded sequence with the recording's weighting reproduces the tracker's poses: replay is
    the tracker's back end (windows from frame 0: the first model's exact pose)."""
    cfg = tiny_config(tmp_path, [])
    (path, _) = build_synthetic_set(cfg, tmp_path / "obs", progress=False)
    seq = load_observations(path)
    win = sequence_windows(seq, window=seq.frames - 1, stride=seq.frames)  # one window: all the updates

    ekf = instantiate(cfg.filter)
    calls = iter(range(1, seq.frames))

    def recorded(_inputs):
        t = next(calls)
        return seq.variances(t)

    out = rollout(ekf, recorded, win, gate=cfg.tracker.gate, refit=cfg.tracker.refit)
    torch.testing.assert_close(out.T_cam_obj[:, 0], seq.T_cam_obj_est[1:], rtol=0, atol=1e-9)
