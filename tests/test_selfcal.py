"""Calibrating the learned weighting on the user's own unlabelled sequences: ``torchtrack-record`` then
``torchtrack-train`` on folders without groundtruth.txt (the innovation NLL needs no ground truth).

Three small synthetic sequences (12 frames, 160 x 120, seeds 3-5) with their groundtruth.txt deleted are recorded
through the CLI; one (seed 5) is left out of training and validation. Oracles: the windows of an unlabelled
recording start from the tracker's recorded estimate (or the exact model pose where a model was selected), and a
labelled one's are unchanged; metrics.csv reports the held-out NLL and no pose error; the NLL-trained model's NLL
per measurement on the left-out sequence beats the untrained model's (constant nominal variances) by a margin that
a run with training disabled (lr 1e-9) does not reach; the supervised loss refuses unlabelled sets in one line.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from torchtrack.config import CONF_DIR
from torchtrack.data.errors import DataError
from torchtrack.data.synthetic import main as synth
from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import load_checkpoint
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.rollout import nll_loss, rollout
from torchtrack.learn.train import sequence_windows
from torchtrack.learn.train_app import train_from_config

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

SEEDS = (3, 4, 5)
HELD_OUT = "seq5"
TRAIN = ["train.epochs=4", "train.window=3", "train.stride=1", "train.batch=4", "train.lr=1e-2", "val_fraction=0.5",
         "train.model.mode=absolute", "train.noise_scale=false"]  # fmt: skip
# Calibrating the absolute level to one sensor (absolute mode, trained without the online scale, which would set the
# level; the shipped recipe's normalised mode leaves the level to the scale and gains 0.057 here: -1.285 vs -1.228). Held-out NLL gain (nats per measurement) the
# calibration must reach. Measured on seq5: untrained -1.228, trained 4 epochs (best: epoch 3) -1.626, a gain of 0.40
# (10 epochs: 0.47); training disabled (lr 1e-9): 8e-9.
MARGIN = 0.2


def script(name: str, module: str) -> list[str]:
    path = Path(sys.executable).with_name(name)
    return [str(path)] if path.is_file() else [sys.executable, "-m", module]


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=300, env={**os.environ})
    assert out.returncode == 0, out.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """The cache folder torchtrack-record wrote for three unlabelled sequences."""
    root = tmp_path_factory.mktemp("selfcal")
    folders = []
    for seed in SEEDS:
        folder = root / f"seq{seed}"
        synth(["--out", str(folder), "--frames", "12", "--width", "160", "--height", "120", "--seed", str(seed)])
        (folder / "groundtruth.txt").unlink()  # the user's own footage: no ground truth
        folders.append(str(folder))
    run(script("torchtrack-record", "torchtrack.learn.record_app") + [
        "data=tum", f"data.root=[{','.join(folders)}]", f"out={root / 'obs'}", "threads=1",
    ], root)  # fmt: skip
    return root / "obs"


@pytest.fixture(scope="module")
def trained(recorded) -> Path:
    """The run folder of torchtrack-train on the unlabelled caches, the held-out sequence left out."""
    run_dir = recorded.parent / "run"
    run(script("torchtrack-train", "torchtrack.learn.train_app") + [
        "~dataset", f"extra_observations=[{recorded}]", f"leave_out=[{HELD_OUT}]", *TRAIN, f"hydra.run.dir={run_dir}",
    ], recorded.parent)  # fmt: skip
    return run_dir


def held_out_nll(weighting, config: dict, cache: Path) -> float:
    """NLL per used measurement of the held-out sequence, replayed in the run's windows through its filter."""
    tc = config["train"]
    seq = load_observations(cache / f"{HELD_OUT}.pt")
    win = sequence_windows(seq, tc["window"], tc["stride"], need_ground_truth=False)
    ekf = instantiate(OmegaConf.create(config["filter"]))
    with torch.no_grad():
        return float(nll_loss(rollout(ekf, weighting, win, gate=tc["gate"], refit=tc["refit"], with_nll=True)))


def composed(overrides: list[str]):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("learn", overrides=overrides)


