"""``torchtrack-report``: one table from any run or multirun folder.

    torchtrack -m filter.iterations=1,2 data.scene.seed=0,1 hydra.sweep.dir=runs/iters
    torchtrack-report runs/iters                                  # markdown on stdout
    torchtrack-report runs/iters --csv iters.csv --plot iters.png

Every ``metrics.json`` below the folder is one tracked sequence (:mod:`torchtrack.run` writes it last). Its run's
settings are the overrides of the nearest Hydra job folder above it (``.hydra/overrides.yaml``; a peer's
``job.json`` ``overrides``; else the resolved ``.hydra/config.yaml``). The overrides that differ between runs are the
setting; those that follow the sequence (the same value for every run of a sequence, as ``data.root`` in a sweep
over sequences) and the seed keys are not. Runs that share a setting and a sequence (seeds, repeated runs) give one
row with the median of each column. A seed key's value written ``seed<value>`` in a sequence name (the synthetic
scenes do) is replaced by ``seed*``, so the seeds of one scene are one sequence.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import re
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path

import yaml

DEFAULT_SEED_KEYS = ("seed", "data.scene.seed")
# (CSV column, markdown header, metrics.json key, factor, markdown digits)
COLUMNS = (
    ("frames", "frames", "frames", 1.0, 0),
    ("ate_rmse_mm", "ATE RMSE (mm)", "ate_rmse_m", 1e3, 2),
    ("rpe_trans_mm", "RPE trans (mm/frame)", "rpe_trans_m", 1e3, 2),
    ("rpe_rot_deg", "RPE rot (deg/frame)", "rpe_rot_deg", 1.0, 3),
    ("fps", "fps", "fps", 1.0, 1),
)


class ReportError(Exception):
    """A folder or file the report cannot use; the message is one line."""


class NoRunsError(ReportError):
    """The folder holds no ``metrics.json`` (or is no folder)."""


@dataclass
class RunRecord:
    """One tracked sequence: its ``metrics.json`` and the overrides of the job that wrote it."""

    path: Path
    sequence: str
    metrics: dict
    overrides: dict[str, str]

    @property
    def complete(self) -> bool:
        return self.metrics.get("complete", True) is not False


@dataclass
class Row:
    """The runs of one setting on one sequence; ``values`` holds each column's median (None: no run has it)."""

    setting: tuple[str | None, ...]
    sequence: str
    runs: list[RunRecord]
    values: dict[str, float | None] = field(default_factory=dict)
    ate_range_mm: tuple[float, float] | None = None  # min, max over the runs


@dataclass
class Table:
    keys: list[str]  # the setting's overrides, one column each
    rows: list[Row]
    seed_keys: list[str]  # the seed keys that vary in these runs
    common: dict[str, str]  # overrides every run shares
    per_sequence: list[str]  # differing overrides that follow the sequence
    incomplete: list[RunRecord]


# ----------------------------------------------------------------------------------------------- reading


def parse_override(text: str) -> tuple[str, str]:
    """``key=value`` -> (key, value) with Hydra's ``+``, ``++``, ``~`` prefixes dropped (a deletion reads ``<deleted>``)."""
    key, eq, value = str(text).partition("=")
    value = value.replace("\\{", "{").replace("\\}", "}")  # Hydra escapes an interpolation's braces when it records it
    if key.startswith("~"):
        return key.lstrip("~"), value if eq else "<deleted>"
    return key.lstrip("+"), value


def _flatten(cfg, prefix: str = "") -> dict[str, str]:
    if isinstance(cfg, dict):
        return {k: v for key, sub in cfg.items() for k, v in _flatten(sub, f"{prefix}{key}.").items()}
    return {prefix.rstrip("."): json.dumps(cfg) if isinstance(cfg, list) else str(cfg)}


def _read(path: Path, parse):
    try:
        return parse(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, yaml.YAMLError) as e:
        why = " ".join(str(e).split()) or type(e).__name__
        raise ReportError(f"cannot read {path}: {why}") from None


def job_overrides(seq_dir: Path, root: Path) -> dict[str, str]:
    """The overrides of the job above ``seq_dir`` (itself included, up to ``root``); {} when none is recorded."""
    for d in [seq_dir, *seq_dir.parents]:
        if (d / ".hydra" / "overrides.yaml").is_file():
            items = _read(d / ".hydra" / "overrides.yaml", yaml.safe_load) or []
            return dict(parse_override(o) for o in items)
        if (d / "job.json").is_file():
            return dict(parse_override(o) for o in _read(d / "job.json", json.loads).get("overrides", []))
        if (d / ".hydra" / "config.yaml").is_file():
            return _flatten(_read(d / ".hydra" / "config.yaml", yaml.safe_load) or {})
        if d == root:
            break
    return {}


