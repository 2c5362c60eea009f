"""What a new user sees first: the default demo's output (one progress bar, each result line once, log lines not
glued onto the bar) and its folder, named so that a person can tell what it holds."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys

from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data.synthetic import SyntheticConfig, display_name
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.run import run_tracker

SCENE = ["data.scene.frames=6", "data.scene.width=160", "data.scene.height=120"]


def screen(text: str) -> list[str]:
    """The lines a terminal shows for ``text``: a carriage return goes back to the line's start, so of each line
    the last non-empty piece after a '\\r' stays (tqdm redraws its bar that way)."""
    return [next((p for p in reversed(line.split("\r")) if p), "") for line in text.split("\n")]


def test_demo_prints_one_bar_and_one_result_line_into_a_named_folder(tmp_path):
    env = {**os.environ, "TORCHTRACK_CACHE": str(tmp_path / "cache")}
    args = [sys.executable, "-m", "torchtrack.cli", *SCENE, f"hydra.run.dir={tmp_path / 'run'}"]
    done = subprocess.run(args, capture_output=True, env=env, cwd=tmp_path, timeout=300)  # bytes: keep the '\r's
    out, err = done.stdout.decode(), done.stderr.decode()
    assert done.returncode == 0, err
    name = display_name(SyntheticConfig(frames=6, width=160, height=120))
    assert name == "synthetic-scene-6frames-160x120-seed0-kinect-noise"
    assert [p.name for p in (tmp_path / "run").iterdir() if p.is_dir() and not p.name.startswith(".")] == [name]
    both = out + err
    assert len(re.findall(rf"{name}: frames=6 ", both)) == 1, both
    assert sum("6/6 [" in line for line in screen(err)) == 1, err  # the bar's final state, once
    assert len(re.findall(r"fps=", both)) == 1, both


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
