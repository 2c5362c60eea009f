"""The synthetic training set's photometric variants: named, perturbed, recorded from the perturbed images."""

from __future__ import annotations

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from PIL import Image

from torchtrack.config import CONF_DIR
from torchtrack.learn.cache import load_observations
from torchtrack.learn.dataset import build_synthetic_set, synthetic_variants


def tiny_config(tmp_path, photometric_seeds, *overrides: str):
    """The tiny training set's config, its cache in ``tmp_path`` (the user's TORCHTRACK_CACHE restored after)."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("TORCHTRACK_CACHE", str(tmp_path / "cache"))
        with initialize_config_dir(str(CONF_DIR), version_base="1.3"):
            cfg = compose(
                "learn",
                overrides=["dataset=synthetic_tiny", f"+dataset.photometric_seeds={photometric_seeds}", *overrides],
            )
        OmegaConf.resolve(cfg)
    return cfg


def test_photometric_seeds_are_recorded_from_the_perturbed_images(tmp_path):
    cfg = tiny_config(tmp_path, [0])
    variants = synthetic_variants(cfg.dataset)
    assert all(v.photometric and v.name.endswith("-seed0-photometric") for v in variants)
    paths = build_synthetic_set(cfg, tmp_path / "obs", progress=False)
    obs = load_observations(paths[0])
    assert "photometric" in obs.source  # the recording read the perturbed folder
    plain = sorted((tmp_path / "cache" / "synthetic").glob("synth-scene-*"))[0]
    perturbed = sorted((tmp_path / "cache" / "synthetic" / "perturbed").glob("*photometric*"))[0]
    a = np.asarray(Image.open(sorted((plain / "rgb").iterdir())[1]), dtype=np.float64)
    b = np.asarray(Image.open(sorted((perturbed / "rgb").iterdir())[1]), dtype=np.float64)
    assert a.shape == b.shape and np.abs(a - b).mean() > 2.0  # grey levels: the images did change
    assert cfg.dataset.photometric_seeds == [0]


def test_no_photometric_seeds_keeps_the_plain_names(tmp_path):
    cfg = tiny_config(tmp_path, [])
    assert not any(v.photometric or "photometric" in v.name for v in synthetic_variants(cfg.dataset))
