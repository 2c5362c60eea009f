"""Long-run benchmark: 10,000 frames of small synthetic images through the loader and the tracker.

Checks what a long recording needs and a short test cannot show: the filter's posterior covariance stays symmetric
positive definite on every frame, and the process memory stays flat after warm-up (no per-frame growth in the
tracker, the loss check's store of model frames, the landmarks' keyframes, the front end's thread or the loader).
The frames come from one rendered synthetic sequence (exact ground truth) played forwards and backwards (a ping-pong:
the motion stays continuous, its velocity reverses at the ends), with timestamps that keep increasing, so any length
can be run from a few hundred rendered frames. The tracker is
built and fed as the CLI does it (default config, the CLI's thread count and allocator settings, frames prepared a
step ahead in the front end's thread when ``frontend.ahead``).

    python experiments/bench/bench_long_run.py                          # 10,000 frames of 160x120, 1 thread
    python experiments/bench/bench_long_run.py --frames 2000 --size 320 240 relocalise.recover=false

Prints, every ``--every`` frames: fps, resident memory (MiB) then and its maximum since the previous checkpoint (it
is read every frame), the largest covariance asymmetry ``max |P - P^T| / max |P|`` and the smallest eigenvalue of P
seen so far; at the end the memory growth after warm-up (the largest resident memory after frame ``--warmup`` minus
the resident memory at that frame) and whether it is within ``--bound`` MiB. Exit code 1 when P ever lost symmetry or
definiteness or the growth exceeds the bound.
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from tqdm import tqdm

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.data.tum import RGBDFrame
from torchtrack.factory import build_tracker
from torchtrack.runtime import configure


class PingPong:
    """A sequence of ``n`` frames read from ``seq`` forwards then backwards (period 2 (F - 1)), at ``seq``'s frame
    interval with increasing timestamps; frames are decoded once and kept (the benchmark measures the tracker)."""

    def __init__(self, seq: TumSequence, n: int) -> None:
        self.name, self.K, self.K_depth, self.T_color_depth = "pingpong", seq.K, seq.K_depth, seq.T_color_depth
        self.frames = [seq[i] for i in range(len(seq))]
        self.dt = float(seq.timestamps[1] - seq.timestamps[0])
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int) -> RGBDFrame:
        F = len(self.frames)
        k = i % (2 * (F - 1))
        f = self.frames[k if k < F else 2 * (F - 1) - k]
        return RGBDFrame(f.rgb, f.depth, i * self.dt, f.T_world_color_gt, f.gt_valid, i)


def rss_mib() -> float:
    """Current resident set size in MiB (Linux /proc)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=10_000, help="frames tracked")
    ap.add_argument("--size", type=int, nargs=2, default=(160, 120), metavar=("W", "H"), help="image size")
    ap.add_argument("--rendered", type=int, default=200, help="frames rendered (played forwards and backwards)")
    ap.add_argument("--every", type=int, default=1000, help="checkpoint interval (frames)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--warmup", type=int, default=1000, help="frames before the memory growth is measured")
    ap.add_argument("--bound", type=float, default=50.0, help="MiB: the largest growth after warm-up accepted")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the tracker's config")
    args = ap.parse_args(argv)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=args.overrides)
    configure(args.threads)
    W, H = args.size
    cache = Path(tempfile.gettempdir()) / "torchtrack-bench-long"
    root = ensure_sequence(SyntheticConfig(width=W, height=H, frames=args.rendered, seed=0), cache)
    seq = PingPong(TumSequence(root), args.frames)
    tracker = build_tracker(cfg)
    worst_asym, min_eig, n_cov, rows = 0.0, float("inf"), 0, []
    peak, rss_warm, peak_warm = 0.0, None, 0.0  # max RSS since the last checkpoint; RSS at and max after warm-up
    frames = tracker.frontend.prepared_ahead(iterate_batched([seq]))  # as torchtrack.run does (frontend.ahead)
    t0 = time.perf_counter()
    with torch.inference_mode():
        for frame in tqdm(frames, total=args.frames, unit="frame", desc="long run"):
            res = tracker.step(frame)
            cov = getattr(res.estimate, "cov", None)
            if cov is not None:
                P = cov.double()
                worst_asym = max(worst_asym, float((P - P.mT).abs().amax() / P.abs().amax()))
                min_eig = min(min_eig, float(torch.linalg.eigvalsh(0.5 * (P + P.mT)).min()))
                n_cov += 1
            i = int(frame.index[0]) + 1
            mem = rss_mib()
            peak = max(peak, mem)
            if i == args.warmup:
                rss_warm = mem
            elif i > args.warmup:
                peak_warm = max(peak_warm, mem)
            if i % args.every == 0 or i == args.frames:
                rows.append((i, i / (time.perf_counter() - t0), mem, peak, worst_asym, min_eig))
                peak = 0.0
    print(f"{args.frames} frames of {W}x{H}, {args.threads} thread(s), overrides {args.overrides or 'none'}")
    print(f"{'frames':>7} {'fps':>7} {'RSS MiB':>8} {'max RSS':>8} {'max asym':>9} {'min eig':>9}")
    for i, fps, mem, top, asym, eig in rows:
        print(f"{i:>7} {fps:>7.1f} {mem:>8.1f} {top:>8.1f} {asym:>9.2e} {eig:>9.2e}")
    spd = n_cov > 0 and worst_asym < 1e-9 and min_eig > 0
    print(f"covariance checked on {n_cov} frames: {'symmetric positive definite' if spd else 'NOT SPD'}")
    if rss_warm is None or args.frames <= args.warmup:
        print(f"memory growth after warm-up: not measured (needs more than --warmup {args.warmup} frames)")
        return 0 if spd else 1
    growth = peak_warm - rss_warm
    flat = growth <= args.bound
    print(f"memory growth after warm-up (max RSS after frame {args.warmup} minus RSS at it, {rss_warm:.1f} MiB): "
          f"{growth:+.1f} MiB, {'within' if flat else 'OVER'} the {args.bound:g} MiB bound")  # fmt: skip
    return 0 if spd and flat else 1


if __name__ == "__main__":
    sys.exit(main())
