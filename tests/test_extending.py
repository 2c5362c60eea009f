"""docs/extending.md, run exactly as printed: its fenced blocks that name a path are written as files and its bash
blocks are run in order, in one shell, in an empty folder (the user's own package and config folder, outside
torchtrack), on the tiny synthetic set.

Oracles: the custom weighting defined outside the package trains with torchtrack-train (its weights moved from
their zero initialisation, and the validation numbers of metrics.csv are a replay of the saved best.pt), loads as its
own class, and tracks through the CLI; the custom back end tracks through the CLI and reproduces, frame by frame, the
shipped weighted Horn (``estimator=horn estimator.weighted=true``) that it re-implements."""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from test_train_app import validation_numbers

import torchtrack
from torchtrack.config import CONF_DIR
from torchtrack.estimators.backends import RegistrationBackend
from torchtrack.estimators.horn import HornEstimator
from torchtrack.filter.frame import Observation
from torchtrack.filter.weighting import Variances
from torchtrack.geometry import make_T, so3_exp, transform_points
from torchtrack.learn.checkpoint import load_checkpoint

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
FENCE = re.compile(r"^```(\w*)[ \t]*(\S*)[ \t]*\n(.*?)^```[ \t]*$", re.M | re.S)
SCRIPTS = {"torchtrack": "torchtrack.cli", "torchtrack-train": "torchtrack.learn.train_app"}


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
        "myext/weighting.py", "myext/backend.py", "myconf/estimator/weighted_horn.yaml",
    }  # fmt: skip


def test_custom_weighting_trains_saves_loads_and_tracks(guide, monkeypatch):
    work, _ = guide
    monkeypatch.syspath_prepend(str(work))  # the user's package, as the shell had it
    run = work / "runs" / "train_depth_tim"
    net, meta = load_checkpoint(run / "best.pt")
    assert type(net).__module__ == "myext.weighting" and type(net).__name__ == "DepthTimWeighting"
    assert meta["target"] == "myext.weighting.DepthTimWeighting" and meta["model"]["hidden"] == 16
    assert float(net.net[-1].weight.detach().abs().max()) > 0  # trained: the zero-initialised last layer moved

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


def test_custom_back_end_equals_the_shipped_weighted_horn(guide, monkeypatch):
    """The guide's WeightedHorn is the shipped weighted Horn (``estimator=horn estimator.weighted=true``) written against
    the protocol: frame by frame the same poses (the same operations: to float64 round-off), through reset, set_pose,
    an inactive sequence and a frame with too few points; through the CLI it tracked every frame."""
    work, _ = guide
    (metrics,) = (work / "runs" / "track_horn").glob("*/metrics.json")
    assert json.loads(metrics.read_text())["frames"] == 6
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["estimator=weighted_horn", f"hydra.searchpath=[file://{work}/myconf]"])
    assert cfg.estimator == {"_target_": "myext.backend.WeightedHorn", "var_floor": 1e-12}

    monkeypatch.syspath_prepend(str(work))
    ours = instantiate(cfg.estimator)
    theirs = RegistrationBackend(HornEstimator(), weighted=True)
    g = torch.Generator().manual_seed(0)
    B, N, F = 3, 16, torch.float64
    X = torch.randn(B, N, 3, generator=g, dtype=F) * 0.2
    K = torch.tensor([[500.0, 0, 80], [0, 500.0, 60], [0, 0, 1]], dtype=F).expand(B, 3, 3)
    T_start = make_T(so3_exp(0.1 * torch.randn(B, 3, generator=g, dtype=F)), torch.tensor([0.0, 0.0, 1.5], dtype=F))
    for backend in (ours, theirs):
        backend.start()
        backend.reset(T_start, torch.ones(B, dtype=torch.bool))
    for k in range(4):
        T_true = make_T(so3_exp(0.05 * (k + 1) * torch.ones(B, 3, dtype=F)), torch.tensor([0.01 * k, 0.0, 1.5]).to(F))
        points_d = transform_points(T_true, X) + 1e-3 * torch.randn(B, N, 3, generator=g, dtype=F)
        valid = torch.rand(B, N, generator=g) > 0.2
        valid[0] &= k != 2  # no points: the previous pose is kept
        var = Variances(torch.ones(B, N, dtype=F), 1e-6 * (0.5 + torch.rand(B, N, generator=g, dtype=F)))
        obs = Observation(torch.full((B,), 0.03, dtype=F), X, points_d, torch.zeros(B, N, 2, dtype=F), valid, K,
                          torch.eye(4, dtype=F).expand(B, 4, 4))  # fmt: skip
        active = torch.tensor([True, True, k != 1])
        a, b = ours.step(obs, var, active).T_cam_obj, theirs.step(obs, var, active).T_cam_obj
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
        if k == 2:  # the pose of some sequences moved from outside
            for backend in (ours, theirs):
                backend.set_pose(T_start, torch.tensor([False, True, False]))