def test_unlabelled_windows_start_from_the_recorded_estimate(recorded):
    """Without ground truth a window starts at the tracker's estimate of its first frame (the exact model pose
    where a model was selected there) and no frame counts for a pose error; the supervised windows are none. With
    ground truth the windows are the same whether or not the loss needs it (the shipped recipe is unchanged)."""
    seq = load_observations(recorded / "seq3.pt")
    assert not bool(seq.T_cam_obj_gt_valid.any())
    assert sequence_windows(seq, 3, 1) is None
    win = sequence_windows(seq, 3, 1, need_ground_truth=False)
    starts = torch.arange(seq.frames - 3)
    assert win.dt.shape == (3, len(starts)) and not bool(win.gt_valid.any())
    expected = torch.where(seq.reselected[starts, None, None], seq.model_T_cam_obj[starts], seq.T_cam_obj_est[starts])
    assert bool(seq.reselected[1:].any()) and bool((~seq.reselected).any())  # both kinds of start are exercised
    torch.testing.assert_close(win.start_T_cam_obj, expected, rtol=0, atol=0)

    gt = seq.T_cam_obj_est.clone()
    gt[:, :3, 3] += 0.01  # a stand-in ground truth, distinguishable from the estimate
    labelled = dataclasses.replace(seq, T_cam_obj_gt=gt, T_cam_obj_gt_valid=torch.ones_like(seq.gt_valid))
    a, b = sequence_windows(labelled, 3, 1), sequence_windows(labelled, 3, 1, need_ground_truth=False)
    for f in dataclasses.fields(a):
        torch.testing.assert_close(getattr(a, f.name), getattr(b, f.name), rtol=0, atol=0)
    torch.testing.assert_close(a.start_T_cam_obj, torch.where(seq.reselected[starts, None, None],
                                                              seq.model_T_cam_obj[starts], gt[starts]))  # fmt: skip


def test_calibration_on_unlabelled_sequences_beats_the_untrained_model(recorded, trained):
    """The CLI trains on the two unlabelled sequences, reports the held-out (validation) NLL and no pose error, and
    its best model's NLL on the sequence it never saw is MARGIN below the untrained model's."""
    rows = list(csv.DictReader((trained / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4]
    for r in rows:
        assert math.isfinite(float(r["val_nll"])) and float(r["val_loss"]) == float(r["val_nll"])
        assert math.isnan(float(r["val_trans_mm"])) and math.isnan(float(r["val_rot_deg"]))  # no ground truth
    net, meta = load_checkpoint(trained / "best.pt")
    assert sorted(meta["train_sequences"] + meta["val_sequences"]) == ["seq3", "seq4"]
    assert len(meta["val_sequences"]) == 1
    config = yaml.safe_load(meta["config"])
    assert config["train"]["loss"] == "nll"
    learned = held_out_nll(net, config, recorded)
    untrained = held_out_nll(LearnedWeighting(**net.config), config, recorded)
    assert learned < untrained - MARGIN, (learned, untrained)


def test_the_oracle_fails_without_training(recorded, tmp_path):
    """The same run with training disabled (lr 1e-9: the weights move by ~1e-8) does not reach MARGIN: the gain of
    the test above comes from the training."""
    cfg = composed(["~dataset", f"extra_observations=[{recorded}]", f"leave_out=[{HELD_OUT}]", *TRAIN,
                    "train.lr=1e-9"])  # fmt: skip
    train_from_config(cfg, tmp_path, progress=False)
    net, meta = load_checkpoint(tmp_path / "best.pt")
    config = yaml.safe_load(meta["config"])
    learned = held_out_nll(net, config, recorded)
    untrained = held_out_nll(LearnedWeighting(**net.config), config, recorded)
    assert not learned < untrained - MARGIN, (learned, untrained)


def test_supervised_loss_on_unlabelled_sequences_says_it_needs_ground_truth(recorded, tmp_path):
    cfg = composed(["~dataset", f"extra_observations=[{recorded}]", *TRAIN, "train.loss=supervised"])
    with pytest.raises(DataError, match=r"train.loss=supervised needs ground truth .* train.loss=nll needs none"):
        train_from_config(cfg, tmp_path, progress=False)