def load_runs(root: str | Path) -> list[RunRecord]:
    """Every ``metrics.json`` below ``root``, with its job's overrides. ReportError (one line) when there is none
    or one cannot be read."""
    root = Path(root)
    if not root.is_dir():
        raise NoRunsError(f"{root} is not a folder")
    paths = sorted(p for p in root.rglob("metrics.json") if p.is_file())
    if not paths:
        raise NoRunsError(f"no metrics.json below {root}: not a torchtrack run or multirun folder")
    runs = []
    for p in paths:
        metrics = _read(p, json.loads)
        if not isinstance(metrics, dict):
            raise ReportError(f"cannot read {p}: not a JSON object")
        seq = str(metrics.get("sequence", p.parent.name))
        runs.append(RunRecord(p, seq, metrics, job_overrides(p.parent, root)))
    return runs


# ----------------------------------------------------------------------------------------------- tabulating


def _natural(value: str | None) -> tuple:
    if value is None:
        return (0, 0.0, "")
    try:
        return (1, float(value), value)
    except ValueError:
        return (2, 0.0, value)


def _median(values: list) -> float | None:
    vals = [float(v) for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    return statistics.median(vals) if vals else None


def sequence_label(run: RunRecord, seed_keys: list[str]) -> str:
    """The run's sequence name with ``seed<value>`` of its seed key replaced by ``seed*``."""
    name = run.sequence
    for k in seed_keys:
        if k in run.overrides:
            name = re.sub(rf"(?<![A-Za-z0-9])seed{re.escape(run.overrides[k])}(?![0-9])", "seed*", name)
    return name


def tabulate(runs: list[RunRecord], seed_keys: tuple[str, ...] | list[str] = DEFAULT_SEED_KEYS) -> Table:
    """Group complete runs by (setting, sequence) and take each column's median (module docstring)."""
    done = [r for r in runs if r.complete]
    incomplete = [r for r in runs if not r.complete]
    if not done:
        raise ReportError(
            f"all {len(runs)} runs are incomplete: {incomplete[0].path}: {incomplete[0].metrics.get('error')}"
        )
    keys = list(dict.fromkeys(k for r in done for k in r.overrides))
    differing = [k for k in keys if len({r.overrides.get(k) for r in done}) > 1]
    seeds = [k for k in differing if k in seed_keys]
    labels = [sequence_label(r, seeds) for r in done]
    per_sequence = []
    for k in (k for k in differing if k not in seeds):
        by_seq: dict[str, set] = {}
        for r, s in zip(done, labels, strict=True):
            by_seq.setdefault(s, set()).add(r.overrides.get(k))
        if all(len(v) == 1 for v in by_seq.values()):
            per_sequence.append(k)
    setting = [k for k in differing if k not in seeds and k not in per_sequence]
    groups: dict[tuple, list[RunRecord]] = {}
    for r, s in zip(done, labels, strict=True):
        groups.setdefault((tuple(r.overrides.get(k) for k in setting), s), []).append(r)
    order = sorted(groups, key=lambda g: ([_natural(v) for v in g[0]], g[1]))
    rows = [_row(st, seq, groups[(st, seq)]) for st, seq in order]
    common = {k: done[0].overrides[k] for k in keys if k not in differing and k in done[0].overrides}
    return Table(setting, rows, seeds, common, per_sequence, incomplete)


def _row(setting: tuple, sequence: str, runs: list[RunRecord]) -> Row:
    values = {col: _median([r.metrics.get(key) for r in runs]) for col, _, key, _, _ in COLUMNS}
    values = {col: None if v is None else v * f for (col, _, _, f, _), v in zip(COLUMNS, values.values(), strict=True)}
    ates = [1e3 * r.metrics["ate_rmse_m"] for r in runs if isinstance(r.metrics.get("ate_rmse_m"), (int, float))]
    return Row(setting, sequence, runs, values, (min(ates), max(ates)) if ates else None)


# ----------------------------------------------------------------------------------------------- output


def _fmt(v: float | None, digits: int) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub markdown table (``|`` inside a cell escaped)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(c.replace("|", "\\|") for c in r) + " |" for r in rows]) + "\n"


