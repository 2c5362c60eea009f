"""Compare the measurement weightings (fixed, the paper's eqs. 11-14, learned) on every sequence and its perturbed
variants.

For every sequence folder under ``--data`` and its variants (:mod:`torchtrack.data.perturb`: faster motion,
reversed playback, photometric change, noisier depth with holes), this runs torchtrack's default tracker exactly as
the CLI composes it (in-process, ``experiments/eval/evaluate.py``'s ``compose_config`` + ``run_ours``) once per
weighting, reads ATE, RPE and the mean reprojection error back from each run's ``metrics.json`` and prints a
markdown table (rows: sequences and variants; columns: each weighting's numbers and the learned / paper ATE ratio)
with a summary (mean ATE per weighting over the real sequences and over the variants, wins and losses, and the
target's numbers: the geometric mean of the ATE ratios, the real sequences at their median over the jitter runs, and
the rows above 1.05).

    python experiments/eval/eval_weighting.py                                   # fixed, paper, learned; 4 variants
    python experiments/eval/eval_weighting.py --weightings fixed,paper --max-frames 300 --runs 3
    python experiments/eval/eval_weighting.py --checkpoint runs/train/model.pt  # the learned model to evaluate
    python experiments/eval/eval_weighting.py --learned all=ckpt/all.pt --learned loo='ckpt/loo-{sequence}.pt'
    python experiments/eval/eval_weighting.py --results experiments/RESULTS.md -- flow.policy=min_tim
    python experiments/eval/eval_weighting.py --weightings paper --method=default=weighting=paper  # the default vs eqs. 11-14

Weightings: ``fixed`` = ``weighting=fixed`` (the paper's EKF-3 ablation: the variances of
conf/weighting/fixed.yaml for every feature), ``paper`` = ``weighting=paper`` (eqs. 11-14 with the default
improvements; both without the online noise scale, the weighting's R as given; the default with it:
``--method=default=weighting=paper``), ``learned`` = ``weighting=learned`` with the shipped model, or ``--checkpoint PATH``, or one column
per ``--learned NAME=PATH`` (``{sequence}`` in PATH becomes the real sequence's name, also for its variants: a
leave-one-out model per sequence). A learned model whose file is missing is reported and left out (a cell says
``missing`` where only some sequences lack one).

Run-to-run spread (``--runs R``): the tracker is deterministic, so each real sequence is re-run R times on its
``jitter`` variant (colour + Gaussian noise of half a grey level, seeds 1..R, depth unchanged) and the spread of
the R + 1 ATEs (the unperturbed run included) is reported per weighting; a difference smaller than
2 sqrt(std_a^2 + std_b^2) counts as within noise.

Writes ``OUT/weighting.md`` (the table), ``OUT/weighting.json`` and the run folders ``OUT/<weighting>/<name>/``
(trajectory.txt, metrics.json, frames.csv, config.yaml); variants are cached under ``--cache``. With
``--results FILE`` the table also replaces the section ``## Learned weighting: the evaluation table`` of FILE (appended when
absent; the rest of the file is kept), with this command line and the git commit.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import re
import shlex
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from common import compose_config, find_sequences, git_describe, replace_section, run_ours, split_argv
from omegaconf import OmegaConf

from torchtrack.config import CONF_DIR, load_option
from torchtrack.data.perturb import DEFAULTS as PERTURB_DEFAULTS
from torchtrack.data.perturb import make_variant
from torchtrack.io import write_json, write_text

log = logging.getLogger("eval_weighting")

REPO = Path(__file__).resolve().parents[2]
CONF = CONF_DIR
DATA = REPO.parent / "shared" / "data"
HEADING = "## Learned weighting: the evaluation table"
VARIANTS = ("skip3", "reversed", "photometric", "depth_noise")
BASE = {
    "fixed": ["weighting=fixed", "filter.noise_scale=false"],
    "paper": ["weighting=paper", "filter.noise_scale=false"],
}
# the weightings as they give R (eqs. 11-14, EKF-3), without the online noise scale of the default; the default itself
# is the column --method=default=weighting=paper
COLUMNS = (("ate_rmse_m", "ATE mm", 1e3, 2), ("rpe_trans_m", "RPE mm", 1e3, 2), ("rpe_rot_deg", "RPE deg", 1, 3))
COLUMNS += (("mean_reprojection_px", "reproj px", 1, 3),)
NOISE_K = 2.0  # |ATE_a - ATE_b| <= NOISE_K sqrt(std_a^2 + std_b^2): within run-to-run noise
TARGET_MAX = 1.05  # the target's largest ATE ratio per row; its geometric mean is to be <= 0.80


# ----------------------------------------------------------------------------------------------- weightings


@dataclass
class Method:
    """One column group: a label (its output folder), its Hydra overrides, and for learned ones the checkpoint
    (a path pattern with ``{sequence}``, or None for the configured default)."""

    label: str
    overrides: list[str]
    learned: bool = False
    checkpoint: str | None = None

    def checkpoint_for(self, sequence: str) -> Path | None:
        if not self.learned:
            return None
        if self.checkpoint is None:
            return default_checkpoint()
        return Path(self.checkpoint.replace("{sequence}", sequence)).expanduser().resolve()


def default_checkpoint() -> Path:
    """The model ``weighting=learned`` loads when ``weighting.checkpoint`` is not given."""
    cfg = load_option("weighting", "learned")
    if cfg.get("checkpoint") is not None:
        return Path(cfg.checkpoint).expanduser().resolve()
    try:
        from torchtrack.learn.checkpoint import DEFAULT_CHECKPOINT
    except (ImportError, AttributeError):
        return REPO / "torchtrack" / "learn" / "weights" / "default.pt"
    return Path(DEFAULT_CHECKPOINT)


def resolve_methods(
    weightings: list[str], checkpoint: str | None, learned: list[str], custom: list[str] = ()
) -> tuple[list[Method], list]:
    """The methods to run and notes on learned models that cannot run (printed and put under the table); ``custom``:
    ``NAME=OVERRIDES`` columns (space-separated Hydra overrides, e.g. ``learned_off=weighting=learned
    filter.noise_scale=false``), run with the configured model where they select ``weighting=learned``."""
    unknown = sorted(set(weightings) - {"fixed", "paper", "learned"})
    if unknown:
        raise SystemExit(f"eval_weighting: unknown weighting(s) {unknown}; choose from fixed, paper, learned")
    methods = [Method(w, BASE[w]) for w in ("fixed", "paper") if w in weightings]
    models = [tuple(spec.split("=", 1)) for spec in learned]
    if any(len(m) != 2 or not m[0] or not m[1] for m in models):
        raise SystemExit(f"eval_weighting: --learned takes NAME=PATH, got {learned}")
    if not models and ("learned" in weightings or checkpoint):
        models = [("learned", checkpoint)]
    labels = [m.label for m in methods] + [name for name, _ in models]
    if len(set(labels)) != len(labels) or any(not re.fullmatch(r"[\w.-]+", lbl) for lbl in labels):
        raise SystemExit(f"eval_weighting: column names must be distinct words, got {labels}")
    notes = []
    if models and not (CONF / "weighting" / "learned.yaml").is_file():
        notes.append("weighting=learned is not available (conf/weighting/learned.yaml is missing): left out")
        return methods, notes
    for name, path in models:
        method = Method(name, ["weighting=learned"], learned=True, checkpoint=path)
        pattern = path or str(default_checkpoint())
        if "{sequence}" not in pattern and not Path(pattern).expanduser().is_file():
            notes.append(
                f"learned checkpoint missing: {name} = {pattern}: left out (train one with torchtrack-train, then "
                "pass --checkpoint PATH or --learned NAME=PATH)"
            )
            continue
        methods.append(method)
    for spec in custom:
        name, _, text = spec.partition("=")
        if not name or not text or not re.fullmatch(r"[\w.-]+", name) or name in {m.label for m in methods}:
            raise SystemExit(f"eval_weighting: --method takes a new NAME=OVERRIDES, got {spec!r}")
        methods.append(Method(name, shlex.split(text)))
    return methods, notes


# ----------------------------------------------------------------------------------------------- runs


def run_one(root: Path, source: str, method: Method, args, overrides: list[str]) -> dict:
    """One tracker run -> {"metrics": metrics.json as written} | {"missing": checkpoint} | {"error": message}."""
    ckpt = method.checkpoint_for(source)
    if ckpt is not None and not ckpt.is_file():
        return {"missing": str(ckpt)}
    extra = [f"weighting.checkpoint='{ckpt}'"] if ckpt is not None and method.checkpoint is not None else []
    out = args.out / method.label
    folder = out / root.name
    try:
        cfg = compose_config(root, args.max_frames, method.overrides + extra + overrides)
        torch.set_num_threads(int(args.threads or cfg.threads or torch.get_num_threads()))
        resolved = OmegaConf.to_yaml(cfg, resolve=True)
        done = folder / "metrics.json"
        if args.reuse and done.is_file() and (folder / "config.yaml").is_file():
            if (folder / "config.yaml").read_text() == resolved:
                return {"metrics": json.loads(done.read_text()), "reused": True}
        t0 = time.perf_counter()
        name = run_ours(cfg, out, plots=args.plots)["sequence"]
        wall = time.perf_counter() - t0
        return {"metrics": json.loads((out / name / "metrics.json").read_text()), "wall_s": wall}
    except Exception as e:  # one failing run must not lose the others
        log.exception("%s with %s failed", root, method.label)
        return {"error": f"{type(e).__name__}: {e}".splitlines()[0]}


def variant(src: Path, kind: str, args, seed: int = 0) -> Path:
    first = {"first": args.max_frames} if args.max_frames else {}
    return make_variant(src, kind, args.cache, seed=seed, **first)


def evaluate_source(src: Path, methods: list[Method], args, overrides: list[str], emit) -> list[dict]:
    """The rows of one real sequence: itself, then its variants; the real row carries the noise runs."""
    rows = []
    for kind in ("real", *args.variants):
        row = {"sequence": src.name, "variant": kind, "runs": {}}
        try:
            root = src if kind == "real" else variant(src, kind, args)
        except Exception as e:
            log.exception("%s: variant %s failed", src, kind)
            row["error"] = f"{type(e).__name__}: {e}".splitlines()[0]
            rows.append(row)
            emit(row)
            continue
        row["root"] = str(root)
        row["runs"] = {m.label: run_one(root, src.name, m, args, overrides) for m in methods}
        rows.append(row)
        emit(row)
    if args.runs:
        rows[0]["noise"] = noise_runs(src, methods, args, overrides, rows[0])
    return rows


def noise_runs(src: Path, methods: list[Method], args, overrides: list[str], real: dict) -> dict:
    """ATE (m) of the unperturbed run and of R runs on the jitter variant (seeds 1..R), per method."""
    ates = {m.label: [ate(real["runs"][m.label])] for m in methods}
    for seed in range(1, args.runs + 1):
        root = variant(src, "jitter", args, seed=seed)
        for m in methods:
            ates[m.label].append(ate(run_one(root, src.name, m, args, overrides)))
    return ates


def ate(run: dict) -> float | None:
    return (run.get("metrics") or {}).get("ate_rmse_m")


# ----------------------------------------------------------------------------------------------- tables


def comparisons(labels: list[str]) -> list[tuple[str, str]]:
    """(a, b) pairs shown as ATE ratio a/b and wins of a over b: every learned model (or --method column) vs paper,
    else paper vs fixed."""
    learned = [lbl for lbl in labels if lbl not in BASE]
    if "paper" in labels and learned:
        return [(lbl, "paper") for lbl in learned]
    return [("paper", "fixed")] if {"paper", "fixed"} <= set(labels) else []


def fmt(v: float | None, scale: float = 1.0, digits: int = 2) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v * scale:.{digits}f}"


def cell(run: dict | None, key: str, scale: float, digits: int) -> str:
    if run is None:
        return "–"
    if "missing" in run:
        return "missing"
    if "error" in run:
        return "error"
    return fmt(run["metrics"].get(key), scale, digits)


def ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def header(labels: list[str]) -> list[str]:
    cols = ["sequence", "variant", "frames"]
    cols += [f"{lbl} {name}" for lbl in labels for _, name, _, _ in COLUMNS]
    cols += [f"ATE {a}/{b}" for a, b in comparisons(labels)]
    return ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]


def table_row(row: dict, labels: list[str]) -> str:
    runs = row["runs"]
    frames = next((r["metrics"]["frames"] for r in runs.values() if "metrics" in r), None)
    cells = [row["sequence"], row["variant"], "–" if frames is None else str(frames)]
    if "error" in row:
        cells[2] = f"error: {row['error']}"
    for lbl in labels:
        cells += [cell(runs.get(lbl), key, scale, d) for key, _, scale, d in COLUMNS]
    cells += [fmt(ratio(ate(runs.get(a, {})), ate(runs.get(b, {}))), 1, 2) for a, b in comparisons(labels)]
    return "| " + " | ".join(cells) + " |"


def table(rows: list[dict], labels: list[str]) -> str:
    return "\n".join(header(labels) + [table_row(r, labels) for r in rows])


def spread(values: list[float | None]) -> tuple[float, float, float, float] | None:
    """(mean, sample std, min, max) of the finite values; None when fewer than two."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)])
    return None if len(v) < 2 else (float(v.mean()), float(v.std(ddof=1)), float(v.min()), float(v.max()))


