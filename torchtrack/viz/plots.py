"""Trajectory and error plots written as PNG files (matplotlib Agg canvas, no pyplot state, atomic save).

Poses are camera-to-world ``T_world_cam`` (F, 4, 4), numpy arrays or torch tensors, as in TUM files.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from torchtrack.geometry import transform_points
from torchtrack.io import write_atomic
from torchtrack.metrics import PerAxisErrors, ate

_AXES = "xyz"
_COLOURS = ("tab:red", "tab:green", "tab:blue")


def save_atomic(fig: Figure, path_png, dpi: int = 100) -> Path:
    """Render to a temporary file beside ``path_png``, then rename: a reader never sees half a PNG."""
    FigureCanvasAgg(fig)
    return write_atomic(path_png, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi))


def _poses(T, name: str, F: int | None = None) -> torch.Tensor:
    T = torch.as_tensor(T, device="cpu").detach().to(torch.float64)  # a plot: host data
    if T.dim() != 3 or T.shape[-2:] != (4, 4) or (F is not None and T.shape[0] != F):
        want = f"({F}, 4, 4)" if F is not None else "(F, 4, 4)"
        raise ValueError(f"{name} must be {want} poses, got {tuple(T.shape)}")
    return T


def _time_axis(F: int, timestamps) -> tuple[np.ndarray, str]:
    if timestamps is None:
        return np.arange(F), "frame"
    ts = np.asarray(timestamps, dtype=np.float64)
    if ts.shape != (F,):
        raise ValueError(f"timestamps must be ({F},), got {ts.shape}")
    return ts - ts[0], "time [s]"


def _top_view_axes(p: np.ndarray) -> tuple[int, int]:
    """The two world axes of largest extent: the plane seen from 'above' whatever the world's up axis."""
    extent = np.nanmax(p, 0) - np.nanmin(p, 0)
    a, b = sorted(np.argsort(extent)[1:].tolist())
    return a, b


