"""Map quality of the panorama (the paper's Figs. 8-9): the map from our poses and from the Open3D odometry
peer's poses against the map from ground-truth poses, on every sequence.

Per sequence: torchtrack's default tracker runs with ``mapping=panorama`` exactly as the CLI composes it (its run
folder, with ``map.ply`` and ``map.png``, goes to ``OUT/ours/<sequence>/``); the peer (experiments/eval/peers.py) runs or
comes from its cache (``OUT/peer/<sequence>/``, the cache of experiments/eval/evaluate.py). The frames of the panorama —
the first and every model frame of our run, those with ground truth — are then fused three times with the mapping
config (B = 3 in one batched map): with the ground-truth poses (the reference), with ours (``trajectory.txt``, the
same world: anchored on the first ground-truth pose) and with the peer's (also started at the first ground-truth
pose). No alignment: a map is as good as its poses are where they were taken.

Distances are nearest-neighbour distances between the maps' points (one per voxel): ``acc`` from each point of the
estimated map to the reference (where its surfaces are misplaced), ``compl`` from each reference point to the
estimated map (what is missing or moved away); mean and 90th percentile, mm. The reference map fused against itself
is 0 by construction; the voxel size (1 cm) and depth noise bound what a perfect trajectory could show only through
voxelisation differences (about half a voxel).

    python experiments/eval/map_quality.py                                  # every folder of ../shared/data
    python experiments/eval/map_quality.py --roots ../shared/data/sun3d_fragment1 --no-results
    python experiments/eval/map_quality.py mapping.voxel_size=0.02          # Hydra overrides pass through

Writes ``OUT/map_quality.md`` and ``.json``, the pictures ``experiments/figures/map_<sequence>.png`` (our map.png at
half size) and the section "## Panoramic maps: map quality" of experiments/RESULTS.md (``--results``; atomically).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from common import compose_config, find_sequences, git_describe, replace_section, run_peer, split_argv
from scipy.spatial import cKDTree
from tqdm import tqdm

from torchtrack.data.batching import iterate_batched
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum_io import read_tum_trajectory
from torchtrack.factory import build_mapper, build_sequences, build_tracker
from torchtrack.io import write_atomic, write_json, write_text
from torchtrack.run import run_tracker

log = logging.getLogger("map_quality")

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
HEADING = "## Panoramic maps: map quality"
POSES = ("gt", "ours", "peer")


class Subsequence:
    """The frames ``indices`` of a sequence, as :func:`iterate_batched` reads them (frame indices kept)."""

    def __init__(self, seq, indices: list[int]):
        self.seq, self.indices = seq, indices
        self.name, self.K, self.K_depth, self.T_color_depth = seq.name, seq.K, seq.K_depth, seq.T_color_depth

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int):
        return self.seq[self.indices[i]]


def run_ours(cfg, out: Path) -> Path:
    """The CLI's run with the mapper: ``out/<sequence>/`` with trajectory.txt, frames.csv, map.ply, map.png."""
    (seq,) = build_sequences(cfg.data)
    run_tracker(build_tracker(cfg), [seq], out, plots=False, mapper=build_mapper(cfg))
    return out / seq.name


def panorama_frames(run_dir: Path, gt_valid: np.ndarray) -> list[int]:
    """The frames our mapper fused (the first and the re-selections: frames.csv) that have ground truth."""
    rows = [line.split(",") for line in (run_dir / "frames.csv").read_text().splitlines()]
    col = rows[0].index("reselected")
    return [i for i, r in enumerate(rows[1:]) if (i == 0 or r[col] == "True") and bool(gt_valid[i])]


def fuse_three(cfg, seq, frames: list[int], poses: dict[str, np.ndarray]):
    """Maps (one per pose set, in POSES order) of the same frames, one batched mapper (B = 3)."""
    mapper = build_mapper(cfg)
    T = torch.as_tensor(np.stack([poses[k] for k in POSES], 1), dtype=torch.float64)  # F,3,4,4
    with torch.inference_mode():
        for frame in tqdm(iterate_batched([Subsequence(seq, frames)]), total=len(frames), desc=f"maps {seq.name}"):
            fb = FrameBatch(**{k: v.expand(len(POSES), *v.shape[1:]) for k, v in vars(frame).items()})
            mapper.fuse(fb, T[int(frame.index[0])], torch.ones(len(POSES), dtype=torch.bool))
    return [mapper.points(b) for b in range(len(POSES))]


def distances(est: np.ndarray, ref: np.ndarray) -> dict:
    """Nearest-neighbour distances (mm) est -> ref (acc) and ref -> est (compl): mean and 90th percentile."""
    acc, _ = cKDTree(ref).query(est, workers=1)
    compl, _ = cKDTree(est).query(ref, workers=1)
    return {
        "acc_mean_mm": 1e3 * float(acc.mean()), "acc_p90_mm": 1e3 * float(np.percentile(acc, 90)),
        "compl_mean_mm": 1e3 * float(compl.mean()), "compl_p90_mm": 1e3 * float(np.percentile(compl, 90)),
    }  # fmt: skip


def write_figure(src: Path, dst: Path) -> None:
    img = cv2.imread(str(src))
    small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    write_atomic(dst, lambda tmp: cv2.imwrite(str(tmp), small, [cv2.IMWRITE_PNG_COMPRESSION, 9]))


