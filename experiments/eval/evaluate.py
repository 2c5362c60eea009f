"""Evaluate torchtrack against the strongest peers on every sequence and its perturbed variants.

For every sequence folder (TUM layout) this runs torchtrack's default tracker exactly as the CLI composes
it (``conf/`` through Hydra, in-process) and the peers of :mod:`peers` (Open3D legacy RGB-D odometry,
hybrid and colour terms; Open3D tensor odometry, hybrid and point-to-plane; Open3D tensor frame-to-model
tracking against a TSDF raycast; OpenCV 5 ``cv2.Odometry``), scores all with
:func:`torchtrack.metrics.trajectory_metrics` (evo's ATE/RPE) and prints per sequence each peer's ATE/RPE/ms, the
best peer and ours against it. The target: ours <= 0.7x the best peer's ATE on the real sequences, <= 1.0x
on the variants.

    python experiments/eval/evaluate.py                                       # every folder in ../shared/data
    python experiments/eval/evaluate.py --variants --variant-frames 300 --results experiments/RESULTS.md
    python experiments/eval/evaluate.py --roots ../shared/data/sun3d_fragment1 --max-frames 20 --peers o3d_hybrid
    python experiments/eval/evaluate.py pipeline.predict_init=false --out outputs/eval_off   # Hydra overrides

``--seeds 1,2,3`` also runs ours on the ``jitter`` variant (half a grey level of colour noise, seeded) of every row's
folder, one per seed: the long sequences are chaotic, so one run says little. The row's ATE/RPE and its ratios then
use the median over the plain run and the jittered ones, and the table shows it with its range.

``--variants`` adds the perturbed variants of every sequence (:func:`torchtrack.data.perturb.make_variant`, seed
``--seed``): skip2/3/4, reversed, photometric, depth_noise, built from the first ``--variant-frames`` frames (so
that the long sequence stays feasible on 2 cores; the table says so).

Writes ``OUT/evaluation.md`` (the tables), ``OUT/evaluation.json``, torchtrack's run folders in
``OUT/ours/<folder>/`` and each peer's in ``OUT/peers/<peer>/<folder>/``. A peer's result is cached there, keyed
by the frames, the camera and the peer's version (library version and code), so re-running after a tracker
change only re-runs torchtrack. ``--results FILE`` replaces this script's section of FILE (atomically).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch
from common import (
    best_peer,
    check_trajectory,
    compose_config,
    find_sequences,
    git_describe,
    n_listed,
    replace_section,
    run_ours,
    run_peer,
    split_argv,
)

from torchtrack.config import CONF_DIR
from torchtrack.data.perturb import make_variant
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import read_tum_trajectory
from torchtrack.factory import build_sequences
from torchtrack.io import write_json, write_text
from torchtrack.metrics import shared_error

log = logging.getLogger("evaluate")

REPO = Path(__file__).resolve().parents[2]
CONF = CONF_DIR
DATA = REPO.parent / "shared" / "data"
TARGET_RATIO = 0.7  # the target: ours <= 0.7x the best peer's ATE on the real sequences ...
VARIANT_RATIO = 1.0  # ... and <= 1.0x on every perturbed variant
VARIANTS = ("skip2", "skip3", "skip4", "reversed", "photometric", "depth_noise")
HEADING = "## Accuracy against the peers: the evaluation table"
# Sequences scored on ATE only, and why (shown under the table).
ATE_ONLY = {"visp_rbt_sequence": "per-frame AprilTag pseudo ground truth (~1 cm) dominates RPE"}
METRICS = ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg")
FLOOR_NOTE = (
    "- shared = sqrt(mean over frames of <e_ours, e_peer>), e the per-frame error vector (RPE: translation of the "
    "delta-1 relative error; ATE: SE(3)-aligned position error), against the best peer. For RPE, independent "
    "per-frame errors average out and what stays is what both methods get wrong the same way: the ground truth's "
    "own errors and artefacts of the data both read; where it exceeds 0.7x the peer's RPE, a tracker reading the "
    "same data cannot meet the target. ATE errors are slow drifts that correlate by chance: the ATE column is no "
    "floor.\n"
    "- Sim(3) scale: the Umeyama scale that maps the trajectory onto the ground truth (1 = metric agreement); a "
    "common scale != 1 in both points at the depth's scale against the ground truth's."
)


# ----------------------------------------------------------------------------------------------- inputs


def shared_floor(ours_folder: Path, peer_folder: Path, seq: TumSequence) -> dict:
    """What ours and a peer have in common (:func:`torchtrack.metrics.shared_error`) on frames with ground truth.

    Two independent methods share the errors of the ground truth and of sensor artefacts both see; where that
    shared part exceeds TARGET_RATIO x the peer's error, a tracker that shares it cannot reach the target.
    """
    ours = read_tum_trajectory(ours_folder / "trajectory.txt").T_world_cam
    peer = read_tum_trajectory(peer_folder / "trajectory.txt").T_world_cam
    keep = torch.as_tensor(seq.gt_valid).bool()
    gt = torch.as_tensor(seq.groundtruth)[keep]
    s = shared_error(torch.as_tensor(ours)[keep], torch.as_tensor(peer)[keep], gt)
    return {"ate_m": s.ate_m, "rpe_trans_m": s.rpe_trans_m, "scale_ours": s.scale_a, "scale_peer": s.scale_b}


# ----------------------------------------------------------------------------------------------- table


def ratio(ours: float | None, peer: float | None) -> float | None:
    if ours is None or peer is None or peer <= 0:
        return None
    return ours / peer


def verdict(name: str, ratios: dict, target: float = TARGET_RATIO) -> tuple[bool | None, str]:
    """(met, text): ATE and RPE translation at most ``target`` x the best peer's; ATE only for ATE_ONLY."""
    keys = ("ate_rmse_m",) if name in ATE_ONLY else ("ate_rmse_m", "rpe_trans_m")
    r = [ratios.get(k) for k in keys]
    if any(v is None for v in r):
        return None, "n/a"
    failed = [lbl for k, lbl, v in zip(keys, ("ATE", "RPE"), r, strict=False) if v > target]
    suffix = " (ATE only)" if name in ATE_ONLY else ""
    return not failed, ("yes" + suffix if not failed else f"**no** ({', '.join(failed)})")