def _draw_top_view(ax, p_est: np.ndarray, p_gt: np.ndarray | None, label_est: str) -> None:
    a, b = _top_view_axes(p_gt if p_gt is not None else p_est)
    if p_gt is not None:
        ax.plot(p_gt[:, a], p_gt[:, b], "k--", lw=1.2, label="ground truth")
    ax.plot(p_est[:, a], p_est[:, b], color="tab:orange", lw=1.2, label=label_est)
    ax.plot(p_est[:1, a], p_est[:1, b], "o", color="tab:orange", ms=5, label="start")
    ax.set(xlabel=f"{_AXES[a]} [m]", ylabel=f"{_AXES[b]} [m]", title=f"top view ({_AXES[a]}{_AXES[b]} plane)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)


def _draw_positions(axes, x, p_est: np.ndarray, x_gt, p_gt: np.ndarray | None, xlabel: str) -> None:
    for k, ax in enumerate(axes):
        if p_gt is not None:
            ax.plot(x_gt, p_gt[:, k], "k--", lw=1)
        ax.plot(x, p_est[:, k], color=_COLOURS[k], lw=1)
        ax.set_ylabel(f"{_AXES[k]} [m]")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel(xlabel)


def plot_trajectory(
    path_png,
    T_est,
    T_gt=None,
    *,
    title: str = "trajectory",
    timestamps=None,
    gt_valid=None,
    align: bool = True,
    dpi: int = 100,
) -> Path:
    """Top view, per-axis position against time and, with ground truth, the ATE per frame.

    Args:
        path_png: output file, written atomically; parent folders are created.
        T_est: (F, 4, 4) estimated ``T_world_cam``.
        T_gt: (F, 4, 4) ground truth or None; rows where ``gt_valid`` (F,) is False are not drawn.
        timestamps: (F,) seconds for the time axis, else frame index.
        align: draw the estimate after the SE(3) Umeyama alignment used by the ATE (as ``evo_ape -a``).
    Returns:
        The written path.
    """
    T_est = _poses(T_est, "T_est")
    F = T_est.shape[0]
    x, xlabel = _time_axis(F, timestamps)
    p_est = T_est[:, :3, 3]
    p_gt, err, label_est, valid = None, None, "estimate", np.ones(F, bool)
    if T_gt is not None:
        T_gt = _poses(T_gt, "T_gt", F)
        valid = np.ones(F, bool) if gt_valid is None else np.asarray(gt_valid, dtype=bool)
        if valid.shape != (F,):
            raise ValueError(f"gt_valid must be ({F},), got {valid.shape}")
        if not valid.any():
            T_gt, valid = None, np.ones(F, bool)
    if T_gt is not None:
        res = ate(T_est[valid], T_gt[valid], align=align)
        if align:
            p_est, label_est = transform_points(res.T_align, p_est), "estimate (SE(3)-aligned)"
        p_gt, err = T_gt[valid, :3, 3].numpy(), res.errors.numpy()  # frames with ground truth only
        title = f"{title}   ATE RMSE {res.rmse_m:.4f} m over {int(valid.sum())} frames"
    p_est = p_est.numpy()
    fig = Figure(figsize=(12, 8 if err is not None else 6), layout="constrained")
    grid = fig.add_gridspec(4 if err is not None else 3, 2, width_ratios=(1, 1.3))
    fig.suptitle(title)
    _draw_top_view(fig.add_subplot(grid[:3, 0]), p_est, p_gt, label_est)
    _draw_positions([fig.add_subplot(grid[k, 1]) for k in range(3)], x, p_est, x[valid], p_gt, xlabel)
    if err is not None:
        ax = fig.add_subplot(grid[3, :])
        ax.plot(x[valid], err, color="tab:purple", lw=1)
        ax.set(xlabel=xlabel, ylabel="ATE [m]", title="absolute trajectory error per frame")
        ax.grid(alpha=0.3)
    return save_atomic(fig, path_png, dpi)


def plot_errors(
    path_png,
    series: Mapping[str, object],
    *,
    x=None,
    xlabel: str = "frame",
    ylabel: str = "error",
    title: str = "",
    dpi: int = 100,
) -> Path:
    """One line per named error series of equal length (F,), e.g. reprojection error (16) of each method.

    NaN entries (frames without a value) leave gaps. The legend shows each series' mean over finite values.
    """
    if not series:
        raise ValueError("plot_errors: no series given")
    ys = {name: np.asarray(torch.as_tensor(v, device="cpu").detach().to(torch.float64)) for name, v in series.items()}
    F = next(iter(ys.values())).shape
    if any(y.ndim != 1 or y.shape != F for y in ys.values()):
        raise ValueError(
            f"plot_errors: every series must be (F,) of one length, got { {k: y.shape for k, y in ys.items()} }"
        )
    x = np.arange(F[0]) if x is None else np.asarray(x)
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax = fig.add_subplot()
    for name, y in ys.items():
        finite = y[np.isfinite(y)]  # an all-NaN series (no frame has a value) has no mean: say so, not NaN
        ax.plot(x, y, lw=1, label=f"{name} (mean {finite.mean():.3g})" if finite.size else f"{name} (no value)")
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    return save_atomic(fig, path_png, dpi)


def plot_per_axis_errors(
    path_png, errors: PerAxisErrors, *, x=None, xlabel: str = "frame", title: str = "", dpi: int = 100
) -> Path:
    """Rotation (degrees) and translation (millimetres) errors per axis against time (Table VI's quantities)."""
    rot, trans = (np.asarray(torch.as_tensor(v, device="cpu")) for v in (errors.rot_deg, 1000 * errors.trans_m))
    x = np.arange(rot.shape[0]) if x is None else np.asarray(x)
    fig = Figure(figsize=(10, 6), layout="constrained")
    fig.suptitle(title)
    for row, (vals, unit, mean) in enumerate(
        ((rot, "deg", errors.rot_mean_deg), (trans, "mm", 1000 * errors.trans_mean_m))
    ):
        ax = fig.add_subplot(2, 1, row + 1)
        for k in range(3):
            ax.plot(x, vals[:, k], color=_COLOURS[k], lw=1, label=f"{_AXES[k]} (mean {float(mean[k]):.3g} {unit})")
        ax.set(xlabel=xlabel, ylabel=f"{'rotation' if row == 0 else 'translation'} error [{unit}]")
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    return save_atomic(fig, path_png, dpi)
