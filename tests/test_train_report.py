"""What torchtrack-train tells the researcher: an empty validation split is an error, each epoch's line puts the model
beside the baselines on the same windows, a best epoch that does not beat them is named, and held-out families are
chosen by pattern."""

import math

import pytest
from hydra import compose, initialize_config_dir
from test_cache import random_observations

from torchtrack.config import CONF_DIR
from torchtrack.data.errors import DataError
from torchtrack.learn.cache import save_observations
from torchtrack.learn.train import epoch_report, worse_than
from torchtrack.learn.train_app import held_out, train_from_config


def learn_config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("learn", overrides=list(overrides))


def test_an_empty_validation_split_is_an_error(tmp_path):
    save_observations(random_observations(T=12), tmp_path / "obs" / "seq.pt")
    cfg = learn_config("~dataset", f"extra_observations=[{tmp_path / 'obs'}]", "train.window=3", "val_fraction=0.2")
    with pytest.raises(DataError, match="no validation sequence: val_fraction=0.2 of 1 sequence"):
        train_from_config(cfg, tmp_path / "run", progress=False)


def test_epoch_report_puts_the_model_beside_the_baselines():
    row = {"epoch": 3, "train_loss": -2.0, "val_loss": -2.3, "val_trans_mm": 0.7, "val_rot_deg": 0.25}
    base = {"paper": {"loss": -2.1, "trans_mm": 0.8, "rot_deg": 0.3}, "fixed": {"loss": -1.6, "trans_mm": 0.9}}
    line = epoch_report(row, 30, base)
    assert line.startswith("epoch 3/30: train loss -2")
    assert "val loss -2.3 (paper -2.1, fixed -1.6)" in line and "drift mm 0.700 (paper 0.800, fixed 0.900)" in line
    assert "deg 0.250 (paper 0.300)" in line
    assert epoch_report({"epoch": 1, "train_loss": 1.0}, 2, base) == "epoch 1/2: train loss 1"


def test_worse_than_names_each_baseline_not_beaten():
    base = {"paper": {"loss": -2.1, "trans_mm": 0.6}, "fixed": {"loss": -1.6, "trans_mm": 0.9}}
    best = {"val_loss": -2.0, "val_trans_mm": 0.7}
    assert worse_than(best, base) == ["loss -2 vs paper -2.1", "drift 0.7 vs paper 0.6"]
    assert worse_than({"val_loss": -3.0, "val_trans_mm": 0.5}, base) == []
    assert worse_than({"val_loss": -3.0, "val_trans_mm": math.nan}, base) == []  # no ground truth: no claim


def test_held_out_families_by_pattern():
    seqs = [random_observations(T=5) for _ in range(3)]
    for s, name in zip(
        seqs, ["scene-medium-kinect-seed0", "near-medium-rig-seed0", "scene-medium-rig-seed0"], strict=True
    ):
        s.sequence = name
    assert [s.sequence for s in held_out(seqs, ["*-rig-*"])] == ["near-medium-rig-seed0", "scene-medium-rig-seed0"]
    assert held_out(seqs, []) == []
    with pytest.raises(DataError, match="no recorded sequence matches"):
        held_out(seqs, ["*-none-*"])


def test_training_replays_the_online_scale_when_asked():
    """train.noise_scale: the loss is the rollout's NLL with the filter's scale (R = k R0, k from the windows' recorded
    start) or without it; the two differ where k is not 1."""
    import torch

    from torchtrack.filter import PaperWeighting
    from torchtrack.filter.fusion import FusionEKF
    from torchtrack.learn.oracle import oracle_windows
    from torchtrack.learn.rollout import nll_loss, rollout
    from torchtrack.learn.train import TrainConfig, window_loss

    win = oracle_windows(B=4, T=3, N=12, seed=5).windows
    win.start_noise = torch.full_like(win.start_noise, 3.0)  # the tracker's scale at the windows' start
    win.start_noise_dof = torch.full_like(win.start_noise_dof, 100.0)
    ekf, w = FusionEKF(jacobian="analytic"), PaperWeighting()
    for on in (True, False):
        cfg = TrainConfig(window=3, loss="nll", noise_scale=on)
        with torch.no_grad():
            loss = window_loss(ekf, w, win, cfg)[0]
            want = nll_loss(rollout(ekf, w, win, gate=cfg.gate, refit=cfg.refit, with_nll=True,
                                    noise_scale=ekf.noise if on else None))  # fmt: skip
        assert float(loss) == float(want)
    with torch.no_grad():
        scaled = window_loss(ekf, w, win, TrainConfig(window=3, loss="nll"))[0]
        plain = window_loss(ekf, w, win, TrainConfig(window=3, loss="nll", noise_scale=False))[0]
    assert abs(float(scaled) - float(plain)) > 0.1
