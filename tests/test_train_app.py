"""``torchtrack-train`` end to end, as a user runs it: record the tiny synthetic set, train two epochs, export the best
checkpoint, and track with it through ``torchtrack weighting=learned weighting.checkpoint=...``.

Oracles: the validation numbers of metrics.csv and the baselines stored in the checkpoint equal an evaluation of
the saved checkpoints written here (the recorded validation sequence replayed in windows, pose errors and the NLL
per measurement averaged here); the exported model tracks at least as well as the untrained (frozen) model on the
same sequence, within a measured margin, and the CLI tracks with the checkpoint it is given."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from hydra.utils import instantiate
from omegaconf import OmegaConf
from test_dataset import tiny_config

from torchtrack.config import load_option
from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.learn.dataset import build_synthetic_set
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.rollout import rollout
from torchtrack.learn.train import sequence_windows

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

SEQUENCES = ["object_bare-medium-kinect-seed0", "scene-medium-kinect-seed0"]  # conf/dataset/synthetic_tiny.yaml


def script(name: str, module: str) -> list[str]:
    path = Path(sys.executable).with_name(name)
    return [str(path)] if path.is_file() else [sys.executable, "-m", module]


def run(cmd: list[str], cache: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "TORCHTRACK_CACHE": str(cache)}
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def validation_numbers(weighting, sequence: Path, config: dict) -> dict[str, float]:
    """The recorded ``sequence`` replayed in the run's windows through its filter with ``weighting``: the mean
    translation error (mm) and rotation chord ``2 sin(angle / 2)`` (as degrees) over the frames with ground truth,
    and the innovation NLL per used measurement over all frames — averaged here, in float64."""
    tc = config["train"]
    seq = load_observations(sequence)
    win = sequence_windows(seq, tc["window"], tc["stride"])
    ekf = instantiate(OmegaConf.create(config["filter"]))
    with torch.no_grad():
        out = rollout(ekf, weighting, win, gate=tc["gate"], refit=tc["refit"], with_nll=True, noise_scale=ekf.noise)
    T_est, T_gt, m = out.T_cam_obj, win.T_cam_obj_gt.to(out.T_cam_obj.dtype), win.gt_valid
    trans = (T_est[..., :3, 3] - T_gt[..., :3, 3]).norm(dim=-1)  # || t_est - t_gt || = || t(T_gt^-1 T_est) ||
    R = T_gt[..., :3, :3].transpose(-1, -2) @ T_est[..., :3, :3]
    skew = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    angle = torch.atan2(skew.norm(dim=-1) / 2, (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2)
    chord = 2 * torch.sin(angle / 2)
    return {
        "trans_mm": 1e3 * float(trans[m].mean()),
        "rot_deg": math.degrees(float(chord[m].mean())),
        "nll": float(out.nll.sum() / out.n_used.sum()),
    }


def test_train_export_and_track(tmp_path):
    cache, run_dir, model = tmp_path / "cache", tmp_path / "run", tmp_path / "model.pt"
    run(script("torchtrack-train", "torchtrack.learn.train_app") + [
        "dataset=synthetic_tiny", "train.epochs=2", "train.window=3", "train.stride=1", "val_fraction=0.5",
        f"export={model}", f"hydra.run.dir={run_dir}",
    ], cache, tmp_path)  # fmt: skip
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    assert (run_dir / "loss.png").stat().st_size > 0
    net, meta = load_checkpoint(model)
    assert sorted(meta["train_sequences"] + meta["val_sequences"]) == SEQUENCES
    assert set(meta["train_sequences"]).isdisjoint(meta["val_sequences"]) and len(meta["val_sequences"]) == 1
    config = yaml.safe_load(meta["config"])
    assert config["train"]["loss"] == "nll"  # the recipe's loss: val_loss is the NLL per measurement
    (val,) = [cache / "observations" / "synthetic_tiny" / f"{name}.pt" for name in meta["val_sequences"]]

    # metrics.csv's validation numbers are the evaluation of the saved models: last.pt after epoch 2, best.pt (and
    # the export, a copy of it) at the epoch of lowest validation loss; float64 in other summation orders: 1e-9.
    best_epoch = min(rows, key=lambda r: float(r["val_loss"]))["epoch"]
    last, last_meta = load_checkpoint(run_dir / "last.pt")
    best, best_meta = load_checkpoint(run_dir / "best.pt")
    assert last_meta["epoch"] == 2 and str(best_meta["epoch"]) == best_epoch == str(meta["epoch"])
    assert all(torch.equal(a, b) for a, b in zip(best.state_dict().values(), net.state_dict().values(), strict=True))
    for ckpt, epoch in ((last, 2), (net, int(best_epoch))):
        row = rows[epoch - 1]
        ours = validation_numbers(ckpt, val, config)
        for key in ("trans_mm", "rot_deg", "nll"):
            assert float(row[f"val_{key}"]) == pytest.approx(ours[key], rel=1e-9, abs=0), (epoch, key)
        assert float(row["val_loss"]) == pytest.approx(ours["nll"], rel=1e-9, abs=0)
    # ... and the baselines the app stored beside them are the paper's and the fixed weighting's on the same windows
    for name in ("paper", "fixed"):
        ours = validation_numbers(instantiate(load_option("weighting", name)), val, config)
        for key in ("trans_mm", "rot_deg", "nll"):
            assert meta[f"val_{name}"][key] == pytest.approx(ours[key], rel=1e-9, abs=0), (name, key)

    # the exported model tracks through the CLI; the same run with the frozen (untrained: zero last layer, constant
    # nominal variances) model on the same sequence is the reference
    frozen = save_checkpoint(tmp_path / "frozen.pt", LearnedWeighting(**net.config))
    sweep = tmp_path / "track"
    run(script("torchtrack", "torchtrack.cli") + [
        "-m", "weighting=learned", f"weighting.checkpoint={model},{frozen}", "data.scene.frames=6",
        "data.scene.width=160", "data.scene.height=120", "plots=false", f"hydra.sweep.dir={sweep}",
    ], cache, tmp_path)  # fmt: skip
    (trained_dir,), (frozen_dir,) = [list((sweep / job).glob("*/metrics.json")) for job in ("0", "1")]
    trained_m, frozen_m = (json.loads(p.read_text()) for p in (trained_dir, frozen_dir))
    assert trained_m["frames"] == frozen_m["frames"] == 6
    # at least as good as frozen within 1 % (measured: 4.855 vs 4.863 mm; a checkpoint of random weights: 7.19 mm,
    # the fixed weighting 7.09 mm). Two epochs at lr 1e-3 move every weight by ~2e-3: training cannot buy more here.
    assert trained_m["ate_rmse_m"] <= 1.01 * frozen_m["ate_rmse_m"]
    # the CLI used the checkpoint it was given: the two trajectories differ (a shipped-default fallback would not)
    trajectories = [(d.parent / "trajectory.txt").read_text() for d in (trained_dir, frozen_dir)]
    assert trajectories[0] != trajectories[1]


@pytest.mark.parametrize("scale", ["false", "true"])
def test_replay_of_a_recording_equals_the_tracker(tmp_path, scale):
    """The rollout of a recorded sequence with the recording's weighting reproduces the tracker's poses: replay is
    the tracker's back end (windows from frame 0: the first model's exact pose), with the online noise scale as the
    tracker ran it (on: R = k x the recorded variances, k from the recorded start and the replayed residuals)."""
    cfg = tiny_config(tmp_path, [], f"filter.noise_scale={scale}")
    (path, _) = build_synthetic_set(cfg, tmp_path / "obs", progress=False)
    seq = load_observations(path)
    win = sequence_windows(seq, window=seq.frames - 1, stride=seq.frames)  # one window: all the updates

    ekf = instantiate(cfg.filter)
    calls = iter(range(1, seq.frames))

    def recorded(_inputs):
        t = next(calls)
        return seq.variances(t)

    out = rollout(ekf, recorded, win, gate=cfg.filter.gate, refit=cfg.filter.refit, noise_scale=ekf.noise)
    torch.testing.assert_close(out.T_cam_obj[:, 0], seq.T_cam_obj_est[1:], rtol=0, atol=1e-9)
    moved = bool((seq.noise_scale[1:] != 1).any())
    assert moved == (scale == "true") and bool((seq.noise_dof[1:] > 0).all()) == (scale == "true")


def test_training_on_recorded_caches_alone_composes(tmp_path):
    """``~dataset`` with ``extra_observations``: the config resolves (``observations`` used to interpolate the removed
    group) and only the extra caches are listed."""
    from hydra import compose, initialize_config_dir

    from torchtrack.config import CONF_DIR
    from torchtrack.learn.train_app import observation_files

    (tmp_path / "a.pt").write_bytes(b"")
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("learn", overrides=["~dataset", f"extra_observations=[{tmp_path}]"])
    OmegaConf.to_container(cfg, resolve=True)
    assert observation_files(cfg) == [tmp_path / "a.pt"]
