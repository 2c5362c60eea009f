"""docs/extending.md, run exactly as printed: its fenced blocks that name a path are written as files and its bash
blocks are run in order, in one shell, in an empty folder (the user's own package and config folder, outside
torchtrack), on the tiny synthetic set.

Oracles: the custom weighting defined outside the package trains with torchtrack-train (its weights moved from
their zero initialisation, and the validation numbers of metrics.csv are a replay of the saved best.pt), loads as its
own class, and tracks through the CLI; the custom back end reproduces, through the CLI, the shipped weighted Horn
(``tracker=horn tracker.weighted=true``) that it re-implements."""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from test_train_app import validation_numbers

import torchtrack
from torchtrack.config import CONF_DIR
from torchtrack.learn.checkpoint import load_checkpoint

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
FENCE = re.compile(r"^```(\w*)[ \t]*(\S*)[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
SCRIPTS = {"torchtrack": "torchtrack.cli", "torchtrack-train": "torchtrack.learn.train_app"}
TINY = ["data.scene.frames=6", "data.scene.width=160", "data.scene.height=120", "plots=false"]


def blocks() -> list[tuple[str, str, str]]:
    """(language, path or "", body) of every fenced block of the guide, in order."""
    return [(m[1], m[2], m[3]) for m in FENCE.finditer(DOC.read_text())]


def environment(work: Path) -> dict[str, str]:
    """The user's shell: this torchtrack importable, its console scripts on PATH (shims running ``python -m`` where
    the package was installed without them), the cache inside ``work``."""
    bin_dir = work / ".bin"
    bin_dir.mkdir()
    for name, module in SCRIPTS.items():
        installed = Path(sys.executable).with_name(name)
        shim = bin_dir / name
        shim.write_text(f'#!/bin/sh\nexec "{installed if installed.is_file() else sys.executable}"' +
                        ("" if installed.is_file() else f" -m {module}") + ' "$@"\n')  # fmt: skip
        shim.chmod(0o755)
    package_root = str(Path(torchtrack.__file__).resolve().parents[1])
    return {
        **os.environ,
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONPATH": os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH")) if p),
        "TORCHTRACK_CACHE": str(work / "cache"),
        "OMP_NUM_THREADS": "1",
    }


@pytest.fixture(scope="module")
def guide(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    work = tmp_path_factory.mktemp("guide")
    env = environment(work)
    script = []
    for lang, path, body in blocks():
        if path:
            (work / path).parent.mkdir(parents=True, exist_ok=True)
            (work / path).write_text(body)
        elif lang == "bash":
            script.append(body)
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", "\n".join(script)], cwd=work, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    return work, env


def test_every_block_is_a_file_or_a_command():
    """Nothing in the guide is left unexercised: a block names the file it is or is a bash command."""
    found = blocks()
    assert found and all(path or lang == "bash" for lang, path, _ in found), [(lang, path) for lang, path, _ in found]
    assert {path for _, path, _ in found if path} == {
        "myext/weighting.py", "myext/backend.py", "myconf/tracker/weighted_horn.yaml",
    }  # fmt: skip


def test_custom_weighting_trains_saves_loads_and_tracks(guide, monkeypatch):
    work, _ = guide
    monkeypatch.syspath_prepend(str(work))  # the user's package, as the shell had it
    run = work / "runs" / "train_depth_tim"
    net, meta = load_checkpoint(run / "best.pt")
    assert type(net).__module__ == "myext.weighting" and type(net).__name__ == "DepthTimWeighting"
    assert meta["target"] == "myext.weighting.DepthTimWeighting" and meta["model"]["hidden"] == 16
    assert float(net.net[-1].weight.abs().max()) > 0  # trained: the zero-initialised last layer moved

    # metrics.csv's validation numbers at the best epoch are the saved module replayed on the validation sequence
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2]
    row = rows[int(meta["epoch"]) - 1]
    (val,) = meta["val_sequences"]
    ours = validation_numbers(net, work / "cache" / "observations" / "synthetic_tiny" / f"{val}.pt",
                              yaml.safe_load(meta["config"]))  # fmt: skip
    for key in ("trans_mm", "rot_deg", "nll"):
        assert float(row[f"val_{key}"]) == pytest.approx(ours[key], rel=1e-9, abs=0), key

    # the CLI's weighting node builds that class from the checkpoint; the tracking run tracked every frame
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["weighting=learned", f"weighting.checkpoint={run / 'best.pt'}"])
    w = instantiate(cfg.weighting)
    assert type(w) is type(net) and all(
        torch.equal(a, b) for a, b in zip(w.parameters(), net.parameters(), strict=True)
    )
    (metrics,) = (work / "runs" / "track_depth_tim").glob("*/metrics.json")
    assert json.loads(metrics.read_text())["frames"] == 6


def test_custom_back_end_equals_the_shipped_weighted_horn(guide):
    """The guide's WeightedHorn is the shipped weighted Horn written against the protocol: the same trajectory
    through the CLI, to float64 round-off (the same operations; 1e-9 m and 1e-9 in the quaternion)."""
    work, env = guide
    ref = work / "runs" / "track_horn_shipped"
    cmd = ["torchtrack", "tracker=horn", "tracker.weighted=true", *TINY, f"hydra.run.dir={ref}"]
    done = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    (ours,) = (work / "runs" / "track_horn").glob("*/trajectory.txt")
    (theirs,) = ref.glob("*/trajectory.txt")
    a, b = np.loadtxt(ours, ndmin=2), np.loadtxt(theirs, ndmin=2)
    assert a.shape == b.shape == (6, 8)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["tracker=weighted_horn", f"hydra.searchpath=[file://{work}/myconf]"])
    assert cfg.tracker == {"_target_": "myext.backend.WeightedHorn", "var_floor": 1e-12}
