"""Cost of the issue-24 landmark switches (landmarks.measure / warp / refine) against the default, in one process.

Each configuration tracks the same frames (decoded once, kept in memory), runs interleaved round by round; prints the
median ms per frame (wall clock and process CPU time) and its difference and ratio to the default's, and the torch
thread count.

    python experiments/bench/bench_landmark_estimation.py --root ../shared/data/sun3d_fragment1 --frames 50 --repeats 3
    python experiments/bench/bench_landmark_estimation.py --root ../shared/data/sun3d_fragment1 --only default warp \
        --config warp32=landmarks.warp=true,landmarks.warp_crop=32
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.factory import build_sequences, build_tracker

CONFIGS = {
    "default": [],
    "measure": ["landmarks.measure=true"],
    "warp": ["landmarks.warp=true"],
    "refine": ["landmarks.measure=true", "landmarks.refine=true"],
    "all": ["landmarks.measure=true", "landmarks.warp=true", "landmarks.refine=true"],
}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--root", type=Path, required=True, help="sequence folder")
    ap.add_argument("--frames", type=int, default=50, help="frames tracked per run")
    ap.add_argument("--repeats", type=int, default=3, help="runs per configuration")
    ap.add_argument("--only", nargs="+", help="run only these of the built-in configurations (None: all)")
    ap.add_argument(
        "--config",
        action="append",
        default=[],
        metavar="NAME=OVERRIDE,...",
        help="another configuration, e.g. warp32=landmarks.warp=true,landmarks.warp_crop=32",
    )
    a = ap.parse_args()
    configs = {k: v for k, v in CONFIGS.items() if a.only is None or k in a.only or k == "default"}
    for c in a.config:
        name, _, over = c.partition("=")
        configs[name] = over.split(",")
    torch.set_num_threads(1)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfgs = {k: compose("config", overrides=["data=tum", f"data.root={a.root}", f"data.max_frames={a.frames}", *v])
                for k, v in configs.items()}  # fmt: skip
    from torchtrack.data.batching import iterate_batched

    frames = list(iterate_batched(build_sequences(cfgs["default"].data)))
    times: dict[str, list[float]] = {k: [] for k in configs}
    cpu: dict[str, list[float]] = {k: [] for k in configs}  # process CPU time: less sensitive to a loaded machine
    for _ in range(a.repeats):
        for k, cfg in cfgs.items():
            tracker = build_tracker(cfg)
            t, c = time.perf_counter(), time.process_time()
            for f in frames:
                tracker.step(f)
            times[k].append((time.perf_counter() - t) * 1000 / len(frames))
            cpu[k].append((time.process_time() - c) * 1000 / len(frames))
    print(f"{a.root.name}, {len(frames)} frames, {torch.get_num_threads()} torch thread(s), {a.repeats} rounds")
    for label, table in (("wall", times), ("cpu", cpu)):
        base = statistics.median(table["default"])
        for k, v in table.items():
            m = statistics.median(v)
            print(f"{label:4s} {k:8s} {m:7.1f} ms/frame  {m - base:+6.1f} ms  ratio {m / base:.2f}  "
                  f"(rounds: {', '.join(f'{x:.1f}' for x in v)})")  # fmt: skip


if __name__ == "__main__":
    main()
