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

from torchtrack.cli import check_overrides
from torchtrack.config import CONF_DIR, TumDataConfig
from torchtrack.learn.dataset import synthetic_variants

# Groups that are wiring, not choices a user makes on the command line (learn's dataset/train, the method's
# per-weighting and per-estimator values, Hydra's own).
INTERNAL = {"dataset", "train", "hydra"}


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


# -- torchtrack-record --help and torchtrack-train --help: each tool's own keys, defaults as composed, examples that
# compose (torchtrack/learn/record_app.py and train_app.py print them; Hydra's template would print the tracker's help).

TOOLS = {  # tool: (module, config name)
    "torchtrack-record": ("torchtrack.learn.record_app", "record"),
    "torchtrack-train": ("torchtrack.learn.train_app", "learn"),
}
PLACEHOLDER = re.compile(r"[A-Z][A-Z_]*")  # DIR, NAME: no default to compare


@pytest.fixture(scope="module", params=sorted(TOOLS))
def tool_help(request) -> tuple[str, str, str]:
    module, config_name = TOOLS[request.param]
    done = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return request.param, config_name, done.stdout


def _composed(config_name: str, overrides: list[str] = ()):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


def _keys(cfg, prefix: str = "") -> set[str]:
    out = set()
    for k in cfg:
        node = cfg._get_node(k)
        out.add(prefix + str(k))
        if hasattr(node, "keys") and not node._is_missing() and not node._is_none():
            out |= _keys(node, f"{prefix}{k}.")
    return out


def _key_lines(text: str) -> list[str]:
    return [ln for title in ("Keys", "train.* keys") if f"== {title}" in text for ln in section(text, title)]


@pytest.mark.slow
def test_tool_help_is_its_own(tool_help):
    tool, _, text = tool_help
    assert text.startswith(f"{tool}: ")
    assert "is powered by Hydra" not in text and "== Configuration groups" not in text  # not the tracker's help
    short = subprocess.run([sys.executable, "-m", TOOLS[tool][0], "-h"], capture_output=True, text=True, timeout=120)
    assert short.returncode == 0 and short.stdout == text


def test_tool_help_names_every_key_the_tool_adds(tool_help):
    """Every key the tool's config adds to torchtrack's (record: out, batch; train: dataset, extra_observations,
    leave_out, ..., and every train.* key) is named."""
    _, config_name, text = tool_help
    added = _keys(_composed(config_name)) - _keys(_composed("config"))
    added = {k for k in added if not k.startswith("dataset.")}  # the set's keys are named by group (dataset.modes, ...)
    assert added, config_name

    def named(k: str) -> bool:  # in full, or (the model's nominal values) by the last part in a list
        last = k.split(".")[-1] if k.startswith("train.model.") else k
        return any(re.search(rf"(?<![\w.]){re.escape(n)}\b", text) for n in (k, last))

    missing = {k for k in added if not named(k)}
    assert not missing
    for key in ("out", "batch") if config_name == "record" else ("extra_observations", "leave_out", "train.epochs"):
        assert re.search(rf"^  \+?{re.escape(key)}=", text, re.M), key  # a line of its own, with its default
    assert "dataset=" in text


def test_tool_help_defaults_are_the_composed_ones(tool_help):
    _, config_name, text = tool_help
    cfg = _composed(config_name)
    stated = re.findall(r"(?<![\w.+~])([a-z_][\w.]*)=([^\s,;)]+)", "\n".join(_key_lines(text)))
    checked = 0
    for key, value in stated:
        if PLACEHOLDER.fullmatch(value) or key.startswith("hydra."):
            continue
        if key == "dataset":
            assert cfg.dataset.name == value
        else:
            actual = _get(cfg, key)
            shown = "null" if actual is None else str(actual).lower() if isinstance(actual, bool) else str(actual)
            assert shown == value, key  # as the command line spells it (Hydra's true/false)
        checked += 1
    assert checked >= (2 if config_name == "record" else 15)


@pytest.mark.slow
def test_tool_help_examples_compose(tool_help):
    tool, config_name, text = tool_help
    examples = [shlex.split(ln.strip())[1:] for ln in section(text, "Examples") if ln.startswith(f"  {tool}")]
    assert len(examples) >= 3
    for overrides in examples:
        assert check_overrides(config_name, overrides) is None, overrides
        cfg = _composed(config_name, overrides)
        for o in overrides:
            key, _, value = o.partition("=")
            if "." in key and not key.startswith(("~", "+")) and not value.startswith("["):
                assert str(_get(cfg, key)) == value, o


@pytest.mark.slow
def test_train_help_states_the_set_sizes():
    """The default set is the 128 sequences the help and the README state; the small example is 2 of them."""
    text = subprocess.run(
        [sys.executable, "-m", "torchtrack.learn.train_app", "--help"], capture_output=True, text=True, timeout=120
    ).stdout
    small = next(shlex.split(ln)[1:] for ln in section(text, "Examples") if "train.epochs=1" in ln)
    assert len(synthetic_variants(_composed("learn").dataset)) == 128 and "128 synthetic sequences" in text
    assert len(synthetic_variants(_composed("learn", small).dataset)) == 2