def summary(rows: list[dict], labels: list[str]) -> str:
    """Mean ATE per weighting over the real sequences, per variant kind and over all variants; wins/losses."""
    groups = [("real sequences", [r for r in rows if r["variant"] == "real"])]
    kinds = list(dict.fromkeys(r["variant"] for r in rows if r["variant"] != "real"))
    groups += [(k, [r for r in rows if r["variant"] == k]) for k in kinds]
    if len(kinds) > 1:
        groups.append(("all variants", [r for r in rows if r["variant"] != "real"]))
    lines = ["| mean ATE mm | rows | " + " | ".join(labels) + " |", "|" + "---|" * (len(labels) + 2)]
    for name, group in groups:
        complete = [r for r in group if all(ate(r["runs"].get(lbl, {})) is not None for lbl in labels)]
        means = [np.mean([ate(r["runs"][lbl]) for r in complete]) if complete else None for lbl in labels]
        lines.append(f"| {name} | {len(complete)} | " + " | ".join(fmt(m, 1e3, 2) for m in means) + " |")
    lines += [""] + [f"- {wins_losses(rows, a, b)}" for a, b in comparisons(labels)]
    lines += [f"- target: {target(rows, a, b)}" for a, b in comparisons(labels)]
    return "\n".join(lines)


def wins_losses(rows: list[dict], a: str, b: str) -> str:
    """'a vs b': rows where a's ATE is lower (win) / higher (loss); on real sequences with a noise estimate, a
    difference within NOISE_K sqrt(std_a^2 + std_b^2) is counted apart."""
    counts = {"real": [0, 0, 0], "variants": [0, 0, 0]}
    for r in rows:
        x, y = ate(r["runs"].get(a, {})), ate(r["runs"].get(b, {}))
        if x is None or y is None:
            continue
        c = counts["real" if r["variant"] == "real" else "variants"]
        sa, sb = (spread((r.get("noise") or {}).get(k, [])) for k in (a, b))
        if sa and sb and abs(x - y) <= NOISE_K * math.hypot(sa[1], sb[1]):
            c[2] += 1
        elif x < y:
            c[0] += 1
        elif x > y:
            c[1] += 1
    (w, lo, t), (vw, vl, _) = counts["real"], counts["variants"]
    noise = f", {t} within noise" if any(r.get("noise") for r in rows) else ""
    return (
        f"{a} vs {b} (ATE): real sequences {w} wins / {lo} losses{noise}; variants {vw} wins / {vl} losses; "
        f"total {w + vw} / {lo + vl}"
    )


