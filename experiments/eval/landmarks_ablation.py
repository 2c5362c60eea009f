"""On/off table of the landmark and re-selection switches on sequences and their variants.

Each configuration (``NAME=override,override``) runs the CLI (``python -m torchtrack.cli``, one torch thread) on every
sequence and variant; the variants come from :func:`torchtrack.data.perturb.make_variant`: ``skipK`` every K-th
frame, ``jitterS`` the ``jitter`` kind with seed S (half a grey level of noise: the run-to-run spread of a chaotic
sequence), and the other kinds by name (seed 0). A finished run (its ``metrics.json``) is not run again.

    python experiments/eval/landmarks_ablation.py --roots /work/shared/data/7scenes_redkitchen \\
        --variants real,jitter1,jitter2,jitter3,skip2,skip3,skip4 --variant-frames 1000 \\
        --configs off= landmarks=landmarks=default --out /tmp/abl

Prints and writes ``OUT/ablation.md``: ATE mm / RPE mm / re-selections per run and configuration, and the median
over the ``jitter`` seeds.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

from torchtrack.data.perturb import make_variant
from torchtrack.io import write_text


def variant_folder(src: Path, name: str, cache: Path, frames: int | None) -> Path:
    """The folder of variant ``name`` of ``src``: real, skipK, jitterS or a perturb kind (seed 0)."""
    if name == "real":
        return src
    m = re.fullmatch(r"jitter(\d+)", name)
    kind, seed = ("jitter", int(m.group(1))) if m else (name, 0)
    return make_variant(src, kind, cache, seed=seed, first=frames)


def run_one(root: Path, out: Path, overrides: list[str], max_frames: int | None) -> dict:
    """The CLI's metrics.json of one run (cached in ``out``)."""
    metrics = out / root.name / "metrics.json"
    if not metrics.exists():
        cmd = [sys.executable, "-m", "torchtrack.cli", "data=tum", f"data.root={root}", f"hydra.run.dir={out}",
               "plots=false", "threads=1", *overrides]  # fmt: skip
        if max_frames is not None:
            cmd.append(f"data.max_frames={max_frames}")
        done = subprocess.run(cmd, capture_output=True, text=True, env=os.environ.copy())
        if done.returncode != 0 or not metrics.exists():
            raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr[-2000:]}")
    return json.loads(metrics.read_text())


def cell(m: dict) -> str:
    return f"{1000 * m['ate_rmse_m']:.1f} / {1000 * m['rpe_trans_m']:.2f} / {m['reselections']}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--roots", nargs="+", type=Path, required=True, help="TUM-layout sequence folders")
    ap.add_argument("--variants", default="real", help="comma-separated: real, skipK, jitterS, reversed, ...")
    ap.add_argument("--variant-frames", type=int, default=None, help="variants from the first N frames (None: all)")
    ap.add_argument("--max-frames", type=int, default=None, help="real runs on the first N frames (None: all)")
    ap.add_argument("--configs", nargs="+", required=True, help="NAME=override,override (NAME= : the default)")
    ap.add_argument("--cache", type=Path, default=Path("/tmp/torchtrack_variants"), help="folder of the built variants")
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    args = ap.parse_args(argv)
    configs = {}
    for c in args.configs:
        name, _, rest = c.partition("=")
        configs[name] = [o for o in rest.split(",") if o]
    rows, results = [], {}
    for src in args.roots:
        for var in args.variants.split(","):
            root = variant_folder(src, var, args.cache, args.variant_frames)
            frames = args.max_frames if var == "real" else None
            for name, overrides in configs.items():
                m = run_one(root, args.out / name / f"{src.name}-{var}", overrides, frames)
                results.setdefault(src.name, {}).setdefault(var, {})[name] = m
                print(f"{src.name} {var} {name}: {cell(m)}", flush=True)
    names = list(configs)
    lines = ["| sequence | variant | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for seq, by_var in results.items():
        for var, by_cfg in by_var.items():
            lines.append(f"| {seq} | {var} | " + " | ".join(cell(by_cfg[n]) for n in names) + " |")
        jit = [v for v in by_var if v.startswith("jitter")]
        if len(jit) > 1:
            med = [statistics.median(1000 * by_var[v][n]["ate_rmse_m"] for v in jit) for n in names]
            lines.append(f"| {seq} | median ATE of {', '.join(jit)} | " + " | ".join(f"{x:.1f}" for x in med) + " |")
    rows = "\n".join(lines)
    text = f"Cells: ATE mm / RPE mm / re-selections. Configurations: {json.dumps(configs)}\n\n{rows}\n"
    write_text(args.out / "ablation.md", text)
    json_path = args.out / "ablation.json"
    write_text(json_path, json.dumps(results, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
