"""Plots of experiments/eval/report.py: grouped bars of Tables III/V/VI and ATE, per-frame reprojection error.

Matplotlib's Agg canvas (no pyplot state); each PNG is written to a temporary name and renamed.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from torchtrack.viz.plots import plot_errors, save_atomic

AXES = ("Rot-x", "Rot-y", "Rot-z", "Tr-x", "Tr-y", "Tr-z")


def grouped_bars(ax, groups: list[str], series: dict[str, list[float | None]], ylabel: str, title: str) -> None:
    """One group of bars per entry of ``groups``, one bar colour per series (None = no bar)."""
    width = 0.8 / max(len(series), 1)
    x = np.arange(len(groups))
    for k, (name, vals) in enumerate(series.items()):
        y = np.array([np.nan if v is None else v for v in vals], dtype=float)
        ax.bar(x + (k - (len(series) - 1) / 2) * width, y, width, label=name)
    ax.set_xticks(x, groups, rotation=15, fontsize=8)
    ax.set(ylabel=ylabel, title=title)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)


def _pivot_series(table: dict, label: Callable[[str], str]) -> tuple[list[str], dict[str, list]]:
    """{seq: {method: value}} -> (sequences, {method label: values per sequence}) without all-empty methods."""
    seqs = list(table)
    methods = list(next(iter(table.values()))) if table else []
    methods = [m for m in methods if any(table[s].get(m) is not None for s in seqs)]
    return seqs, {label(m): [table[s].get(m) for s in seqs] for m in methods}


def write_plots(out: Path, runs: list, numbers: dict, label: Callable[[str], str]) -> list[Path]:
    """reprojection.png (Tables III and V), ate.png, improvement.png (Table VI), frames_<seq>.png.

    Args: runs: report.Run list; numbers: report.Report.numbers; label: method name -> column title.
    """
    paths = []
    fig = Figure(figsize=(11, 4), layout="constrained")
    for i, (key, title) in enumerate((("table3", "Table III"), ("table5", "Table V"))):
        seqs, series = _pivot_series(numbers[key], label)
        grouped_bars(fig.add_subplot(1, 2, i + 1), seqs, series, "mean reprojection error [px]", title)
    paths.append(save_atomic(fig, out / "reprojection.png"))
    ate = {s: {m: None if v is None else 100 * v for m, v in row.items()} for s, row in numbers["ate_rmse_m"].items()}
    seqs, series = _pivot_series(ate, label)
    fig = Figure(figsize=(11, 4), layout="constrained")
    grouped_bars(fig.add_subplot(), seqs, series, "ATE RMSE [cm]", "absolute trajectory error")
    paths.append(save_atomic(fig, out / "ate.png"))
    if numbers["table6"]:
        fig = Figure(figsize=(9, 4), layout="constrained")
        series = {label(b): v["pi"] for b, v in numbers["table6"].items()}
        grouped_bars(fig.add_subplot(), list(AXES), series, "improvement of the proposed tracker [%]", "Table VI")
        paths.append(save_atomic(fig, out / "improvement.png"))
    for seq in sorted({r.sequence for r in runs}):
        per_frame = {label(r.method): r.frames for r in runs if r.sequence == seq and r.frames}
        if not per_frame:
            continue
        F = int(max(row["frame"] for rows in per_frame.values() for row in rows)) + 1
        series = {}
        for name, rows in per_frame.items():
            y = np.full(F, np.nan)
            y[[int(r["frame"]) for r in rows]] = [r["reprojection_px"] for r in rows]
            series[name] = y
        paths.append(plot_errors(out / f"frames_{seq}.png", series, ylabel="reprojection error [px]", title=seq))
    return paths
