"""Helpers that the experiment scripts share: sequence folders, the CLI's config for one, runs of torchtrack and of a
peer (cached), the trajectory check, the best peer, the results section of a Markdown file and the git state.

The scripts (``evaluate.py``, ``eval_weighting.py``, ``map_quality.py``, ``object_case.py``) import this module; no
script imports another script.
"""

from __future__ import annotations

import hashlib
import json
import logging
import re
import subprocess
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

from torchtrack.config import CONF_DIR
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import read_tum_trajectory, write_tum_trajectory
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.io import write_atomic, write_json
from torchtrack.metrics import trajectory_metrics
from torchtrack.run import run_tracker

log = logging.getLogger("evaluate")
REPO = Path(__file__).resolve().parents[2]
CONF = CONF_DIR

# ----------------------------------------------------------------------------------------------- inputs


def split_argv(argv: list[str]) -> tuple[list[str], list[str]]:
    """Hydra overrides (``key=value`` tokens not starting with '-') apart from this script's options."""
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    return [a for a in argv if a not in overrides], overrides


def is_sequence(path: Path) -> bool:
    return (path / "rgb.txt").is_file() and (path / "depth.txt").is_file()


def n_listed(path: Path) -> int:
    return sum(1 for line in open(path / "rgb.txt") if line.strip() and not line.startswith("#"))


def find_sequences(roots: list[Path]) -> list[Path]:
    """Sequence folders: each root itself when it is one, else its sub-folders that are; shortest first."""
    found = []
    for root in roots:
        if not root.is_dir():
            raise SystemExit(f"evaluate: {root}: not a folder")
        subs = [root] if is_sequence(root) else sorted(p for p in root.iterdir() if p.is_dir() and is_sequence(p))
        if not subs:
            raise SystemExit(f"evaluate: {root}: no sequence folder (with rgb.txt and depth.txt) in it")
        found += subs
    return sorted(dict.fromkeys(p.resolve() for p in found), key=lambda p: (n_listed(p), p.name))


def compose_config(root: Path, max_frames: int | None, overrides: list[str]) -> DictConfig:
    """The CLI's configuration for one sequence: ``data=tum data.root=ROOT`` plus the user's overrides."""
    base = ["data=tum", f"data.root='{root}'"]
    if max_frames is not None:
        base.append(f"data.max_frames={max_frames}")
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF), job_name="evaluate"):
        return compose("config", overrides=base + overrides)


# ----------------------------------------------------------------------------------------------- ours and the peers


def run_ours(cfg: DictConfig, out: Path, plots: bool) -> dict:
    """torchtrack on the config's (single) sequence; its run folder goes to ``out/<sequence>/``."""
    (seq,) = build_sequences(cfg.data)
    tracker = build_tracker(cfg)
    (metrics,) = run_tracker(tracker, [seq], out, plots=plots)
    (out / seq.name / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    return metrics


def sha16(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def peer_key(seq: TumSequence, peer) -> dict:
    """What a peer's result depends on: the frames, the camera and the peer's version (library and code)."""
    frames = zip(seq.timestamps, seq.rgb_paths, seq.depth_paths, strict=True)
    return {
        "root": str(seq.root.resolve()),
        "frames": len(seq),
        "frames_sha": sha16("\n".join(f"{t:.6f} {r.name} {d.name}" for t, r, d in frames)),
        "K": seq.K.tolist(),
        "depth_scale": seq.depth_scale,
        "peer": peer.name,
        "version": peer.version,
    }


def run_peer(seq: TumSequence, peer, out: Path) -> dict:
    """``peer`` on ``seq``, cached in ``out/<peer>/<sequence>/`` (metrics.json holds the cache key)."""
    folder, key = out / peer.name / seq.name, peer_key(seq, peer)
    cached = folder / "metrics.json"
    if cached.is_file() and (folder / "trajectory.txt").is_file():
        metrics = json.loads(cached.read_text())
        if metrics.get("cache_key") == key:
            log.info("%s: %s from cache %s", seq.name, peer.name, folder)
            return {**metrics, "cached": True}
    T_world_cam, fps = peer(seq, progress=log.isEnabledFor(logging.INFO))
    write_atomic(folder / "trajectory.txt", lambda tmp: write_tum_trajectory(tmp, seq.timestamps, T_world_cam))
    metrics = {"sequence": seq.name, "peer": peer.name, "frames": len(seq), "fps": fps}
    metrics.update(trajectory_metrics(seq.timestamps, T_world_cam, seq.groundtruth, seq.gt_valid))
    write_json(cached, {**metrics, "cache_key": key})  # written last: the cache entry is complete
    return {**metrics, "cached": False}


def check_trajectory(folder: Path, seq: TumSequence, metrics: dict) -> None:
    """The written trajectory re-scores to the reported ATE (guards the table against a stale or partial folder)."""
    traj = read_tum_trajectory(folder / "trajectory.txt")
    n = len(traj.timestamps)
    ate = trajectory_metrics(traj.timestamps, traj.T_world_cam, seq.groundtruth[:n], seq.gt_valid[:n])["ate_rmse_m"]
    if n != len(seq) or not np.isclose(ate or 0.0, metrics.get("ate_rmse_m") or 0.0, rtol=1e-4, atol=1e-7):
        raise RuntimeError(f"{folder}: trajectory.txt ({n} poses, ATE {ate}) disagrees with metrics.json {metrics}")


def best_peer(peers: dict[str, dict], key: str = "ate_rmse_m") -> str | None:
    """The peer with the smallest ``key`` (None when no peer has it)."""
    scored = {n: m[key] for n, m in peers.items() if m and m.get(key) is not None}
    return min(scored, key=scored.get) if scored else None


# ----------------------------------------------------------------------------------------------- outputs


def replace_section(text: str, heading: str, body: str) -> str:
    """``text`` with the section that starts at the line ``heading`` (up to the next heading of the same or a
    higher level) replaced by ``heading`` + ``body``; appended at the end when there is none."""
    level = len(heading) - len(heading.lstrip("#"))
    lines = text.splitlines(keepends=True)
    section = [f"{heading}\n\n", body.rstrip("\n") + "\n"]
    start = next((i for i, line in enumerate(lines) if line.rstrip() == heading), None)
    if start is None:
        sep = "" if not text or text.endswith("\n\n") else ("\n" if text.endswith("\n") else "\n\n")
        return text + sep + "".join(section)
    stop = re.compile(rf"^#{{1,{level}}}\s")
    end = next((i for i in range(start + 1, len(lines)) if stop.match(lines[i])), len(lines))
    return "".join(lines[:start] + section + (["\n"] if end < len(lines) else []) + lines[end:])


def git_describe() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "-uno"], cwd=REPO, capture_output=True, text=True
        ).stdout
        return sha.strip() + ("+dirty" if dirty.strip() else "")
    except OSError:
        return "unknown"
