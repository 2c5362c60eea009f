"""The shipped default model: loads by ``weighting=learned``, was trained on synthetic data only, and was produced
by the documented recipe (conf/train/default.yaml)."""

from __future__ import annotations

import torch
import yaml

from torchtrack.config import CONF_DIR
from torchtrack.filter import WeightingInputs
from torchtrack.learn.checkpoint import DEFAULT_CHECKPOINT, learned_weighting, load_checkpoint
from torchtrack.learn.cues import CUE_NAMES

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
    for key in ("window", "stride", "batch", "epochs", "lr", "loss", "gate", "refit", "seed", "model"):
        assert trained[key] == recipe[key], key
