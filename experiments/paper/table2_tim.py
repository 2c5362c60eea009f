"""Paper Table II: mean TIM error (px) of the intensity, SIM and combined trackers, per sequence.

    python experiments/paper/table2_tim.py --out runs/paper/table2                 # every sequence, 20 frame pairs each
    python experiments/paper/table2_tim.py --sequences sun3d_fragment1 --pairs 5 --out /tmp/t2

The flow stage alone (paper §III-C): for consecutive frames (t-1, t), features are selected on frame t-1
(:func:`torchtrack.image.select.select_features`, spatio-textural, eq. 9) and tracked to t by
:func:`torchtrack.image.flow.combined_track`: pyramidal LK on the intensity image and on the SIM image
(eq. 8), each tracked back to t-1, ``d_TIM = || x_{t-1} - x'_{t-1} ||`` (eq. 10); the combined tracker keeps,
per feature, the tracker with the smaller d_TIM. One call in mode "combined" gives all three: the
intensity and SIM trackers' own d_TIM (what modes "intensity" and "sim" compute, the same LK passes) and
the winner's. d_TIM is taken before the threshold of step IV (the table measures the trackers, not the
filter). A feature that a tracker loses (LK failure, out of the image) has no d_TIM there; it counts in
the failure rate, and the combined tracker then takes the other one.

Reported per sequence and tracker: the mean d_TIM over the features it tracked, the median, and the
share of features lost. Writes ``OUT/table2_tim.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor

from torchtrack.data.tum import TumSequence
from torchtrack.geometry import warp_depth
from torchtrack.image.flow import FlowFrame, combined_track, prepare_frame
from torchtrack.image.select import select_features
from torchtrack.image.shape_index import compute_sim

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
MODES = ("intensity", "sim", "combined")
LABELS = {"intensity": "Intensity tracker", "sim": "SIM tracker", "combined": "Combined tracker"}
# The paper's Table II: mean TIM error (px) of the tracked features of TUM's Freiburg2-Desk sequence.
PAPER_TABLE2 = {"intensity": 1.15, "sim": 332.43, "combined": 0.09}
PAPER_SEQUENCE = "Freiburg2-Desk"


def load_frames(seq: TumSequence, indices: list[int]) -> tuple[Tensor, Tensor, Tensor]:
    """Frames as a batch: gray (B, 1, H, W), depth in the colour grid (B, 1, H, W), K (B, 3, 3)."""
    frames = [seq[i] for i in indices]
    rgb = torch.stack([f.rgb for f in frames])
    gray = rgb_to_grayscale(rgb)  # as FrameBatch.gray
    depth = torch.stack([f.depth for f in frames])
    B, (H, W) = len(frames), rgb.shape[-2:]
    K = seq.K.expand(B, 3, 3)
    if not torch.allclose(seq.T_color_depth, torch.eye(4)) or not torch.allclose(seq.K_depth, seq.K):
        depth = warp_depth(depth, seq.K_depth.expand(B, 3, 3), K, seq.T_color_depth.expand(B, 4, 4), (H, W))
    return gray, depth, K


def tim_by_tracker(prev: FlowFrame, next: FlowFrame, pixels: Tensor, valid: Tensor, **flow_kwargs) -> dict:
    """d_TIM (B, N) of each tracker, eq. (10), +inf where lost or invalid.

    Args: prev, next: frames t-1 and t from :func:`prepare_frame` with a SIM image; pixels (B, N, 2) and
    valid (B, N) on frame t-1; flow_kwargs: LK parameters of :func:`combined_track`.
    """
    r = combined_track(
        prev, next, pixels, valid, mode="combined", policy="min_tim", **flow_kwargs
    )  # the paper's step III
    inf = torch.full_like(r.d_tim, float("inf"))
    return {m: torch.where(valid, d, inf) for m, d in zip(MODES, (r.d_tim_int, r.d_tim_sim, r.d_tim), strict=True)}


def sequence_tim(seq: TumSequence, pairs: int, batch: int, levels: int, window: int, sim_kwargs: dict) -> dict:
    """Pooled d_TIM of every tracker over ``pairs`` consecutive frame pairs of a sequence."""
    d = {m: [] for m in MODES}
    n_pairs = min(pairs, len(seq) - 1)
    for start in range(0, n_pairs, batch):
        ts = list(range(start + 1, min(start + batch, n_pairs) + 1))
        gray, depth, K = load_frames(seq, [t - 1 for t in ts] + ts)
        sim = compute_sim(depth, K, **sim_kwargs)
        B = len(ts)
        feats = select_features(gray[:B], depth[:B], K[:B], sim=_slice_sim(sim, B), roi_fraction=None)  # eq. (9), t-1
        prev = prepare_frame(gray[:B], sim.image[:B], levels)
        next = prepare_frame(gray[B:], sim.image[B:], levels)
        tim = tim_by_tracker(prev, next, feats.pixels, feats.valid, levels=levels, window=window)
        for m in MODES:
            d[m].append(tim[m][feats.valid].numpy())
    return {m: _stats(np.concatenate(v)) for m, v in d.items()} | {"pairs": n_pairs}


def _slice_sim(sim, B: int):
    return type(sim)(*(x[:B] for x in sim))


def _stats(d: np.ndarray) -> dict:
    ok = np.isfinite(d)
    return {
        "mean_px": float(d[ok].mean()) if ok.any() else None,
        "median_px": float(np.median(d[ok])) if ok.any() else None,
        "lost_fraction": float(1 - ok.mean()) if d.size else None,
        "features": int(d.size),
    }


def markdown(result: dict) -> str:
    """Rows: the three trackers; columns: the paper's value (its Table II, on Freiburg2-Desk), then each sequence's
    mean (median) d_TIM and the share of features lost."""
    s, seqs = result["settings"], result["sequences"]
    lines = [
        f"Features selected on frame t-1 (eq. 9), tracked to t and back; {s['pairs']} consecutive pairs per "
        f"sequence, LK {s['levels']} levels, window {s['window']} px. Per sequence: mean (median) d_TIM over the "
        "features each tracker kept, in pixels, and the share of features it lost. The paper's column is its "
        f"Table II ({PAPER_SEQUENCE}, mean only).\n",
        "| tracker | paper | " + " | ".join(seqs) + " |",
        "|---|---|" + "---|" * len(seqs),
    ]
    for m in MODES:
        cells = [
            f"{_f(r[m]['mean_px'])} ({_f(r[m]['median_px'])}), {_lost(r[m]['lost_fraction'])} lost"
            for r in seqs.values()
        ]
        lines.append(f"| {LABELS[m]} | {PAPER_TABLE2[m]:.2f} | " + " | ".join(cells) + " |")
    lines.append("| features | – | " + " | ".join(str(r["intensity"]["features"]) for r in seqs.values()) + " |")
    return "\n".join(lines) + "\n"


def _lost(x) -> str:
    return "–" if x is None else f"{100 * x:.0f}%"


def _f(x) -> str:
    return "–" if x is None else f"{x:.2f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--data", type=Path, default=DATA, help="folder of TUM-layout sequence folders")
    p.add_argument("--sequences", default=None, help="comma list of folder names (None: all)")
    p.add_argument("--pairs", type=int, default=20, help="consecutive frame pairs per sequence")
    p.add_argument("--batch", type=int, default=5, help="pairs processed together")
    p.add_argument("--levels", type=int, default=3, help="LK pyramid levels")
    p.add_argument("--window", type=int, default=21, help="LK window (px)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (None: torch's default)")
    p.add_argument("--out", type=Path, default=Path("outputs/table2"), help="output folder")
    args = p.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    names = args.sequences.split(",") if args.sequences else sorted(
        d.name for d in args.data.iterdir() if (d / "rgb.txt").is_file()
    )  # fmt: skip
    result = {"settings": {k: v for k, v in vars(args).items() if k not in ("out", "data")}, "sequences": {}}
    result["settings"]["data"] = str(args.data)
    with torch.inference_mode():
        for name in names:
            seq = TumSequence(args.data / name, max_frames=args.pairs + 1)
            result["sequences"][name] = sequence_tim(seq, args.pairs, args.batch, args.levels, args.window, {})
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table2_tim.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "table2_tim.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
