"""Self-calibration of the learned weighting on unlabelled sequences, measured leave-one-out.

For each of the sequences under ``--data`` (the five shared ones by default):

1. **Record** its front end without ground truth: a copy of the folder without ``groundtruth.txt`` (links to the
   same files) goes through ``torchtrack-record`` (``data.max_frames=--max-frames``), so the windows of the real
   sequences start from the tracker's recorded estimate and nothing in training sees a ground-truth pose of them.
2. **Train** one model per held-out sequence on the other sequences' recordings plus ``--synthetic-windows``
   windows drawn from the synthetic set's recordings (``--synthetic``, with ground truth), with the innovation NLL
   (``train.loss=nll``, the recipe of ``conf/train/default.yaml`` with ``--epochs`` and ``--lr``), starting from the
   shipped model (``--init shipped``: a fine-tune) or from scratch (``--init scratch``). No validation split and no
   model selection: the model after the last epoch is the one tested (the held-out sequence is only the test).
3. **Held-out NLL**: every window of the held-out recording (unlabelled: from the tracker's estimate) replayed through
   the filter with eqs. 11-14 (``paper``), the shipped model and the leave-one-out model; the NLL per used
   measurement pooled over the windows, its spread over the windows (std of the per-window values) and the
   per-window paired difference to ``paper`` (mean +- standard error).
4. **Held-out ATE**: ``experiments/eval/eval_weighting.py`` on the original folders (with ground truth), in process:
   ``weighting=paper``, ``weighting=learned`` (the shipped model, online scale on) and ``weighting=learned`` with
   the leave-one-out model (``--learned loo=OUT/models/loo-{sequence}.pt``), ``--runs R`` jittered re-runs each for
   the spread (median, mean +- std over the R + 1 runs).

Writes ``OUT/selfcal_loo.md`` (the tables) and ``OUT/selfcal_loo.json``; the recordings (``OUT/observations``), the
fold runs (``OUT/folds/<sequence>``: metrics.csv, last.pt; a fold is resumed from its last.pt) and the models
(``OUT/models/loo-<sequence>.pt``). One heavy run: the folds run one after another on one thread.

    python experiments/eval/eval_selfcal_loo.py --out outputs/selfcal_loo --synthetic OBS_SYNTHETIC
    python experiments/eval/eval_selfcal_loo.py --max-frames 300 --epochs 8 --runs 1 --synthetic OBS_SYNTHETIC
    python experiments/eval/eval_selfcal_loo.py --skip-ate ...          # recordings, folds and held-out NLL only

``--synthetic`` is a folder of synthetic recordings (``torchtrack-record +dataset=synthetic out=DIR``; the default is
torchtrack-train's cache, ``$TORCHTRACK_CACHE/observations/synthetic``); ``--synthetic-windows 0`` trains on the real
recordings alone.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

import torch
from common import git_describe
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf
from tqdm import tqdm

from torchtrack.config import CONF_DIR, load_option
from torchtrack.io import write_json, write_text
from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import DEFAULT_CHECKPOINT, build_weighting, load_checkpoint, save_checkpoint
from torchtrack.learn.rollout import concat_windows, rollout
from torchtrack.learn.train import TrainConfig, fit, select_windows, windows_of

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"


def default_synthetic() -> Path:
    root = os.environ.get("TORCHTRACK_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "torchtrack") / "observations" / "synthetic"


# ----------------------------------------------------------------------------------------------- recording


def unlabelled_copy(src: Path, dst_root: Path) -> Path:
    """``dst_root/<name>``: links to every entry of ``src`` but groundtruth.txt (the user's own footage)."""
    dst = dst_root / src.name
    dst.mkdir(parents=True, exist_ok=True)
    for entry in src.iterdir():
        link = dst / entry.name
        if entry.name != "groundtruth.txt" and not link.exists():
            link.symlink_to(entry.resolve())
    return dst


def record(folders: list[Path], out: Path, max_frames: int | None, overrides: list[str]) -> None:
    """torchtrack-record, one sequence at a time (resumable: up-to-date recordings are kept)."""
    for folder in tqdm(folders, desc="recording", unit="sequence"):
        cmd = [sys.executable, "-m", "torchtrack.learn.record_app", "data=tum", f"data.root='{folder}'", f"out={out}",
               "batch=1", "threads=1", f"data.max_frames={max_frames if max_frames else 'null'}", *overrides]  # fmt: skip
        done = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
        if done.returncode != 0:
            raise SystemExit(f"eval_selfcal_loo: recording {folder} failed:\n{done.stderr[-2000:]}")


# ----------------------------------------------------------------------------------------------- training


def train_config(args) -> tuple[TrainConfig, object]:
    """The recipe of conf/learn.yaml (train.loss=nll) with --epochs/--lr, and the filter it trains through."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="learn", overrides=["~dataset", "train.loss=nll", *args.overrides])
    train = OmegaConf.to_container(cfg.train, resolve=True)
    train.update(epochs=args.epochs, lr=args.lr, seed=args.seed)
    tc = TrainConfig(**train)
    return tc, instantiate(cfg.filter)


def synthetic_windows(folder: Path, tc: TrainConfig, n: int, seed: int):
    """``n`` windows drawn (seeded) from every recording in ``folder``; None when n is 0."""
    if n <= 0:
        return None
    files = sorted(folder.glob("*.pt"))
    if not files:
        raise SystemExit(f"eval_selfcal_loo: no synthetic recordings (*.pt) in {folder}; pass --synthetic DIR")
    win = windows_of([load_observations(f) for f in files], tc.window, tc.stride, need_ground_truth=False)
    g = torch.Generator().manual_seed(seed)
    pick = torch.randperm(win.dt.shape[1], generator=g)[: min(n, win.dt.shape[1])]
    return select_windows(win, pick.sort().values)


def initial_model(args, tc: TrainConfig) -> torch.nn.Module:
    torch.manual_seed(tc.seed)
    recipe = build_weighting(tc.model)
    if args.init == "shipped":
        model, _ = load_checkpoint(DEFAULT_CHECKPOINT)
        if model.config.get("mode") != getattr(recipe, "config", {}).get("mode"):
            raise SystemExit(f"eval_selfcal_loo: the shipped model is {model.config}, the recipe {tc.model}")
        return model
    return recipe


def train_fold(held_out: str, real: dict, synth, tc: TrainConfig, ekf, args) -> Path:
    """Train on every real recording but ``held_out`` plus the synthetic windows; the last epoch's model."""
    path = args.out / "models" / f"loo-{held_out}.pt"
    if path.is_file() and args.reuse:
        return path
    parts = [windows_of([s], tc.window, tc.stride, need_ground_truth=False) for n, s in real.items() if n != held_out]
    parts = [w for w in parts if w is not None] + ([synth] if synth is not None else [])
    train = concat_windows(parts)
    model = initial_model(args, tc).train().requires_grad_(True)
    run = args.out / "folds" / held_out
    run.mkdir(parents=True, exist_ok=True)
    extra = {"held_out": held_out, "init": args.init, "train_sequences": sorted(n for n in real if n != held_out),
             "synthetic_windows": 0 if synth is None else int(synth.dt.shape[1])}  # fmt: skip
    t0 = time.perf_counter()
    history = fit(model, ekf, train, tc, out_dir=run, extra=extra, progress=True)
    extra.update(train_windows=int(train.dt.shape[1]), train_s=time.perf_counter() - t0,
                 last_train_nll=history[-1]["train_nll"] if history else float("nan"))  # fmt: skip
    save_checkpoint(path, model.eval(), extra=extra)
    return path


# ----------------------------------------------------------------------------------------------- held-out NLL


def window_nll(ekf, weighting, win, tc: TrainConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,) NLL sums and (B,) used-measurement counts per window (no gradient)."""
    sums, counts = [], []
    with torch.no_grad():
        for i in range(0, win.dt.shape[1], tc.batch):
            idx = torch.arange(i, min(i + tc.batch, win.dt.shape[1]))
            out = rollout(ekf, weighting, select_windows(win, idx), gate=tc.gate, refit=tc.refit, with_nll=True,
                          noise_scale=ekf.noise)  # as training evaluates
            sums.append(out.nll.sum(0).double())
            counts.append(out.n_used.sum(0).double())
    return torch.cat(sums), torch.cat(counts)


def held_out_nll(seq, weightings: dict, ekf, tc: TrainConfig) -> dict:
    """Per weighting: pooled NLL per measurement, std over windows, and the paired difference to ``paper``."""
    win = windows_of([seq], tc.window, tc.stride, need_ground_truth=False)
    per = {}
    for name, w in weightings.items():
        s, n = window_nll(ekf, w, win, tc)
        per[name] = (s, n)
    s0, n0 = per["paper"]
    rows = {"windows": int(win.dt.shape[1])}
    for name, (s, n) in per.items():
        v = s / n.clamp_min(1)
        d = v - s0 / n0.clamp_min(1)
        rows[name] = {"nll": float(s.sum() / n.sum()), "std": float(v.std()), "diff": float(d.mean()),
                      "diff_se": float(d.std() / math.sqrt(len(d))), "better": int((d < 0).sum())}  # fmt: skip
    return rows


# ----------------------------------------------------------------------------------------------- ATE


def ate_runs(args, names: list[str]) -> dict:
    """experiments/eval/eval_weighting.py (a subprocess: scripts do not import scripts) on the labelled folders;
    {sequence: {method: [ATE m per run]}}."""
    argv = ["--data", str(args.data), "--variants", "none", "--weightings", "paper,learned",
            "--learned", f"learned={DEFAULT_CHECKPOINT}", "--learned", f"loo={args.out / 'models'}/loo-{{sequence}}.pt",
            "--runs", str(args.runs), "--out", str(args.out / "ate"), "--threads", "1", *(["--reuse"] if args.reuse else [])]  # fmt: skip
    if args.max_frames:
        argv += ["--max-frames", str(args.max_frames)]
    cmd = [sys.executable, str(REPO / "experiments" / "eval" / "eval_weighting.py"), *argv, "--", *args.overrides]
    if subprocess.run(cmd, cwd=REPO).returncode not in (0, 1):  # 1: some run failed (its cell says so)
        raise SystemExit("eval_selfcal_loo: eval_weighting.py failed")
    rows = json.loads((args.out / "ate" / "weighting.json").read_text())["rows"]
    out = {}
    for r in rows:
        if r["sequence"] in names and r["variant"] == "real":
            out[r["sequence"]] = r.get("noise") or {k: [_ate(v)] for k, v in r["runs"].items()}
    return out


def _ate(run: dict) -> float | None:
    return (run.get("metrics") or {}).get("ate_rmse_m")


def stats(values: list) -> tuple[float, float, float]:
    v = torch.tensor([x for x in values if x is not None], dtype=torch.float64)
    if len(v) == 0:
        return (math.nan,) * 3
    return float(v.median()), float(v.mean()), float(v.std()) if len(v) > 1 else math.nan


# ----------------------------------------------------------------------------------------------- tables


def nll_table(nll: dict) -> str:
    lines = ["| held-out sequence | windows | paper NLL (std) | shipped NLL (std) | LOO NLL (std) | "
             "shipped - paper (se) | LOO - paper (se) | LOO - shipped | LOO better than paper |",
             "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for name, r in nll.items():
        cells = [f"{r[k]['nll']:.3f} ({r[k]['std']:.3f})" for k in ("paper", "shipped", "loo")]
        lines.append(f"| {name} | {r['windows']} | " + " | ".join(cells) + f" | {r['shipped']['diff']:+.3f} "
                     f"({r['shipped']['diff_se']:.3f}) | {r['loo']['diff']:+.3f} ({r['loo']['diff_se']:.3f}) | "
                     f"{r['loo']['nll'] - r['shipped']['nll']:+.3f} | {r['loo']['better']}/{r['windows']} |")  # fmt: skip
    return "\n".join(lines)


def ate_table(ates: dict) -> str:
    lines = ["| held-out sequence | paper ATE mm: median, mean ± std | shipped | LOO | shipped/paper | LOO/paper | "
             "LOO/shipped |", "|---|---|---|---|---|---|---|"]  # fmt: skip
    logs = {"shipped": [], "loo": [], "ls": []}
    for name, runs in ates.items():
        st = {k: stats(runs.get(k, [])) for k in ("paper", "learned", "loo")}
        cells = [f"{1e3 * m:.2f}, {1e3 * mu:.2f} ± {1e3 * sd:.2f}" for m, mu, sd in st.values()]
        r1, r2, r3 = st["learned"][0] / st["paper"][0], st["loo"][0] / st["paper"][0], st["loo"][0] / st["learned"][0]
        for k, r in zip(("shipped", "loo", "ls"), (r1, r2, r3), strict=True):
            logs[k].append(math.log(r))
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {r1:.2f} | {r2:.2f} | {r3:.2f} |")
    gm = {k: math.exp(sum(v) / len(v)) if v else math.nan for k, v in logs.items()}
    lines.append(f"| geometric mean | | | | {gm['shipped']:.3f} | {gm['loo']:.3f} | {gm['ls']:.3f} |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------- main


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and every option's default."""


def parse_args(argv: list[str]) -> argparse.Namespace:
    opts, overrides = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--data", type=Path, default=DATA, help="a folder of sequence folders (with ground truth)")
    ap.add_argument("--sequences", default=None, help="comma-separated names (default: every folder in --data)")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames of every sequence")
    ap.add_argument("--synthetic", type=Path, default=default_synthetic(), help="folder of synthetic recordings")
    ap.add_argument("--synthetic-windows", type=int, default=128, help="synthetic windows added to each fold")
    ap.add_argument("--init", choices=("shipped", "scratch"), default="shipped", help="fine-tune or train anew")
    ap.add_argument("--epochs", type=int, default=8, help="training epochs per fold")
    ap.add_argument("--lr", type=float, default=5e-4, help="learning rate")
    ap.add_argument("--seed", type=int, default=0, help="training seed")
    ap.add_argument("--runs", type=int, default=1, help="jittered re-runs per sequence for the ATE spread")
    ap.add_argument("--skip-ate", action="store_true", help="recordings, training and held-out NLL only")
    ap.add_argument("--reuse", action="store_true", help="keep finished models and tracker runs")
    ap.add_argument("--out", type=Path, default=REPO / "outputs" / "selfcal_loo", help="output folder")
    args = ap.parse_args(opts)
    args.overrides = overrides
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    torch.set_num_threads(1)
    t_start = time.perf_counter()
    sources = sorted(p for p in args.data.iterdir() if (p / "rgb.txt").is_file())
    if args.sequences:
        keep = set(args.sequences.split(","))
        sources = [p for p in sources if p.name in keep]
    if len(sources) < 2:
        raise SystemExit("eval_selfcal_loo: leave-one-out needs at least two sequences")
    names = [p.name for p in sources]
    args.out.mkdir(parents=True, exist_ok=True)
    obs = args.out / "observations"
    record([unlabelled_copy(p, args.out / "unlabelled") for p in sources], obs, args.max_frames, args.overrides)
    real = {n: load_observations(obs / f"{n}.pt") for n in names}
    assert not any(bool(s.T_cam_obj_gt_valid.any()) for s in real.values()), "the recordings must be unlabelled"
    tc, ekf = train_config(args)
    synth = synthetic_windows(args.synthetic, tc, args.synthetic_windows, args.seed)
    paper = instantiate(load_option("weighting", "paper"))
    shipped, _ = load_checkpoint(DEFAULT_CHECKPOINT)
    nll, timing = {}, {}
    for name in tqdm(names, desc="folds", unit="fold"):
        t0 = time.perf_counter()
        model, meta = load_checkpoint(train_fold(name, real, synth, tc, ekf, args))
        timing[name] = meta.get("train_s", math.nan)
        nll[name] = held_out_nll(real[name], {"paper": paper, "shipped": shipped, "loo": model}, ekf, tc)
        print(f"{name}: held-out NLL paper {nll[name]['paper']['nll']:.3f}, shipped {nll[name]['shipped']['nll']:.3f}, "
              f"LOO {nll[name]['loo']['nll']:.3f} ({time.perf_counter() - t0:.0f} s)", flush=True)  # fmt: skip
    ates = {} if args.skip_ate else ate_runs(args, names)
    total = time.perf_counter() - t_start
    command = shlex.join(["python", "experiments/eval/eval_selfcal_loo.py", *argv])
    meta = (f"`{command}`  \ncommit {git_describe()}, torch {torch.__version__}, 1 thread, total {total:.0f} s; "
            f"init {args.init}, {args.epochs} epochs, lr {args.lr}, {args.synthetic_windows} synthetic windows "
            f"per fold, max frames {args.max_frames}, train s per fold: "
            + ", ".join(f"{n} {t:.0f}" for n, t in timing.items()))  # fmt: skip
    body = f"{meta}\n\nHeld-out NLL per measurement (nats; unlabelled windows from the tracker's estimate):\n\n"
    body += nll_table(nll)
    if ates:
        body += f"\n\nHeld-out ATE (mm; the unperturbed run and {args.runs} jittered re-run(s)):\n\n{ate_table(ates)}"
    write_text(args.out / "selfcal_loo.md", f"# Self-calibration, leave-one-out\n\n{body}\n")
    write_json(args.out / "selfcal_loo.json", {"command": command, "nll": nll, "ate": ates, "total_s": total})
    print("\n" + body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