def evaluate_one(root: Path, args, overrides: list[str]) -> dict:
    cfg = compose_config(root, args.max_frames, ["mapping=panorama", *overrides])
    (seq,) = build_sequences(cfg.data)
    t0 = time.perf_counter()
    run_dir = run_ours(cfg, args.out / "ours")
    ours_s = time.perf_counter() - t0
    peer = run_peer(seq, args.out / "peer")
    gt_valid = np.asarray(seq.gt_valid)
    frames = panorama_frames(run_dir, gt_valid)
    poses = {
        "gt": np.asarray(seq.groundtruth),
        "ours": read_tum_trajectory(run_dir / "trajectory.txt").T_world_cam,
        "peer": read_tum_trajectory(args.out / "peer" / seq.name / "trajectory.txt").T_world_cam,
    }
    maps = dict(zip(POSES, fuse_three(cfg, seq, frames, poses), strict=True))
    ref = maps["gt"].xyz.numpy()
    row = {"sequence": seq.name, "frames": len(seq), "fused": len(frames), "ref_points": len(ref), "ours_s": ours_s}
    row["run_map_points"] = json.loads((run_dir / "map.json").read_text())["map_points"]
    row["ours_points"] = len(maps["ours"].count)
    metrics = json.loads((run_dir / "metrics.json").read_text())
    row["ate_ours_mm"] = 1e3 * metrics.get("ate_rmse_m", float("nan"))
    row["ate_peer_mm"] = 1e3 * peer.get("ate_rmse_m", float("nan"))
    for k in ("ours", "peer"):
        row[k] = distances(maps[k].xyz.numpy(), ref)
    write_figure(run_dir / "map.png", args.figures / f"map_{seq.name}.png")
    return row


def table(rows: list[dict]) -> str:
    head = (
        "| sequence | frames | fused | ref. points | ours acc mean | p90 | compl mean | p90 "
        "| peer acc mean | p90 | compl mean | p90 | ATE ours | ATE peer |"
    )
    lines = [head, "|" + "---|" * 14]
    for r in rows:
        cells = [r["sequence"], str(r["frames"]), str(r["fused"]), str(r["ref_points"])]
        for k in ("ours", "peer"):
            d = r[k]
            cells += [f"{d[m]:.1f}" for m in ("acc_mean_mm", "acc_p90_mm", "compl_mean_mm", "compl_p90_mm")]
        cells += [f"{r['ate_ours_mm']:.1f}", f"{r['ate_peer_mm']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def report(rows: list[dict], command: str, commit: str) -> str:
    figs = "\n".join(
        f"![{r['sequence']}](figures/map_{r['sequence']}.png)" for r in rows
    )  # relative to experiments/RESULTS.md
    notes = [
        "Distances in mm between the maps' points (1 cm voxels, one averaged coloured point each): acc = from each "
        "point of the map fused with the estimated poses to the nearest point of the map fused with ground truth "
        "(same frames), compl = the reverse; mean and 90th percentile. No alignment: all trajectories start at the "
        "first ground-truth pose.",
        "fused = the panorama's frames: the first and every model (re-selected) frame of our run that has ground "
        "truth; the same frames for the three maps, so only the poses differ.",
        "ATE (mm, SE(3)-aligned RMSE) of the whole trajectories, for context.",
        "Ours vs the peer: "
        + ", ".join(
            f"{m} {sum(r['ours'][k] < r['peer'][k] for r in rows)} of {len(rows)} sequences lower"
            for m, k in (("acc mean", "acc_mean_mm"), ("acc p90", "acc_p90_mm"), ("compl mean", "compl_mean_mm"))
        )
        + ".",
        "Check: the map re-fused here from our trajectory.txt has as many points as the run's own map.ply on "
        + (
            "every sequence."
            if all(r["run_map_points"] == r["ours_points"] for r in rows)
            else "NOT every sequence: "
            + ", ".join(r["sequence"] for r in rows if r["run_map_points"] != r["ours_points"])
            + "."
        ),
        "Pictures: our map.png (perspective from the first camera with twice its field of view | top-down along the "
        "first camera's y axis), half size.",
    ]
    body = [
        f"`{command}` (commit {commit}, {time.strftime('%Y-%m-%d', time.gmtime())})",
        "",
        table(rows),
        "",
        "\n".join(f"- {n}" for n in notes),
        "",
        figs,
    ]
    return "\n".join(body) + "\n"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    opts, overrides = split_argv(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--roots", type=Path, nargs="+", default=[DATA], help="sequence folders or folders of them")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames (None: all)")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "evaluation", help="runs (peer cache shared)")
    ap.add_argument("--figures", type=Path, default=REPO / "experiments" / "figures", help="where the map pictures go")
    ap.add_argument(
        "--results",
        type=Path,
        default=REPO / "experiments" / "RESULTS.md",
        help="markdown file whose section is replaced",
    )
    ap.add_argument("--no-results", action="store_true", help="do not touch RESULTS.md")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from OUT/map_quality.json")
    args = ap.parse_args(opts)
    args.out = args.out.resolve()
    logging.basicConfig(level=logging.WARNING, format="%(name)s: %(message)s")
    torch.set_num_threads(args.threads)
    command = "python experiments/eval/map_quality.py " + " ".join(argv)
    if args.report_only:
        saved = json.loads((args.out / "map_quality.json").read_text())
        rows, command, commit = saved["rows"], saved["command"], saved["commit"]
    else:
        rows, commit = [], git_describe()  # the code that measures: HEAD when the run starts
        for root in find_sequences(args.roots):
            rows.append(evaluate_one(root, args, overrides))
            print(table(rows[-1:]).splitlines()[-1], flush=True)
    text = report(rows, command.strip(), commit)
    write_text(args.out / "map_quality.md", text)
    write_json(args.out / "map_quality.json", {"command": command, "commit": commit, "rows": rows})
    print(text)
    if not args.no_results:
        old = args.results.read_text() if args.results.is_file() else ""
        write_text(args.results, replace_section(old, HEADING, text))
    return 0


if __name__ == "__main__":
    sys.exit(main())