def typical_ate(row: dict, label: str) -> float | None:
    """The row's ATE of ``label``: the median over the unperturbed run and its jitter re-runs where there are any
    (real sequences with --runs), else the one run's."""
    values = [x for x in (row.get("noise") or {}).get(label, []) if x is not None and math.isfinite(x)]
    return float(np.median(values)) if values else ate(row["runs"].get(label, {}))


def target(rows: list[dict], a: str, b: str, limit: float = TARGET_MAX) -> str:
    """The target's numbers for ``a`` over ``b``: the geometric mean of the per-row ATE ratios (medians over the
    jitter runs where there are any) and the rows above ``limit``, those beyond the run-to-run spread marked."""
    ratios, above = [], []
    for r in rows:
        x, y = typical_ate(r, a), typical_ate(r, b)
        if x is None or y is None or y <= 0:
            continue
        ratios.append(x / y)
        if x / y > limit:
            sa, sb = (spread((r.get("noise") or {}).get(k, [])) for k in (a, b))
            within = sa and sb and abs(x - y) <= NOISE_K * math.hypot(sa[1], sb[1])
            above.append(f"{r['sequence']}/{r['variant']} {x / y:.2f}" + (" (within spread)" if within else ""))
    if not ratios:
        return f"{a}/{b}: no row with both ATEs"
    gm = math.exp(float(np.mean(np.log(ratios))))
    return (f"{a}/{b}: geometric mean of the ATE ratio {gm:.3f} over {len(ratios)} rows (median {np.median(ratios):.2f}, "
            f"max {max(ratios):.2f}); above {limit:g}: {', '.join(above) if above else 'none'}")  # fmt: skip