def markdown(table: Table, root: str | Path | None = None) -> str:
    """The table and, below it, what it left out or holds fixed."""
    header = [*table.keys, "sequence", "runs", *(h for _, h, _, _, _ in COLUMNS)]
    rows = [
        [("–" if v is None else v) for v in r.setting]
        + [r.sequence, str(len(r.runs))]
        + [_fmt(r.values[col], d) for col, _, _, _, d in COLUMNS]
        for r in table.rows
    ]
    n = sum(len(r.runs) for r in table.rows)
    where = f" under `{root}`" if root is not None else ""
    over = f" over {', '.join(f'`{k}`' for k in table.seed_keys)}" if table.seed_keys else ""
    notes = [f"{n} run{'s' if n != 1 else ''}{where}; a row of several runs shows their medians{over}."]
    if not table.keys:
        notes.append("No override differs between the runs.")
    if table.common:
        notes.append("Every run: " + " ".join(f"`{k}={v}`" for k, v in table.common.items()) + ".")
    if table.per_sequence:
        notes.append("Following the sequence: " + ", ".join(f"`{k}`" for k in table.per_sequence) + ".")
    for r in table.incomplete:
        notes.append(f"Left out, incomplete: `{r.path}`: {r.metrics.get('error', 'no reason recorded')}.")
    return markdown_table(header, rows) + "\n" + "\n".join(f"- {s}" for s in notes) + "\n"


def to_csv(table: Table) -> str:
    """One line per row: the setting's overrides, sequence, runs, then the medians at full precision."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*table.keys, "sequence", "runs", *(col for col, _, _, _, _ in COLUMNS)])
    for r in table.rows:
        vals = [_exact(r.values[col]) for col, _, _, _, _ in COLUMNS]
        w.writerow([*("" if v is None else v for v in r.setting), r.sequence, len(r.runs), *vals])
    return buf.getvalue()


def _exact(v: float | None) -> str:
    return "" if v is None else str(int(v)) if float(v).is_integer() else repr(v)


def setting_label(table: Table, row: Row) -> str:
    parts = [f"{k}={'–' if v is None else v}" for k, v in zip(table.keys, row.setting, strict=True)]
    return ", ".join(parts) or "all runs"


def plot_ate(table: Table, path: str | Path) -> Path:
    """Grouped bars: per sequence, one bar per setting (median ATE RMSE, whiskers min to max over its runs)."""
    import numpy as np
    from matplotlib.figure import Figure

    from torchtrack.viz.plots import save_atomic

    seqs = list(dict.fromkeys(r.sequence for r in table.rows))
    settings = list(dict.fromkeys(r.setting for r in table.rows))
    cell = {(r.setting, r.sequence): r for r in table.rows}
    fig = Figure(figsize=(max(6.0, 1.2 * len(seqs) * max(1, len(settings)) ** 0.5 + 3), 4), layout="constrained")
    ax = fig.add_subplot()
    width, x = 0.8 / len(settings), np.arange(len(seqs))
    for k, st in enumerate(settings):
        rows = [cell.get((st, s)) for s in seqs]
        y = np.array(
            [np.nan if r is None or r.values["ate_rmse_mm"] is None else r.values["ate_rmse_mm"] for r in rows]
        )
        lo = np.array([0.0 if r is None or r.ate_range_mm is None else r.ate_range_mm[0] for r in rows])
        hi = np.array([0.0 if r is None or r.ate_range_mm is None else r.ate_range_mm[1] for r in rows])
        err = np.nan_to_num(np.stack([y - lo, hi - y]).clip(min=0))
        label = setting_label(table, next(r for r in rows if r is not None))
        ax.bar(x + (k - (len(settings) - 1) / 2) * width, y, width, yerr=err, capsize=3, label=label)
    ax.set_xticks(x, seqs, rotation=15, fontsize=8)
    ax.set(ylabel="ATE RMSE [mm] (median, min-max)", title="ATE per sequence and setting")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    return save_atomic(fig, Path(path))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="torchtrack-report",
        description="One table from any run or multirun folder: the overrides that differ between its runs x "
        "sequence -> ATE, RPE, fps (medians over seeds), as markdown on stdout.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("folder", type=Path, help="a run or multirun folder (any folder with metrics.json below it)")
    p.add_argument("--csv", type=Path, default=None, help="also write the table as CSV to this file")
    p.add_argument("--plot", type=Path, default=None, help="also write a grouped bar chart of ATE to this PNG")
    p.add_argument("--seed-key", action="append", default=None, metavar="KEY",
                   help=f"an override whose runs are repeats to take the median over (repeatable; default: "
                        f"{', '.join(DEFAULT_SEED_KEYS)})")  # fmt: skip
    args = p.parse_args(argv)
    try:
        table = tabulate(load_runs(args.folder), tuple(args.seed_key or DEFAULT_SEED_KEYS))
        if args.csv is not None:
            from torchtrack.io import write_text

            write_text(args.csv, to_csv(table))
        if args.plot is not None:
            plot_ate(table, args.plot)
    except (ReportError, OSError) as e:
        print(f"torchtrack-report: error: {e}", file=sys.stderr)
        return 2
    print(markdown(table, args.folder), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
