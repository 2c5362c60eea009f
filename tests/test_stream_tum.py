"""Frames from Python at the CLI's terms: :func:`torchtrack.stream.tum_frames` pairs a TUM-layout folder's colour and
depth as the CLI does, and :class:`torchtrack.stream.RGBDTracker` sets the CLI's thread count.

Oracles: the CLI's own reader and loop (the composed config's ``data`` through :func:`torchtrack.factory.load_sequences`
and :func:`torchtrack.data.iterate_batched`), and a folder written here whose pairs are known by construction.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import iterate_batched
from torchtrack.factory import load_sequences
from torchtrack.stream import RGBDTracker, tum_frames

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "sun3d_fragment2"
DEPTH_SCALE = 1000.0
COLOUR_T = np.arange(6) / 30.0  # six colour frames at 30 Hz
NO_DEPTH = 2  # the third colour frame's depth image is missing from depth.txt
DEPTH_OFFSET = 0.004  # s: each depth image 4 ms after its colour image, within the default max_dt (0.02 s)


def cli_frames(root: Path) -> list[tuple[float, torch.Tensor, torch.Tensor]]:
    """(timestamp, colour (3, H, W), depth (1, H, W)) of every frame as ``torchtrack data=tum data.root=ROOT`` loads
    and iterates them."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["data=tum", f"data.root='{root}'"])
    (seq,) = load_sequences(cfg.data).loaded
    return [(float(f.timestamp[0]), f.rgb[0], f.depth[0]) for f in iterate_batched([seq], prefetch=False)]


def helper_frames(root: Path) -> list[tuple[float, torch.Tensor, torch.Tensor]]:
    """The same from :func:`tum_frames`, colour and depth put back into the CLI's layout."""
    return [(t, c.permute(2, 0, 1), d[None]) for c, d, t in tum_frames(root)]


def assert_same_frames(a, b) -> None:
    assert [t for t, _, _ in a] == [t for t, _, _ in b]
    for (_, ca, da), (_, cb, db) in zip(a, b, strict=True):
        assert torch.equal(ca, cb) and torch.equal(da, db)


@pytest.fixture
def folder(tmp_path) -> Path:
    """A TUM-layout folder of six 32 x 24 frames; depth.txt lists no depth near colour frame NO_DEPTH. Frame k's
    depth is (k + 1) m everywhere, so a depth image read with the wrong colour frame shows."""
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    rgb_rows, depth_rows = [], []
    rng = np.random.default_rng(0)
    for k, t in enumerate(COLOUR_T):
        cv2.imwrite(str(tmp_path / "rgb" / f"{k}.png"), rng.integers(0, 256, (24, 32, 3), dtype=np.uint8))
        rgb_rows.append(f"{t:.6f} rgb/{k}.png")
        if k != NO_DEPTH:
            cv2.imwrite(str(tmp_path / "depth" / f"{k}.png"), np.full((24, 32), (k + 1) * DEPTH_SCALE, np.uint16))
            depth_rows.append(f"{t + DEPTH_OFFSET:.6f} depth/{k}.png")
    (tmp_path / "rgb.txt").write_text("\n".join(rgb_rows) + "\n")
    (tmp_path / "depth.txt").write_text("\n".join(depth_rows) + "\n")
    (tmp_path / "intrinsics.txt").write_text(f"30 30 16 12 {DEPTH_SCALE:g}\n")
    return tmp_path


def test_a_colour_frame_without_depth_is_left_out_and_counted(folder, caplog):
    with caplog.at_level(logging.INFO, logger="torchtrack.data.tum"):
        frames = helper_frames(folder)
    kept = [k for k in range(len(COLOUR_T)) if k != NO_DEPTH]
    assert [t for t, _, _ in frames] == [float(f"{COLOUR_T[k]:.6f}") for k in kept]
    assert [float(d.unique()) for _, _, d in frames] == [float(k + 1) for k in kept]  # each with its own depth
    assert "1 colour frame without depth within 0.02 s left out" in caplog.text
    assert_same_frames(frames, cli_frames(folder))


@pytest.mark.skipif(not SHARED.is_dir(), reason="the shared sequences (../shared/data) are not in this checkout")
def test_the_helper_pairs_a_shared_sequence_as_the_cli_does():
    assert_same_frames(helper_frames(SHARED), cli_frames(SHARED))


def test_the_stream_sets_the_clis_thread_count(folder):
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        RGBDTracker(np.eye(3), announce=False)  # the config's default, threads=1
        assert torch.get_num_threads() == 1
        RGBDTracker(np.eye(3), overrides=["threads=2"], announce=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
