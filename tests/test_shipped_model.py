"""The shipped default model: loads by ``weighting=learned``, was trained on synthetic data only, by the documented
recipe (conf/train/default.yaml), is the best epoch of its recorded run, and keeps its recorded validation gain over
eqs. (11)-(14) on held-out synthetic sequences.

Oracle for the weights: the checkpoint records its validation numbers (meta ``history``, ``val_paper``,
``val_fixed``: the innovation NLL per measurement it was selected on). Sequences of the training set's family with a
seed it never saw (seeds 0 and 1 were trained and validated on) are rendered, recorded and replayed here in the
recipe's windows: the shipped model's NLL must beat the paper weighting's and the untrained model's by at least a
third of the recorded validation gain. Weights re-initialised, corrupted, or from another run fail it."""

from __future__ import annotations

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from torchtrack.config import CONF_DIR, load_option
from torchtrack.data import TumSequence
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.filter import WeightingInputs
from torchtrack.filter.cues import CUE_NAMES
from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import (
    DEFAULT_CHECKPOINT,
    build_weighting,
    learned_weighting,
    load_checkpoint,
    weighting_spec,
)
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.record import record_sequences
from torchtrack.learn.rollout import rollout
from torchtrack.learn.train import sequence_windows

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

SHARED = ("visp_castle_simu", "visp_rbt_sequence", "sun3d_fragment1", "sun3d_fragment2", "7scenes_redkitchen")


def test_default_model_loads_without_a_checkpoint_argument():
    model = learned_weighting()
    assert DEFAULT_CHECKPOINT.is_file() and DEFAULT_CHECKPOINT.stat().st_size < 100_000
    assert sum(p.numel() for p in model.parameters()) <= 10_000
    B, N = 2, 50
    g = torch.Generator().manual_seed(0)
    cues = torch.rand(B, N, len(CUE_NAMES), generator=g)
    valid = torch.rand(B, N, generator=g) > 0.2
    depth = 0.5 + 3 * torch.rand(B, N, generator=g)
    points = torch.cat([torch.zeros(B, N, 2), depth[..., None]], -1)
    var = model(WeightingInputs(cues[..., 0], depth, points, valid, torch.full((B,), 525.0), cues=cues))
    assert torch.isfinite(var.var_pix).all() and (var.var_pix > 0).all() and (var.var_xyz > 0).all()


def test_default_model_was_trained_on_synthetic_sequences_only_with_the_documented_recipe():
    _, meta = load_checkpoint(DEFAULT_CHECKPOINT)
    seen = meta["train_sequences"] + meta["val_sequences"]
    assert seen and not any(name in s for s in seen for name in SHARED)
    assert all(s.split("-")[0] in ("scene", "object", "object_bare") for s in seen)  # the synthetic set's names
    trained = yaml.safe_load(meta["config"])["train"]
    recipe = yaml.safe_load((CONF_DIR / "train" / "default.yaml").read_text())
    for key in ("window", "stride", "batch", "epochs", "lr", "loss", "gate", "refit", "seed"):
        assert trained[key] == recipe[key], key
    # the recipe's node (with the defaults it leaves) builds the shipped architecture, as its run's config did
    spec = weighting_spec(build_weighting(recipe["model"]), recipe["model"])
    assert spec.pop("_target_") == "torchtrack.learn.model.LearnedWeighting" and spec == meta["model"]
    run = weighting_spec(build_weighting(trained["model"]), trained["model"])  # its run's node (null: the default)
    assert run.pop("_target_") == meta["target"] and run == meta["model"]


def test_default_model_is_the_best_epoch_of_its_recorded_run():
    """The recorded run: the shipped epoch has the lowest validation loss of the history (the selection rule), and
    that loss (the NLL per measurement, the recipe's loss) beats the recorded baselines on the same windows."""
    _, meta = load_checkpoint(DEFAULT_CHECKPOINT)
    history = meta["history"]
    assert [h["epoch"] for h in history] == list(range(1, len(history) + 1))
    best = min(history, key=lambda h: h["val_loss"])
    assert meta["epoch"] == best["epoch"] and best["val_nll"] == best["val_loss"] == best["select"]
    assert best["val_loss"] < meta["val_paper"]["loss"] < meta["val_fixed"]["loss"]


# Held out: the training set's family (conf/dataset/synthetic.yaml: 640 x 480, Kinect noise, medium speed), seed 2.
HELD_OUT = {
    "scene": SyntheticConfig(width=640, height=480, frames=21, seed=2, mode="scene", noise="kinect"),
    "object": SyntheticConfig(width=640, height=480, frames=21, seed=2, mode="object", noise="kinect",
                              trans_step_m=0.004),
}  # fmt: skip


@pytest.fixture(scope="module")
def held_out(tmp_path_factory):
    """The held-out sequences recorded with the default pipeline (each with its mode's region), as the training set
    was: [(region, SequenceObservations, composed config)]."""
    root = tmp_path_factory.mktemp("held_out")
    out = []
    for region, synth in HELD_OUT.items():
        seq = TumSequence(ensure_sequence(synth, root / "render"))
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("config", overrides=[f"region={region}"])
        (path,) = record_sequences(cfg, [seq], root / "obs", names=[region], progress=False)
        out.append((region, load_observations(path), cfg))
    return out


def nll_per_measurement(weighting, obs, cfg, recipe) -> float:
    """The innovation NLL per used measurement over the recipe's windows (from ground truth, gate and refit)."""
    win = sequence_windows(obs, recipe["window"], recipe["stride"])
    ekf = instantiate(cfg.filter)  # the analytic Jacobian, as trained
    with torch.no_grad():
        out = rollout(ekf, weighting, win, gate=recipe["gate"], refit=recipe["refit"], with_nll=True)
    return float(out.nll.sum() / out.n_used.sum())


def test_default_model_keeps_its_validation_gain_on_held_out_sequences(held_out):
    """Recorded: validation NLL per measurement -2.325 (the shipped epoch) vs -2.062 for eqs. (11)-(14), a gain of
    0.263. Required here: a gain of at least a third of that over the paper weighting and over the untrained model
    (zero last layer: constant nominal variances with the depth prior). Measured (seed 2): scene -1.551 vs paper
    -1.343, untrained -1.302; object -2.659 vs -2.475, -2.453. Weights not loaded give the untrained numbers, which
    fail it (the earlier model of cue version 1 was also checked with re-initialised, permuted-cue and negated
    weights)."""
    model = learned_weighting()
    _, meta = load_checkpoint(DEFAULT_CHECKPOINT)
    seen = meta["train_sequences"] + meta["val_sequences"]
    assert not any("seed2" in s for s in seen), "the held-out seed was trained on"
    recipe = yaml.safe_load(meta["config"])["train"]
    best = min(meta["history"], key=lambda h: h["val_loss"])
    required = (meta["val_paper"]["loss"] - best["val_loss"]) / 3
    assert required > 0.07  # recorded: -2.325 vs -2.062 (retrained on the dense-map default's recordings): 0.088
    untrained = LearnedWeighting(**model.config)
    paper = instantiate(load_option("weighting", "paper"))
    for name, obs, cfg in held_out:
        ours = nll_per_measurement(model, obs, cfg, recipe)
        for base_name, base in (("paper", paper), ("untrained", untrained)):
            theirs = nll_per_measurement(base, obs, cfg, recipe)
            assert ours < theirs - required, f"{name}: shipped {ours:.4f} vs {base_name} {theirs:.4f}"
