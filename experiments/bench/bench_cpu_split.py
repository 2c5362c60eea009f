"""Where a step's CPU goes by thread: the CLI's loop on B copies of a sequence, wall clock, CPU of the whole
process and of the main (tracking) thread; the rest ran in the loader and front-end threads. Median of ``--runs``.

Load-robust where wall clock is not: on a shared machine compare the CPU columns; run two checkouts alternately
(``PYTHONPATH=<checkout> python experiments/bench/bench_cpu_split.py``) for a before/after. Hydra overrides pass through:

    python experiments/bench/bench_cpu_split.py --batch 1 --runs 3                     # the default (frontend.ahead=true)
    python experiments/bench/bench_cpu_split.py --batch 1 --runs 3 frontend.ahead=false
    python experiments/bench/bench_cpu_split.py --batch 8 --frames 20 --runs 1
"""

from __future__ import annotations

import os

os.environ.setdefault("TQDM_DISABLE", "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import bench_pipeline as bp  # noqa: E402

import torchtrack  # noqa: E402
import torchtrack.run as run_module  # noqa: E402
from torchtrack.factory import build_sequences, build_tracker  # noqa: E402
from torchtrack.runtime import configure  # noqa: E402


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--root", type=Path, default=bp.DEFAULT_ROOT, help="sequence folder")
    ap.add_argument("--batch", type=int, default=1, help="B copies of the sequence in lockstep")
    ap.add_argument("--frames", type=int, default=50, help="frames per copy")
    ap.add_argument("--runs", type=int, default=3, help="runs; the median is reported")
    args, overrides = ap.parse_known_args()
    configure(1)
    cfg = bp.compose_config(args.root, args.frames, overrides)
    rows = []
    for _ in range(args.runs):
        (seq,) = build_sequences(cfg.data)
        tracker = build_tracker(cfg)
        with tempfile.TemporaryDirectory() as out:
            w, c, m = time.perf_counter(), time.process_time(), time.thread_time()
            run_module.run_tracker(tracker, [seq] * args.batch, Path(out), plots=False)
            w, c, m = time.perf_counter() - w, time.process_time() - c, time.thread_time() - m
        rows.append([1e3 * x / args.frames for x in (w, c, m)])
    wall, cpu, main_cpu = (statistics.median(r[i] for r in rows) for i in range(3))
    print(f"{Path(torchtrack.__file__).resolve().parents[1].name} B={args.batch} {' '.join(overrides)}: wall "
          f"{wall:.1f} ms/step ({1e3 * args.batch / wall:.1f} frames/s), CPU all threads {cpu:.1f}, main thread "
          f"{main_cpu:.1f}, other threads {cpu - main_cpu:.1f}; load {os.getloadavg()[0]:.1f}")  # fmt: skip


if __name__ == "__main__":
    main()
