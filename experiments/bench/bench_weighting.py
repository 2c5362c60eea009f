"""Benchmark of the weighting stage: LearnedWeighting (both modes) against PaperWeighting on the same inputs.

Run: ``python experiments/bench/bench_weighting.py [--b 1] [--n 300] [--reps 2000] [--json out.json]``

One thread (``torch.set_num_threads(1)``, as the CLI), ``torch.inference_mode()`` (as ``run_tracker``), float32
inputs (as the tracker's), every variant timed interleaved in one process; reports the minimum and the median
wall time per call and the median ratio to PaperWeighting (the machine may be shared: compare ratios).
The budget is 1 ms per frame at B = 1, N = 300.
"""

from __future__ import annotations

import argparse
import json

import torch
from bench_ekf import timeit  # experiments/bench/bench_ekf.py: interleaved timing of both sides in one process

from torchtrack.filter.cues import CUE_NAMES, D_TIM_CAP
from torchtrack.filter.weighting import PaperWeighting, WeightingInputs
from torchtrack.learn.model import LearnedWeighting


def inputs(B: int, N: int, seed: int = 0) -> WeightingInputs:
    """Random but plausible float32 inputs: 10 % invalid, 20 % of SIM d_TIM at the cap."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(B, N, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 2.0])
    cues = torch.rand(B, N, len(CUE_NAMES), generator=g)
    cues[..., CUE_NAMES.index("d_tim_sim")].masked_fill_(torch.rand(B, N, generator=g) < 0.2, D_TIM_CAP)
    cues[..., CUE_NAMES.index("depth")] = pts[..., 2]
    valid = torch.rand(B, N, generator=g) > 0.1
    return WeightingInputs(cues[..., 0], pts[..., 2], pts, valid, torch.full((B,), 525.0), cues=cues)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--b", type=int, default=1, help="sequences per batch")
    ap.add_argument("--n", type=int, default=300, help="features per sequence")
    ap.add_argument("--reps", type=int, default=2000, help="timed calls per variant")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    inp = inputs(args.b, args.n)
    paper = PaperWeighting(1.0, 4e-6, depth_var_exponent=4.0)
    learned = {mode: LearnedWeighting(mode=mode).eval() for mode in ("normalised", "absolute")}
    fns = {"paper": lambda: paper(inp)} | {f"learned_{m}": (lambda w=w: w(inp)) for m, w in learned.items()}
    with torch.inference_mode():
        res = timeit(fns, args.reps, warmup=20)
    base = res["paper"][1]
    n_params = sum(p.numel() for p in learned["normalised"].parameters())
    print(f"B={args.b} N={args.n} threads=1 reps={args.reps} torch {torch.__version__}; learned: {n_params} parameters")
    for k, (lo, med) in res.items():
        print(f"  {k:20s} min {lo:.3f} ms  median {med:.3f} ms  x{med / base:.2f} of paper")
    if args.json:
        with open(args.json, "w") as f:
            out = {k: {"min_ms": lo, "median_ms": med} for k, (lo, med) in res.items()}
            json.dump(
                {"B": args.b, "N": args.n, "reps": args.reps, "parameters": n_params, "results": out}, f, indent=1
            )


if __name__ == "__main__":
    main()
