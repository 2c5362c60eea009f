"""The object case: a small textured object on an empty (or far) background, ours against the peers.

Builds deterministic synthetic RGB-D sequences of a small object (``torchtrack.data.synthetic``, ``object="small"``:
an ~18 cm textured box with a sphere and a cylinder, 0.55 m from a static camera, 6-9 % of the image) with exact
ground truth in TUM layout (``groundtruth.txt`` is the camera in the object's frame, so a camera trajectory from any
tracker is comparable), in a few variants, then runs torchtrack in one or more configurations (``--ours``:
label=overrides; the default compares the scene region, i.e. the plain default, with ``region=object``, what a user
runs for an object) and the peers of :mod:`peers` on each, and prints one table of ATE / RPE (evo's, as
:mod:`evaluate`), the best peer and ours against it, plus our mean feature count and re-selections.

    python experiments/eval/object_case.py                                   # every case, the default configurations
    python experiments/eval/object_case.py --cases slow,fast --peers o3d_color,cv2_rgbd
    python experiments/eval/object_case.py --ours default= object=region=object "noedge=region=object reselect.edge_step=null"
    python experiments/eval/object_case.py --roots ../shared/data/visp_castle_simu       # any TUM folder too

Sequences are cached under ``--cache`` (default ``$TORCHTRACK_CACHE/object_case``, else
``~/.cache/torchtrack/object_case``), one folder per case, re-rendered when its configuration changes. Runs go to
``OUT/ours/<label>/<sequence>/`` and ``OUT/peers/<peer>/<sequence>/`` (peers cached as in :mod:`evaluate`); the
table to ``OUT/object_case.md`` and ``OUT/object_case.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import torch
from common import best_peer, check_trajectory, compose_config, git_describe, run_ours, run_peer

from torchtrack.data.synthetic import SyntheticConfig, render_sequence
from torchtrack.data.tum import TumSequence
from torchtrack.factory import build_sequences
from torchtrack.io import write_json, write_text

log = logging.getLogger("object_case")

REPO = Path(__file__).resolve().parents[2]
FRAMES = 60
# The cases: a small object (object="small") on an empty background unless said otherwise; Kinect-like noise
# (depth noise, quantisation, holes at the silhouette, colour noise) unless "clean".
CASES: dict[str, dict] = {
    "slow": dict(trans_step_m=0.003, rot_step_deg=1.0),
    "clean": dict(trans_step_m=0.003, rot_step_deg=1.0, noise="none"),
    "fast": dict(trans_step_m=0.005, rot_step_deg=3.0),
    "rotation": dict(trans_step_m=0.0005, rot_step_deg=3.0),
    "far_background": dict(trans_step_m=0.003, rot_step_deg=1.0, background=True),
}
OURS = {"default": "", "object": "region=object"}
PEERS_DEFAULT = "o3d_color,o3d_hybrid,o3d_t_hybrid,o3d_t_p2plane,o3d_f2m,cv2_rgbd"


def case_config(name: str, frames: int = FRAMES, seed: int = 0) -> SyntheticConfig:
    """The synthetic configuration of case ``name`` (:data:`CASES`)."""
    kw = dict(mode="object", object="small", background=False, noise="kinect", frames=frames, seed=seed)
    return SyntheticConfig(**(kw | CASES[name]))


def build_case(name: str, cache: Path, frames: int = FRAMES, seed: int = 0) -> Path:
    """The TUM folder ``cache/object_<name>`` of case ``name``, rendered unless a complete one of the same config
    (``config.json`` digest) is there."""
    cfg, folder = case_config(name, frames, seed), cache / f"object_{name}"
    meta = folder / "config.json"
    if (folder / "SOURCE.txt").is_file() and meta.is_file() and json.loads(meta.read_text())["digest"] == cfg.digest():
        return folder
    return render_sequence(cfg, folder, overwrite=True, progress=True)


def object_fraction(folder: Path) -> float:
    """Mean fraction of the image with depth over the sequence's frames (every 10th)."""
    seq = TumSequence(folder)
    fr = [float((seq[i].depth > 0).float().mean()) for i in range(0, len(seq), 10)]
    return sum(fr) / len(fr)


def peer_folder(root: Path, out: Path) -> Path:
    """Where the peers' results on ``root`` are cached: per rendered configuration for a synthetic case (the peers'
    cache key names the frames, not their content), else ``out/peers``."""
    meta = root / "config.json"
    return out / "peers" / (json.loads(meta.read_text())["digest"] if meta.is_file() else "")