def fmt(v: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "–" if v is None else f"{v * scale:.{digits}f}"


def ms(m: dict | None) -> str:
    fps = (m or {}).get("fps")
    return "–" if not fps else f"{1e3 / fps:.0f}"


def table(rows: list[dict], peers: list[str], compare: dict[str, dict] | None = None) -> str:
    """One line per (sequence, variant): ours, each peer (ATE mm / RPE mm / ms per frame), the best and the ratios;
    ``compare`` {label: {(sequence, variant): ours}} adds ours from other runs (ablations) as columns."""
    compare = compare or {}
    seeded = any(r.get("ours_median") for r in rows)
    head = ["sequence", "variant", "frames", "ours ATE / RPE / ms", "re-sel."]
    head += ["ours median ATE [range] / RPE, runs"] if seeded else []
    head += [f"{c} ATE / RPE / ms, re-sel." for c in compare] + list(peers)
    head += ["best (ATE)", "ATE ours/best", "RPE ours/best RPE", "target"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        o, q = r.get("ours") or {}, r.get("ratio", {})
        cells = [r["sequence"], r["variant"], str(r.get("frames", "–")), triple(o), str(o.get("reselections", "–"))]
        cells += [spread(r.get("ours_median"))] if seeded else []
        for runs in compare.values():
            c = runs.get((r["sequence"], r["variant"]))
            cells.append(f"{triple(c)}, {c.get('reselections', '–')}" if c else "–")
        cells += [triple(r.get("peers", {}).get(p)) for p in peers]
        cells += [r.get("best") or "–", fmt(q.get("ate_rmse_m")), fmt(q.get("rpe_trans_m"))]
        cells.append(r["verdict"] if "error" not in r else f"error: {r['error']}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def load_compare(specs: list[str]) -> dict[str, dict]:
    """``LABEL=OUT/evaluation.json`` -> {LABEL: {(sequence, variant): ours metrics}}: ablation columns (a label given
    twice merges its runs)."""
    out = {}
    for spec in specs:
        label, sep, path = spec.partition("=")
        if not sep or not Path(path).is_file():
            raise SystemExit(f"evaluate: --compare wants LABEL=PATH/evaluation.json, got {spec!r}")
        rows = json.loads(Path(path).read_text())["rows"]
        out.setdefault(label, {}).update({(r["sequence"], r["variant"]): r["ours"] for r in rows if r.get("ours")})
    return out


def triple(m: dict | None) -> str:
    if not m:
        return "–"
    if "error" in m:
        return "failed"
    return f"{fmt(m.get('ate_rmse_m'), 1e3, 1)} / {fmt(m.get('rpe_trans_m'), 1e3, 2)} / {ms(m)}"


def spread(m: dict | None) -> str:
    """A median cell: 'ATE [min-max] / RPE, runs' in mm."""
    if not m or m.get("ate_rmse_m") is None:
        return "–"
    lo, hi = m["ate_rmse_m_range"]
    return (
        f"{m['ate_rmse_m'] * 1e3:.1f} [{lo * 1e3:.1f}-{hi * 1e3:.1f}] / {fmt(m.get('rpe_trans_m'), 1e3)}, {m['runs']}"
    )


def floor_table(rows: list[dict]) -> str:
    """The error ours and the best peer share against the target, and each one's Sim(3) scale (real sequences)."""
    lines = [
        "| sequence | best peer | ATE shared mm | 0.7x best ATE | RPE shared mm | 0.7x best RPE | Sim(3) scale ours "
        "| peer |",
        "|" + "---|" * 8,
    ]
    for r in rows:
        f = r.get("shared")
        if not f:
            continue
        p = r["peers"][r["best"]]
        cells = [r["sequence"], r["best"], fmt(f["ate_m"], 1e3), fmt(p.get("ate_rmse_m"), TARGET_RATIO * 1e3)]
        cells += [fmt(f["rpe_trans_m"], 1e3), fmt(p.get("rpe_trans_m"), TARGET_RATIO * 1e3)]
        cells += [fmt(f["scale_ours"], 1, 3), fmt(f["scale_peer"], 1, 3)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""


def summary(rows: list[dict]) -> str:
    """Geometric mean of ours/best ATE over the real sequences and over the variants; targets met."""
    out = []
    for label, real in (("real sequences", True), ("variants", False)):
        r = [x for x in rows if (x["variant"] == "real") == real and x.get("ratio", {}).get("ate_rmse_m")]
        if r:
            gm = float(np.exp(np.mean([np.log(x["ratio"]["ate_rmse_m"]) for x in r])))
            met = sum(bool(x.get("met")) for x in r)
            out.append(f"{label}: geometric mean ATE ours/best {gm:.2f}, target met on {met} of {len(r)}")
    return "; ".join(out)


def footnotes(rows: list[dict], peers: list[str], args) -> str:
    from peers import PEERS

    notes = [
        "Cells: ATE mm (RMSE after SE(3) Umeyama alignment, evo_ape -a) / RPE mm (RMSE over consecutive frames, "
        "evo_rpe delta 1) / ms per frame (wall time incl. image decoding, 1 torch thread; on a shared 2-core machine: "
        "a rough guide). best = the peer with the smallest ATE; RPE ratio against the smallest peer RPE. Target: "
        f"ATE and RPE ratios <= {TARGET_RATIO} on the real sequences, <= {VARIANT_RATIO} on the variants.",
        "Peers: " + "; ".join(f"`{p}` {PEERS[p].label}" for p in peers) + ".",
    ]
    if any(r["variant"] != "real" for r in rows):
        notes.append(
            f"Variants: torchtrack.data.perturb, seed {args.seed}, each built from the first {args.variant_frames} "
            "frames of its sequence (only 7scenes_redkitchen is longer); skipK keeps every K-th frame (K x faster "
            "motion)."
        )
    seeds = sorted({r["seed"] for row in rows for r in row.get("ours_runs", [])[1:]})
    if seeds:
        notes.append(
            f"ours median: over the plain run and the `jitter` variants (seeds {', '.join(map(str, seeds))}: half a grey"
            " level of colour noise) of the same frames; the ratios and the target use it."
        )
    cut = [f"{r['sequence']} (first {r['frames']} of {n_listed(Path(r['root']))})" for r in rows
           if r["variant"] == "real" and r.get("frames") and Path(r["root"]).is_dir() and r["frames"] < n_listed(Path(r["root"]))]  # fmt: skip
    if cut:
        notes.append("Real rows on a prefix (--max-frames): " + ", ".join(cut) + ".")
    notes += [f"{n}: ATE only ({why})." for n, why in ATE_ONLY.items() if any(r["sequence"] == n for r in rows)]
    s = summary(rows)
    if s:
        notes.append(s + ".")
    return "\n".join(f"- {n}" for n in notes)


# ----------------------------------------------------------------------------------------------- main


def jittered(root: Path, max_frames: int | None, overrides: list[str], args) -> list[dict]:
    """Ours on the ``jitter`` variant of ``root`` (its first ``max_frames`` frames) for every seed of ``--seeds``;
    each run folder goes to ``OUT/ours_jitter/s<seed>/``."""
    runs = []
    for seed in args.seeds:
        folder = make_variant(root, "jitter", args.cache, seed=seed, first=max_frames)
        cfg = compose_config(folder, None, overrides)
        runs.append({**run_ours(cfg, args.out / "ours_jitter" / f"s{seed}", plots=False), "seed": seed})
    return runs


def median_metrics(runs: list[dict]) -> dict:
    """Per metric (ATE, RPE, fps, re-selections): the median over the runs that have it, and ``<key>_range``
    [min, max]; ``runs`` the number of runs."""
    out: dict = {"runs": len(runs)}
    for key in (*METRICS, "fps", "reselections"):
        vals = [r[key] for r in runs if r.get(key) is not None]
        if vals:
            out[key], out[f"{key}_range"] = float(np.median(vals)), [float(min(vals)), float(max(vals))]
    return out


def evaluate_one(src: Path, root: Path, kind: str, args, overrides: list[str]) -> dict:
    """One table row: ours and every peer on ``root`` (``src`` itself or its ``kind`` variant)."""
    from peers import PEERS

    max_frames = args.max_frames if kind == "real" else None  # a variant already is its prefix
    cfg = compose_config(root, max_frames, overrides)
    torch.set_num_threads(args.threads or int(cfg.threads or 1))
    row: dict = {"sequence": src.name, "variant": kind, "root": str(root), "ours": None, "peers": {}, "ratio": {}}
    try:
        (seq,) = build_sequences(cfg.data)
        row["frames"] = len(seq)
        t0 = time.perf_counter()
        row["ours"] = run_ours(cfg, args.out / "ours", plots=not args.no_plots)
        check_trajectory(args.out / "ours" / seq.name, seq, row["ours"])
        row["ours_wall_s"] = time.perf_counter() - t0
        if args.seeds:
            row["ours_runs"] = [row["ours"], *jittered(root, max_frames, overrides, args)]
            row["ours_median"] = median_metrics(row["ours_runs"])
        for name in args.peers:
            try:
                row["peers"][name] = run_peer(seq, PEERS[name], args.out / "peers")
            except Exception as e:  # a failing peer is a cell, not a lost row
                log.exception("%s: peer %s failed", seq.name, name)
                row["peers"][name] = {"error": f"{type(e).__name__}: {e}".splitlines()[0]}
        row["best"] = best_peer(row["peers"])
        if row["best"]:
            best, best_rpe = row["peers"][row["best"]], row["peers"][best_peer(row["peers"], "rpe_trans_m")]
            ours = row.get("ours_median") or row["ours"]
            row["ratio"] = {k: ratio(ours.get(k), (best_rpe if k == "rpe_trans_m" else best).get(k)) for k in METRICS}
            if kind == "real" and seq.has_groundtruth and row["ours"].get("ate_rmse_m") is not None:
                peer_folder = args.out / "peers" / row["best"] / seq.name
                row["shared"] = shared_floor(args.out / "ours" / seq.name, peer_folder, seq)
    except Exception as e:  # one failing sequence must not lose the others' rows
        log.exception("%s failed", root)
        row["error"] = f"{type(e).__name__}: {e}".splitlines()[0]
    target = TARGET_RATIO if kind == "real" else VARIANT_RATIO
    row["met"], row["verdict"] = verdict(src.name, row["ratio"], target)
    return row


def sources(src: Path, args) -> list[tuple[str, Path]]:
    """(kind, folder): the sequence itself, then its variants (built deterministically from ``args.seed``)."""
    out = [] if args.no_real else [("real", src)]
    for kind in args.variants:
        out.append((kind, make_variant(src, kind, args.cache, seed=args.seed, first=args.variant_frames)))
    return out


def default_cache() -> Path:
    root = os.environ.get("TORCHTRACK_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "torchtrack") / "variants"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    from peers import PEERS

    opts, overrides = split_argv(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--roots", type=Path, nargs="+", default=[DATA], help="sequence folders or folders of them")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames of every real sequence")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "evaluation", help="output folder")
    ap.add_argument("--peers", default=",".join(PEERS), help=f"comma-separated, of {', '.join(PEERS)} ('' none)")
    ap.add_argument("--no-peer", action="store_true", help="no peers (same as --peers '')")
    ap.add_argument("--variants", nargs="?", const=",".join(VARIANTS), default="", help="perturbed variants")
    ap.add_argument("--variant-frames", type=int, default=300, help="variants are built from this many frames")
    ap.add_argument("--no-real", action="store_true", help="only the variants (e.g. a second process)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the variants")
    ap.add_argument("--seeds", default="", help="comma-separated jitter seeds: ours also on those, median reported")
    ap.add_argument("--cache", type=Path, default=default_cache(), help="folder of the built variants")
    ap.add_argument("--results", type=Path, default=None, help="replace this script's section of this markdown file")
    ap.add_argument(
        "--compare",
        action="append",
        default=[],
        metavar="LABEL=JSON",
        help="ours of another run as columns; write --compare=LABEL=JSON",
    )
    ap.add_argument(
        "--render",
        type=Path,
        nargs="+",
        default=None,
        metavar="JSON",
        help="run nothing: the tables of these evaluation.json files, one after the other",
    )
    ap.add_argument("--no-plots", action="store_true", help="no trajectory/feature pictures per run")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (None: the config's)")
    ap.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    args = ap.parse_args(opts)
    args.peers = [] if args.no_peer else [p for p in args.peers.split(",") if p]
    args.variants = [v for v in args.variants.split(",") if v and v != "none"]
    try:
        args.seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--seeds wants comma-separated integers, got {args.seeds!r}")
    unknown = [p for p in args.peers if p not in PEERS] + [v for v in args.variants if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown peer(s) or variant(s): {', '.join(unknown)}")
    return args, overrides


PARTIAL = "; stopped before its end: the rows it finished"


def render(args, compare: dict) -> str:
    """The section's body from finished runs (``--render``): their commands, then one table of all their rows."""
    runs = [json.loads(p.read_text()) for p in args.render]
    rows = [r for run in runs for r in run["rows"]]
    peers = list(dict.fromkeys(p for r in rows for p in r.get("peers", {})))
    commands = "\n".join(
        f"`{run['meta']['command']}` (commit {run['meta']['commit']}, {run['meta']['total_s']:.0f} s{PARTIAL if run['meta'].get('partial') else ''})  "
        for run in runs
    )
    body = f"{commands}\n\n{table(rows, peers, compare)}\n\n{footnotes(rows, peers, args)}\n"
    floors = floor_table(rows)
    return body + (
        f"\nWhat ours and the best peer have in common (real sequences):\n\n{floors}\n\n{FLOOR_NOTE}\n"
        if floors
        else ""
    )


def write_results(path: Path, body: str) -> None:

    text = path.read_text() if path.is_file() else ""
    write_text(path, replace_section(text, HEADING, body))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args, overrides = parse_args(argv)
    compare = load_compare(args.compare)
    if args.render:
        body = render(args, compare)
        if args.results:
            write_results(args.results, body)
        print(body)
        return 0
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    log.setLevel(logging.INFO)
    args.out.mkdir(parents=True, exist_ok=True)
    start, rows = time.perf_counter(), []
    command, commit = "python experiments/eval/evaluate.py " + " ".join(argv), git_describe()
    print("\n".join(table([], args.peers, compare).splitlines()[:2]), flush=True)
    for src in find_sequences(args.roots):
        for kind, root in sources(src, args):
            log.info("== %s (%s)", src.name, kind)
            rows.append(evaluate_one(src, root, kind, args, overrides))
            print(table(rows[-1:], args.peers, compare).splitlines()[-1], flush=True)
            meta = {"command": command, "overrides": overrides, "total_s": time.perf_counter() - start}
            write_json(
                args.out / "evaluation.json", {"meta": {**meta, "commit": commit, "partial": True}, "rows": rows}
            )
    total = time.perf_counter() - start
    header = (
        f"`{command.strip()}`  \ncommit {git_describe()}, torch {torch.__version__}, {torch.get_num_threads()} "
        f"thread(s), {platform.machine()}, overrides: {overrides or 'none (default config)'}, total {total:.0f} s\n"
    )
    body = f"{header}\n{table(rows, args.peers, compare)}\n\n{footnotes(rows, args.peers, args)}\n"
    floors = floor_table(rows)
    if floors:
        body += f"\nWhat ours and the best peer have in common (real sequences):\n\n{floors}\n\n{FLOOR_NOTE}\n"
    write_text(args.out / "evaluation.md", f"# torchtrack vs the peers\n\n{body}")
    meta = {"command": command, "overrides": overrides, "total_s": total, "commit": commit}
    write_json(args.out / "evaluation.json", {"meta": meta, "rows": rows})
    if args.results:
        write_results(args.results, body)
    print("\n" + body)
    print(f"wrote {args.out / 'evaluation.md'} and evaluation.json ({total:.0f} s)")
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