def noise_table(rows: list[dict], labels: list[str], runs: int) -> str:
    lines = [
        "| sequence | runs | " + " | ".join(f"{lbl} ATE mm: mean ± std (min–max)" for lbl in labels) + " |",
        "|" + "---|" * (len(labels) + 2),
    ]
    for r in rows:
        if not r.get("noise"):
            continue
        cells = [r["sequence"], str(runs + 1)]
        for lbl in labels:
            s = spread(r["noise"].get(lbl, []))
            cells.append(
                "–" if s is None else f"{s[0] * 1e3:.2f} ± {s[1] * 1e3:.2f} ({s[2] * 1e3:.2f}–{s[3] * 1e3:.2f})"
            )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def footnotes(args, notes: list[str], rows: list[dict]) -> str:
    ph, dn = PERTURB_DEFAULTS["photometric"], PERTURB_DEFAULTS["depth_noise"]
    out = [
        "ATE: RMSE after SE(3) alignment; RPE: RMSE over consecutive frames (translation mm, rotation deg); reproj: "
        "mean reprojection error (eq. 16) in px; all from each run's metrics.json. ATE a/b: ratio of the two ATEs.",
        "Weightings: fixed = `weighting=fixed` (EKF-3: conf/weighting/fixed.yaml's variances for every feature); "
        "paper = `weighting=paper` (eqs. 11-14 with the default improvements); others = `weighting=learned` with "
        "the model named in the command (the shipped one for `learned` without --checkpoint).",
        f"Variants (torchtrack.data.perturb, seed 0): skipK every K-th frame; reversed: backwards with re-timed "
        f"ground truth; photometric: smooth per-frame gain {list(ph['gain_range'])} / gamma {list(ph['gamma_range'])}, "
        f"x{ph['darken']:g} darker, noise sigma {ph['noise_sigma']:g}; depth_noise: + N(0, ({dn['sigma_k']:g} z^2)^2) "
        f"m, {dn['dropout']:.0%} dropout and {dn['blobs']} hole blobs per frame"
        + (f"; each built from the first {args.max_frames} frames of its sequence." if args.max_frames else "."),
        "Means are over the rows where every weighting has an ATE; wins count rows where the first weighting's ATE "
        "is lower.",
    ]
    if args.runs:
        out.append(
            f"Run-to-run spread: the tracker is deterministic, so each real sequence was re-run {args.runs} time(s) "
            "on its `jitter` variant (colour + i.i.d. Gaussian noise of half a grey level, seeds 1.."
            f"{args.runs}: about a third of the pixels change by one 8-bit level; depth unchanged); mean, sample std "
            "and range over these runs and the unperturbed one. A real-sequence difference within "
            f"{NOISE_K:g} sqrt(std_a^2 + std_b^2) counts as within noise (variants: no estimate, plain comparison)."
        )
    missing = sorted(
        {
            f"{r['sequence']}/{r['variant']}: {run['missing']}"
            for r in rows
            for run in r["runs"].values()
            if "missing" in run
        }
    )
    out += notes + [f"learned checkpoint missing for {m}" for m in missing]
    return "\n".join(f"- {n}" for n in out)


