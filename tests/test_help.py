"""``torchtrack --help`` (conf/hydra/help/torchtrack.yaml): the tool described, the config groups with exactly the
options conf/ has, every data=tum key, and example commands that compose."""

from __future__ import annotations

import dataclasses
import re
import shlex
import subprocess
import sys

import pytest
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR, TumDataConfig

# Groups that are wiring, not choices a user makes on the command line (learn's dataset/train, the method's
# per-weighting and per-estimator values, Hydra's own).
INTERNAL = {"dataset", "train", "method_tracker", "method_weighting", "hydra"}


@pytest.fixture(scope="module")
def help_text() -> str:
    done = subprocess.run(
        [sys.executable, "-m", "torchtrack.cli", "--help"], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def section(text: str, title: str) -> list[str]:
    """The lines under ``== title... ==`` up to the next blank line."""
    lines = text.splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith(f"== {title}"))
    end = next((i for i in range(start + 1, len(lines)) if not lines[i].strip()), len(lines))
    return lines[start + 1 : end]


def test_help_describes_the_tool_not_hydra(help_text):
    assert help_text.startswith("torchtrack: model-free 3D rigid tracking from RGB-D video")
    assert "is powered by Hydra" not in help_text
    assert "cache_dir:" not in help_text  # the synthetic group's config is no longer dumped


def test_help_lists_every_group_with_exactly_its_options(help_text):
    listed = {}
    for line in section(help_text, "Configuration groups"):
        m = re.match(r"  \+?(\w+)(?: \([^)]*\))?:\s+(.*)", line)  # continuation lines are indented further
        if m:
            listed[m.group(1)] = {part.split()[0] for part in m.group(2).split("|")}
    groups = {d.name for d in CONF_DIR.iterdir() if d.is_dir()} - INTERNAL
    assert set(listed) == groups
    for group, options in listed.items():
        assert options == {f.stem for f in (CONF_DIR / group).glob("*.yaml")}, group


def test_help_names_every_tum_key(help_text):
    keys = {m.group(1) for line in section(help_text, "data=tum keys") if (m := re.match(r"  (\w+) ", line))}
    assert keys == {f.name for f in dataclasses.fields(TumDataConfig)}


def test_help_examples_compose(help_text):
    examples = [ln.strip() for ln in section(help_text, "Examples") if ln.startswith("  torchtrack")]
    assert len(examples) == 3
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for example in examples:
            overrides = shlex.split(example)[1:]
            cfg = compose("config", overrides=overrides, return_hydra_config=True)
            for o in overrides:
                key, _, value = o.lstrip("+").partition("=")
                if "." in key and not value.startswith("["):
                    assert str(_get(cfg, key)) == value, o


def _get(cfg, dotted: str):
    for k in dotted.split("."):
        cfg = cfg[k]
    return cfg
