"""What the dense map costs per frame: the default tracker with and without it (``dense=none``) over the same
decoded frames, in one process, the configurations stepping through each frame back to back (in a rotating order, so
that the shared machine's drifting speed falls on all alike); and the map's own calls (align, add) timed from the
outside.

    python experiments/bench/bench_dense_map.py ../shared/data/7scenes_redkitchen --frames 300 --repeats 2 --also dense.every=10

Prints, per configuration (``--also``: more of them, each one override; ``--reference``: the default with the
alignment's fit in pure torch, ``DenseMap._fit_torch``, instead of the compiled operator), the median ms per frame
over the repeats and its ratio to the tracker without the map, and for the default: the calls to
``DenseMap.align`` and ``DenseMap.add`` (count, ms per call, ms per frame) and its voxels at the end. One torch thread
(the CLI's), frames decoded before timing (the tracker is measured, not the loader); wall clock on a shared machine.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.factory import build_tracker


def timed(obj, name: str, log: list[float]) -> None:
    """Wrap ``obj.name`` so that each call's seconds are appended to ``log``."""
    inner = getattr(obj, name)

    def call(*args, **kwargs):
        t = time.perf_counter()
        out = inner(*args, **kwargs)
        log.append(time.perf_counter() - t)
        return out

    setattr(obj, name, call)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("root", type=Path, help="a sequence in TUM layout")
    ap.add_argument("--frames", type=int, default=300, help="its first frames tracked")
    ap.add_argument("--repeats", type=int, default=2, help="runs of each configuration, alternating")
    ap.add_argument("--also", nargs="*", default=[], help="more configurations with the map: Hydra overrides, one each")
    ap.add_argument("--reference", action="store_true", help="also the alignment's pure-torch reference")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    seq = TumSequence(args.root, max_frames=args.frames)
    batches = list(iterate_batched([seq], prefetch=False))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfgs = {"dense map": compose("config"), "without": compose("config", overrides=["dense=none"])}
        cfgs |= {o: compose("config", overrides=[o]) for o in args.also}
        if args.reference:
            cfgs["torch alignment"] = cfgs["dense map"]
    ms: dict[str, list[float]] = {k: [] for k in cfgs}
    calls: dict[str, list[float]] = {"align": [], "add": []}
    for r in range(args.repeats):
        trackers = {name: build_tracker(cfg) for name, cfg in cfgs.items()}
        if "torch alignment" in trackers:
            dense = trackers["torch alignment"].dense
            dense.fit = dense._fit_torch
        if r == args.repeats - 1:
            for k, log in calls.items():
                timed(trackers["dense map"].dense, k, log)
        spent = dict.fromkeys(trackers, 0.0)
        names = list(trackers)
        for i, frame in enumerate(batches):
            # all configurations step through the same frame back to back, in a rotating order: the machine's
            # speed drifts over seconds on a shared host, and this way each configuration sees the same drift
            for name in names[i % len(names) :] + names[: i % len(names)]:
                t = time.perf_counter()
                trackers[name].step(frame)
                spent[name] += time.perf_counter() - t
        for name in names:
            ms[name].append(spent[name] / len(batches) * 1e3)
        voxels = trackers["dense map"].dense.map.size(0)
    med = {k: statistics.median(v) for k, v in ms.items()}
    print(f"{seq.name}, {len(batches)} frames, {args.repeats} repeats, 1 thread")
    for k, v in med.items():
        print(f"  {k:10s} {v:7.2f} ms/frame  (runs: {', '.join(f'{x:.2f}' for x in ms[k])}), "
              f"{v / med['without']:.3f}x without")  # fmt: skip
    print(
        f"  ratio {med['dense map'] / med['without']:.3f}, difference {med['dense map'] - med['without']:+.2f} ms/frame"
    )
    for k, log in calls.items():
        per = sum(log) / len(batches) * 1e3
        print(f"  DenseMap.{k}: {len(log)} calls, {sum(log) / max(len(log), 1) * 1e3:.1f} ms each, {per:.2f} ms/frame")
    print(f"  map: {voxels} voxels")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
