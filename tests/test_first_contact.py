"""What a new user sees first: the default demo's output (one progress bar, each result line once, log lines not
glued onto the bar, one name for the sequence in the log and on disk), a first-run build of the compiled operators
announced before the bar and left out of fps, and one fps for a lockstep batch."""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time

import pytest
from hydra import compose, initialize_config_dir
from reference import requires_ops

from torchtrack import ops
from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence
from torchtrack.data.synthetic import SyntheticConfig, display_name
from torchtrack.factory import build_sequences, build_tracker, warm_up
from torchtrack.run import run_tracker

pytestmark = pytest.mark.slow  # the demo and the operators' build announcement, end to end

SCENE = ["data.scene.frames=6", "data.scene.width=160", "data.scene.height=120"]


def screen(text: str) -> list[str]:
    """The lines a terminal shows for ``text``: a carriage return goes back to the line's start, so of each line
    the last non-empty piece after a '\\r' stays (tqdm redraws its bar that way)."""
    return [next((p for p in reversed(line.split("\r")) if p), "") for line in text.split("\n")]


@pytest.mark.slow
def test_demo_prints_one_bar_and_one_result_line_into_a_named_folder(tmp_path):
    env = dict(os.environ)  # the compiled operators' build cache shared: a first build is tested below, in-process
    args = [
        sys.executable,
        "-m",
        "torchtrack.cli",
        *SCENE,
        f"data.cache_dir={tmp_path / 'cache'}",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]
    done = subprocess.run(args, capture_output=True, env=env, cwd=tmp_path, timeout=300)  # bytes: keep the '\r's
    out, err = done.stdout.decode(), done.stderr.decode()
    assert done.returncode == 0, err
    name = display_name(SyntheticConfig(frames=6, width=160, height=120))
    assert name == "synthetic-scene-6frames-160x120-seed0-kinect-noise"
    assert [p.name for p in (tmp_path / "run").iterdir() if p.is_dir() and not p.name.startswith(".")] == [name]
    both = out + err
    assert len(re.findall(rf"{name}: frames=6 ", both)) == 1, both
    named = re.findall(r"\] - (\S+): \d+ frames", both)  # the load line: the name the run folder has
    assert named == [name] and not re.search(r"\] - synth-scene-", both), both  # not the cache folder's name
    (bar,) = [line for line in screen(err) if "6/6 [" in line]  # the bar's final state, once
    (result,) = re.findall(rf"{name}: frames=6 +fps=(\S+) ", both)
    metrics = json.loads((tmp_path / "run" / name / "metrics.json").read_text())
    assert re.findall(r"fps=(\S+)\]", bar) == [result] == [f"{metrics['fps']:.4g}"], (bar, result)  # one number


class LoggingTracker:
    """The real tracker, logging a warning mid-sequence (as the EKF does when it adds jitter)."""

    def __init__(self, tracker):
        self.tracker, self.frames = tracker, 0

    def step(self, frame):
        self.frames += 1
        if self.frames == 3:
            logging.getLogger("torchtrack.test").warning("a warning while tracking")
        return self.tracker.step(frame)


def test_log_lines_are_not_glued_onto_the_progress_bar(tmp_path, capsys):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[*SCENE, f"data.cache_dir={tmp_path / 'cache'}", "plots=false"])
    sequences, tracker = build_sequences(cfg.data), build_tracker(cfg)
    handler = logging.StreamHandler(sys.stderr)  # as Hydra's console handler: a stream handler on the root logger
    handler.setFormatter(logging.Formatter("[LOG] %(message)s"))
    logging.getLogger().addHandler(handler)
    try:
        capsys.readouterr()
        run_tracker(LoggingTracker(tracker), sequences, tmp_path / "out", plots=False)
    finally:
        logging.getLogger().removeHandler(handler)
    err = capsys.readouterr().err
    pieces = re.split(r"[\r\n]", err)
    assert "[LOG] a warning while tracking" in pieces, err  # a line of its own, not the tail of a bar
    assert sum("6/6 [" in line for line in screen(err)) == 1, err


def _config(tmp_path):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=[*SCENE, f"data.cache_dir={tmp_path / 'cache'}", "plots=false"])


BUILD_S = 3.0  # a stand-in first build: long next to the ~1 s the 6 tiny frames take


@requires_ops
def test_a_first_build_is_announced_before_the_bar_and_not_timed(tmp_path, capsys, monkeypatch):
    """A first build (stood in for by a sleep: the real one is loaded) runs when the tracker is made, says so on one
    line before the progress bar, and is not in fps: 6 frames at the reported fps take less than the build."""
    monkeypatch.setattr(ops, "_state", {})  # not loaded yet, as in a fresh process
    monkeypatch.setattr(ops, "loaded", lambda: False)
    monkeypatch.setattr(ops, "_finished", lambda folder, library: False)
    monkeypatch.setattr(ops, "_load", lambda: time.sleep(BUILD_S) or BUILD_S)
    cfg = _config(tmp_path)
    sequences = build_sequences(cfg.data)
    capsys.readouterr()
    tracker = build_tracker(cfg)
    warm_up("cpu")  # as the command line does
    (metrics,) = run_tracker(tracker, sequences, tmp_path / "out", plots=False)
    err = capsys.readouterr().err
    line = "torchtrack: building the compiled LK, SIM and dense-map operators (first run only)... done in 3 s\n"
    assert err.startswith(line) and err.count("building") == 1 and "tracking:" in err[len(line) :], err
    assert metrics["frames"] == 6 and metrics["frames"] / metrics["fps"] < BUILD_S


def test_a_lockstep_batch_reports_one_fps(tmp_path):
    cfg = _config(tmp_path)
    (seq,) = build_sequences(cfg.data)
    copies = [TumSequence(shutil.copytree(seq.root, tmp_path / name)) for name in ("a", "b")]
    results = run_tracker(build_tracker(cfg), copies, tmp_path / "out", plots=True)  # plots: the first writes longer
    written = [json.loads((tmp_path / "out" / n / "metrics.json").read_text())["fps"] for n in ("a", "b")]
    assert results[0]["fps"] == results[1]["fps"] == written[0] == written[1] > 0