def run_row(root: Path, ours: dict[str, list[str]], peers: list[str], out: Path) -> dict:
    """One row: every configuration of ours and every peer on ``root``."""
    from peers import PEERS

    row: dict = {"sequence": root.name, "root": str(root), "ours": {}, "peers": {}}
    for label, overrides in ours.items():
        cfg = compose_config(root, None, overrides)
        (seq,) = build_sequences(cfg.data)
        folder = out / "ours" / label
        m = run_ours(cfg, folder, plots=False)
        if m.get("complete", True):
            check_trajectory(folder / seq.name, seq, m)
        else:  # e.g. the object left the view: a cell with the reason, not a lost table
            m = {**m, "ate_rmse_m": None}
        row["ours"][label] = m
    row["frames"], row["depth_fraction"] = len(seq), object_fraction(root)
    for name in peers:
        try:
            row["peers"][name] = run_peer(seq, PEERS[name], peer_folder(root, out))
        except Exception as e:  # a failing peer is a cell
            log.exception("%s: peer %s failed", seq.name, name)
            row["peers"][name] = {"error": f"{type(e).__name__}: {e}".splitlines()[0]}
    row["best"] = best_peer(row["peers"])
    return row


def _cell(m: dict | None) -> str:
    if not m or m.get("ate_rmse_m") is None:
        return "–" if not m else ("(incomplete)" if m.get("complete") is False else f"({m.get('error', 'no ATE')})")
    return f"{m['ate_rmse_m'] * 1e3:.1f} / {m['rpe_trans_m'] * 1e3:.2f}"


def table(rows: list[dict], ours: list[str], peers: list[str]) -> str:
    """Markdown: ATE mm / RPE mm per configuration and peer; features and re-selections of ours; ratios."""
    head = ["sequence", "frames", "depth px"] + [f"ours {o}" for o in ours] + [f"feat. / re-sel. {o}" for o in ours]
    head += peers + ["best peer", *[f"{o} / best" for o in ours]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        best = r["peers"].get(r.get("best") or "", {})
        cells = [r["sequence"], str(r["frames"]), f"{100 * r['depth_fraction']:.1f} %"]
        cells += [_cell(r["ours"].get(o)) for o in ours]
        cells += [f"{r['ours'][o].get('mean_features') or 0:.0f} / {r['ours'][o].get('reselections', 0)}" for o in ours]
        cells += [_cell(r["peers"].get(p)) for p in peers]
        cells.append(r.get("best") or "–")
        for o in ours:
            a, b = r["ours"][o].get("ate_rmse_m"), best.get("ate_rmse_m")
            cells.append(f"{a / b:.2f}" if a is not None and b else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def default_cache() -> Path:
    root = os.environ.get("TORCHTRACK_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "torchtrack") / "object_case"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)} ('' none)")
    ap.add_argument("--roots", type=Path, nargs="*", default=[], help="TUM folders evaluated besides the cases")
    ap.add_argument("--frames", type=int, default=FRAMES, help="frames per synthetic case")
    ap.add_argument("--seed", type=int, default=0, help="seed of the synthetic cases (scene, motion, noise)")
    ap.add_argument("--ours", nargs="+", default=None, metavar="LABEL=OVERRIDES",
                    help="our configurations, each 'label=space-separated Hydra overrides' (None: "
                    + ", ".join(f"'{k}={v}'" for k, v in OURS.items()) + ")")  # fmt: skip
    ap.add_argument("--peers", default=PEERS_DEFAULT, help="comma-separated peers of peers.py ('' none)")
    ap.add_argument("--cache", type=Path, default=default_cache(), help="folder of the built sequences")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "object_case", help="output folder")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    args = ap.parse_args(argv)
    args.cases = [c for c in args.cases.split(",") if c]
    unknown = [c for c in args.cases if c not in CASES]
    if unknown:
        ap.error(f"unknown case(s): {', '.join(unknown)}")
    specs = args.ours if args.ours is not None else [f"{k}={v}" for k, v in OURS.items()]
    if any("=" not in s for s in specs):
        ap.error("--ours takes LABEL=OVERRIDES (overrides may be empty: 'default=')")
    args.ours = {s.split("=", 1)[0]: s.split("=", 1)[1].split() for s in specs}
    args.peers = [p for p in args.peers.split(",") if p]
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    roots = [build_case(c, args.cache, args.frames, args.seed) for c in args.cases] + list(args.roots)
    rows = []
    for root in roots:
        rows.append(run_row(root.resolve(), args.ours, args.peers, args.out))
        print(table(rows[-1:], list(args.ours), args.peers).splitlines()[-1], flush=True)
    body = (
        f"`python experiments/eval/object_case.py {' '.join(argv)}`  \ncommit {git_describe()}, "
        f"{time.perf_counter() - start:.0f} s\n\n{table(rows, list(args.ours), args.peers)}\n\n"
        "Cells: ATE mm / RPE mm (evo's, as evaluate.py); depth px: mean fraction of the image with depth; "
        "feat.: mean tracked features per frame; re-sel.: model re-selections.\n"
    )
    write_text(args.out / "object_case.md", body)
    write_json(args.out / "object_case.json", {"argv": argv, "ours": args.ours, "rows": rows})
    print("\n" + body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