# ----------------------------------------------------------------------------------------------- results file


def write_results(path: Path, body: str) -> None:
    text = path.read_text() if path.is_file() else ""
    write_text(path, replace_section(text, HEADING, body))


# ----------------------------------------------------------------------------------------------- main


def default_cache() -> Path:
    root = os.environ.get("TORCHTRACK_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "torchtrack") / "variants"


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and every option's default."""


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    if "--" in argv:
        i = argv.index("--")
        opts, overrides = argv[:i], argv[i + 1 :]
    else:
        opts, overrides = split_argv(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA, help="a sequence folder or a folder of them")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated kinds ('' or none: real only)")
    ap.add_argument("--weightings", default="fixed,paper,learned", help="comma-separated: fixed, paper, learned")
    ap.add_argument("--checkpoint", default=None, help="the learned model (default: the shipped one)")
    ap.add_argument("--learned", action="append", default=[], metavar="NAME=PATH", help="a learned model column")
    ap.add_argument(
        "--method",
        action="append",
        default=[],
        metavar="NAME=OVERRIDES",
        help="a column of its own Hydra overrides, e.g. 'scale=weighting=paper filter.noise_scale=true'",
    )
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames of every sequence")
    ap.add_argument("--runs", type=int, default=0, help="R jittered re-runs per real sequence: run-to-run spread")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "eval_weighting", help="output folder")
    ap.add_argument("--cache", type=Path, default=default_cache(), help="where the variants are written")
    ap.add_argument("--results", type=Path, default=None, help="markdown file whose table section is replaced")
    ap.add_argument("--reuse", action="store_true", help="keep finished runs whose resolved config is unchanged")
    ap.add_argument("--plots", action="store_true", help="trajectory and feature pictures per run")
    ap.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: the config's)")
    ap.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    args = ap.parse_args(opts)
    args.variants = [v for v in args.variants.split(",") if v and v != "none"]
    args.weightings = [w for w in args.weightings.split(",") if w]
    if args.runs < 0 or (args.max_frames is not None and args.max_frames < 2):
        ap.error("--runs must be >= 0 and --max-frames >= 2")
    return args, overrides


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args, overrides = parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(name)s: %(message)s")
    methods, notes = resolve_methods(args.weightings, args.checkpoint, args.learned, args.method)
    for n in notes:
        print(f"eval_weighting: {n}", file=sys.stderr, flush=True)
    if not methods:
        raise SystemExit("eval_weighting: no weighting to run")
    labels = [m.label for m in methods]
    sources = find_sequences([args.data])
    args.out.mkdir(parents=True, exist_ok=True)
    commit = git_describe()  # the code that runs (others may commit while it does)
    start = time.perf_counter()
    print("\n".join(header(labels)), flush=True)
    rows = []
    for src in sources:
        rows += evaluate_source(src, methods, args, overrides, lambda r: print(table_row(r, labels), flush=True))
    total = time.perf_counter() - start
    command = shlex.join(["python", "experiments/eval/eval_weighting.py", *argv])
    meta = (
        f"`{command}`  \ncommit {commit}, torch {torch.__version__}, {torch.get_num_threads()} thread(s), "
        f"{platform.machine()}, {os.cpu_count()} CPUs, overrides: {overrides or 'none (default config)'}, "
        f"total {total:.0f} s\n"
    )
    body = f"{meta}\n{table(rows, labels)}\n\n{summary(rows, labels)}\n"
    if args.runs:
        body += f"\n### Run-to-run spread of the ATE (--runs {args.runs})\n\n{noise_table(rows, labels, args.runs)}\n"
    body += f"\n{footnotes(args, notes, rows)}\n"
    (args.out / "weighting.md").write_text(f"# Weightings on sequences and perturbed variants\n\n{body}")
    write_json(args.out / "weighting.json", {"command": command, "commit": commit, "total_s": total,
                                             "labels": labels, "notes": notes, "rows": rows})  # fmt: skip
    if args.results:
        write_results(args.results, body)
    print("\n" + body)
    print(f"wrote {args.out / 'weighting.md'}" + (f" and {args.results}" if args.results else "") + f" ({total:.0f} s)")
    failed = any("error" in r or any("error" in run for run in r["runs"].values()) for r in rows)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
