"""Turn a sweep folder into the paper's tables (markdown) and plots (PNG).

    python experiments/eval/report.py runs/paper                 # writes runs/paper/report/{REPORT.md,report.json,*.png}
    python experiments/eval/report.py runs/paper --data ../shared/data --out somewhere

Reads every run ``SWEEP/<method>/<job>/<seq>/metrics.json`` (the layout of experiments/eval/sweep.py; a plain
``torchtrack`` output folder moved under ``SWEEP/<method>/`` reads the same), its ``frames.csv`` and
``trajectory.txt``, and the sequence's ``groundtruth.txt`` (found through the job's ``.hydra/config.yaml``
``data.root``, the peer's ``job.json``, or ``--data``). Writes:

* Table II  — mean TIM error of the intensity, SIM and combined trackers: ``SWEEP/table2/table2_tim.md`` from
  experiments/paper/table2_tim.py when present, plus the mean d_TIM the tracker runs logged (combined vs EKF-2).
* Table III — mean reprojection error (16) per sequence: proposed vs ICP, CPD, quaternion.
* Table V   — the same for the ablations of Table IV (EKF-1, EKF-2, EKF-3).
* Table VI  — mean percentage improvement (17) of the proposed tracker over each baseline, per axis, over
  the sequences with ground truth, and the per-axis errors behind it.
* ATE / RPE / fps of every run, the Open3D RGB-D odometry peer included.
* Table I   — ``SWEEP/table1/table1_spread.md`` from experiments/paper/table1_spread.py when present.

Per-axis errors (Table VI) compare object poses as the paper's state does: the scene seen from the first
frame is the object, ``T_cam_obj(t) = inv(T_world_cam(t)) @ T_world_cam(0)``, for the estimate and the
ground truth (:func:`torchtrack.metrics.per_axis_errors`: wrapped Euler-angle and translation differences).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from sweep import METHODS

from torchtrack.io import write_text
from torchtrack.report import NoRunsError, ReportError, RunRecord, markdown_table, tabulate
from torchtrack.report import load_runs as load_records
from torchtrack.report import markdown as settings_markdown

log = logging.getLogger("report")

AXES = ("Rot-x", "Rot-y", "Rot-z", "Tr-x", "Tr-y", "Tr-z")
TABLE3 = ("fusion_ekf", "icp", "cpd", "horn")
TABLE5 = ("fusion_ekf", "paper", "ekf1", "ekf2", "ekf3")
BASELINES = ("icp", "cpd", "horn", "open3d_odometry")
PROPOSED = "fusion_ekf"


@dataclass
class Run:
    """One tracked sequence: ``dir`` holds metrics.json, trajectory.txt and (trackers) frames.csv."""

    method: str
    sequence: str
    dir: Path
    metrics: dict
    frames: list[dict] = field(default_factory=list)
    record: RunRecord | None = None  # as torchtrack-report reads it: the job's overrides

    @property
    def job_dir(self) -> Path:
        return self.dir.parent


def label(method: str) -> str:
    return METHODS[method].label if method in METHODS else method


def read_frames_csv(path: Path) -> list[dict]:
    """frames.csv -> rows with numbers parsed (booleans as bool)."""
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    parse = {"True": True, "False": False, "true": True, "false": False}
    return [{k: parse[v] if v in parse else float(v) for k, v in r.items()} for r in rows]


def load_runs(sweep: Path) -> list[Run]:
    """Every ``SWEEP/<method>/<job>/<seq>/metrics.json``, sorted by sequence, then method (table order).

    The files are found and read by :func:`torchtrack.report.load_runs` (``torchtrack-report``'s reader)."""
    try:
        records = [r for r in load_records(sweep) if len(r.path.relative_to(sweep).parts) == 4]
    except NoRunsError:
        records = []
    if not records:
        raise FileNotFoundError(
            f"no run under {sweep}: expected {sweep}/<method>/<job>/<seq>/metrics.json, as written by "
            f"experiments/eval/sweep.py --out {sweep}"
        )
    runs = [Run(r.path.relative_to(sweep).parts[0], r.sequence, r.path.parent, r.metrics,
                read_frames_csv(r.path.parent / "frames.csv"), r) for r in records]  # fmt: skip
    return sorted(runs, key=lambda r: (r.sequence, _order(r.method)))


def _order(method: str) -> int:
    return list(METHODS).index(method) if method in METHODS else len(METHODS)


# ----------------------------------------------------------------------------------------------- numbers


def mean_reprojection(run: Run) -> float | None:
    """Eq. (16) pooled over all tracked features of all frames after the model frame (Table III's "mean
    reprojection errors of all tracked features"): ``sum_f n_f e_f / sum_f n_f``. Falls back to metrics.json."""
    rows = [r for r in run.frames if r["frame"] > 0 and r["features"] > 0]
    if rows:
        n = np.array([r["features"] for r in rows])
        return float(np.sum(n * np.array([r["reprojection_px"] for r in rows])) / n.sum())
    return run.metrics.get("mean_reprojection_px")


def mean_tim(run: Run) -> float | None:
    """Mean d_TIM (px) that the tracker logged per frame, over the frames after the model frame."""
    vals = [r["mean_tim_px"] for r in run.frames if r["frame"] > 0 and r["features"] > 0]
    return float(np.mean(vals)) if vals else None


def sequence_root(run: Run, data: Path | None) -> Path | None:
    """The sequence folder of a run: the job's Hydra config (data.root), the peer's job.json, or ``data/<seq>``."""
    cfg_path = run.job_dir / ".hydra" / "config.yaml"
    if cfg_path.is_file():
        from omegaconf import OmegaConf

        try:
            root = OmegaConf.load(cfg_path).data.root
            roots = [root] if isinstance(root, str) else list(root)
            match = [Path(r) for r in roots if Path(r).name == run.sequence]
            if match and match[0].is_dir():
                return match[0]
        except Exception as e:  # noqa: BLE001 - an unresolvable config falls back to --data
            log.debug("%s: %s", cfg_path, e)
    job = run.job_dir / "job.json"
    if job.is_file() and Path(json.loads(job.read_text())["data_root"]).is_dir():
        return Path(json.loads(job.read_text())["data_root"])
    if data is not None and (Path(data) / run.sequence).is_dir():
        return Path(data) / run.sequence
    return None


def per_axis(run: Run, data: Path | None, max_dt: float = 0.02) -> np.ndarray | None:
    """Mean per-axis errors (6,): rotation about x, y, z in mrad, translation along x, y, z in mm; None without
    ground truth. Object poses relative to the first frame with ground truth (module docstring)."""
    from torchtrack.data.tum_io import nearest_within, read_tum_trajectory
    from torchtrack.geometry import T_inv
    from torchtrack.metrics import per_axis_errors

    root = sequence_root(run, data)
    if root is None or not (root / "groundtruth.txt").is_file() or not (run.dir / "trajectory.txt").is_file():
        return None
    est = read_tum_trajectory(run.dir / "trajectory.txt")
    gt = read_tum_trajectory(root / "groundtruth.txt")
    idx, ok = nearest_within(est.timestamps, gt.timestamps, max_dt)
    if ok.sum() < 2:
        return None
    import torch

    T_est, T_gt = torch.from_numpy(est.T_world_cam[ok]), torch.from_numpy(gt.T_world_cam[idx[ok]])
    obj_est, obj_gt = T_inv(T_est) @ T_est[0], T_inv(T_gt) @ T_gt[0]  # T_cam_obj, object = scene of frame 0
    e = per_axis_errors(obj_est, obj_gt)
    return np.concatenate([np.deg2rad(e.rot_mean_deg.numpy()) * 1e3, e.trans_mean_m.numpy() * 1e3])


# ----------------------------------------------------------------------------------------------- tables


def fmt(x, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return f"{x:.{digits}f}"


def pivot(runs: list[Run], methods, value) -> dict[str, dict[str, float | None]]:
    """{sequence: {method: value(run)}} for the given methods (absent runs are None)."""
    seqs = sorted({r.sequence for r in runs})
    by = {(r.method, r.sequence): r for r in runs}
    return {s: {m: value(by[(m, s)]) if (m, s) in by else None for m in methods} for s in seqs}


def pivot_table(table: dict[str, dict[str, float | None]], methods, digits: int = 2) -> str:
    """Rows = sequences (+ the mean over sequences where every method has a value), columns = methods."""
    methods = [m for m in methods if any(table[s][m] is not None for s in table)]
    if not methods:
        return "No runs of these methods.\n"
    rows = [[s] + [fmt(table[s][m], digits) for m in methods] for s in table]
    full = [s for s in table if all(table[s][m] is not None for m in methods)]
    if len(full) > 1:
        rows.append([f"mean ({len(full)} seq.)"] + [fmt(np.mean([table[s][m] for s in full]), digits) for m in methods])
    return markdown_table(["sequence"] + [label(m) for m in methods], rows)


def improvement_table(errors: dict[str, dict[str, np.ndarray | None]]) -> tuple[dict, str]:
    """Table VI: eq. (17) per axis for each baseline, averaged over the sequences where both have errors.

    Args: errors {sequence: {method: (6,) per-axis errors or None}}.
    Returns: ({baseline: {"pi": (6,) list, "sequences": [...]}}, markdown).
    """
    out, rows = {}, []
    for base in BASELINES:
        seqs = [s for s, e in errors.items() if e.get(PROPOSED) is not None and e.get(base) is not None]
        if not seqs:
            continue
        pis = np.stack([_improvement(errors[s][PROPOSED], errors[s][base]) for s in seqs])
        mean = pis.mean(0)  # eq. (17) per sequence, then the mean over sequences ("mean percentage improvement")
        out[base] = {"pi": mean.tolist(), "sequences": seqs}
        rows.append([label(base)] + [fmt(v, 1) for v in mean] + [str(len(seqs))])
    if not rows:
        return out, f"No sequence with ground truth and runs of both {label(PROPOSED)} and a baseline.\n"
    return out, markdown_table(["Method / PI (%)", *AXES, "sequences"], rows)


def _improvement(proposed: np.ndarray, baseline: np.ndarray) -> np.ndarray:
    """Eq. (17) per entry; NaN where the baseline error is exactly 0 (improvement undefined)."""
    from torchtrack.metrics import percentage_improvement

    ok = baseline > 0
    return np.where(ok, percentage_improvement(proposed, np.where(ok, baseline, 1.0)).numpy(), np.nan)


def _cm(metrics: dict, key: str) -> float | None:
    return None if metrics.get(key) is None else 100 * metrics[key]


def trajectory_table(runs: list[Run]) -> str:
    """Every run: frames, ATE RMSE (cm), RPE (cm, deg per frame), reprojection (px), fps, re-selections."""
    rows = []
    for r in sorted(runs, key=lambda r: (r.sequence, _order(r.method))):
        m = r.metrics
        rows.append([r.sequence, label(r.method), str(m.get("frames", "–")), fmt(_cm(m, "ate_rmse_m")), fmt(_cm(m, "rpe_trans_m")),
                     fmt(m.get("rpe_rot_deg"), 3), fmt(mean_reprojection(r)), fmt(m.get("fps"), 1),
                     str(m.get("reselections", "–"))])  # fmt: skip
    header = ["sequence", "method", "frames", "ATE RMSE (cm)", "RPE trans (cm/frame)", "RPE rot (deg/frame)",
              "reprojection (px)", "fps", "re-selections"]  # fmt: skip
    return markdown_table(header, rows)


@dataclass
class Report:
    markdown: str
    numbers: dict


def build_report(sweep: Path, data: Path | None = None) -> Report:
    """All tables from the runs under ``sweep`` (and Tables I/II from their scripts' outputs when present)."""
    sweep = Path(sweep)
    runs = load_runs(sweep)
    t3 = pivot(runs, TABLE3, mean_reprojection)
    t5 = pivot(runs, TABLE5, mean_reprojection)
    tim = pivot(runs, (PROPOSED, "ekf2"), mean_tim)
    ate = pivot(runs, list(dict.fromkeys([*METHODS, *(r.method for r in runs)])), lambda r: r.metrics.get("ate_rmse_m"))
    errors = pivot(runs, [PROPOSED, *BASELINES], lambda r: per_axis(r, data))
    errors = {s: e for s, e in errors.items() if any(v is not None for v in e.values())}
    t6, t6_md = improvement_table(errors)
    numbers = {"table3": t3, "table5": t5, "tim_runs": tim, "ate_rmse_m": ate, "table6": t6,
               "per_axis": {s: {m: None if v is None else v.tolist() for m, v in e.items()} for s, e in errors.items()}}  # fmt: skip
    md = [f"# torchtrack: the paper's tables\n\nSweep: `{sweep}` ({len(runs)} runs).\n"]
    md += _included(
        sweep / "table1" / "table1_spread.md", "Table I: 3D spread of features vs pose error", "paper/table1_spread.py"
    )
    md += _included(sweep / "table2" / "table2_tim.md", "Table II: mean TIM error (px)", "paper/table2_tim.py")
    md += ["## Mean d_TIM logged by the tracker runs (px)\n\nCombined tracker (Proposed) vs intensity only (EKF-2).\n",
           pivot_table(tim, (PROPOSED, "ekf2"), 3)]  # fmt: skip
    md += ["## Table III: mean reprojection error (px), eq. (16)\n", pivot_table(t3, TABLE3)]
    md += ["## Table V: mean reprojection error (px) of the ablations (Table IV)\n", pivot_table(t5, TABLE5)]
    md += ["## Table VI: mean percentage improvement (%) of the proposed tracker, eq. (17)\n",
           "Per axis, averaged over the sequences with ground truth; positive = proposed better.\n", t6_md]  # fmt: skip
    md += ["### Per-axis errors behind Table VI (rotation mrad, translation mm)\n", _per_axis_table(errors)]
    md += ["## ATE RMSE (cm)\n", pivot_table({s: {m: None if v is None else 100 * v for m, v in row.items()}
                                              for s, row in ate.items()}, list(next(iter(ate.values()))))]  # fmt: skip
    md += ["## Every run\n", trajectory_table(runs)]
    md += ["## Settings x sequence (as `torchtrack-report` tabulates the sweep)\n",
           settings_markdown(tabulate([r.record for r in runs if r.record is not None]), sweep)]  # fmt: skip
    return Report("\n".join(md), numbers)


def _included(path: Path, title: str, script: str) -> list[str]:
    if path.is_file():
        return [f"## {title}\n", path.read_text()]
    return [f"## {title}\n", f"Not computed: run `python experiments/{script} --out {path.parent}`.\n"]


def _per_axis_table(errors: dict[str, dict[str, np.ndarray | None]]) -> str:
    rows = [[s, label(m)] + [fmt(x, 1) for x in v] for s, e in errors.items() for m, v in e.items() if v is not None]
    return markdown_table(["sequence", "method", *AXES], rows)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, np.ndarray):
        return x.tolist()
    return x


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][report] %(message)s")
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("sweep", type=Path, help="folder written by experiments/eval/sweep.py")
    p.add_argument("--data", type=Path, default=None, help="sequences folder, when the runs do not say where")
    p.add_argument("--out", type=Path, default=None, help="output folder (None: SWEEP/report)")
    p.add_argument("--no-plots", action="store_true", help="tables only, no PNG")
    args = p.parse_args(argv)
    try:  # no sweep there (or a sequence's ground truth missing): one line, no traceback
        if not args.sweep.is_dir():
            raise FileNotFoundError(f"{args.sweep} is not a folder")
        report = build_report(args.sweep, args.data)
    except (FileNotFoundError, ReportError) as e:
        print(f"report.py: error: {e}", file=sys.stderr)
        return 2
    out = args.out or args.sweep / "report"
    write_text(out / "REPORT.md", report.markdown)
    write_text(out / "report.json", json.dumps(_jsonable(report.numbers), indent=2) + "\n")
    if not args.no_plots:
        from report_plots import write_plots

        write_plots(out, load_runs(args.sweep), report.numbers, label)
    print(report.markdown)
    log.info("wrote %s", out / "REPORT.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
