"""Training a learned weighting through the differentiable fusion EKF (``torchtrack-train``).

Recorded observations (:mod:`torchtrack.learn.cache`) are cut into windows of T frames (:func:`sequence_windows`);
each window is replayed through the weighting and the back end (:func:`torchtrack.learn.rollout.rollout`) from the
pose of its first frame (ground truth, or the tracker's recorded estimate where there is none), and one of two
losses is backpropagated into the weighting:

* ``supervised``: the pose error against ground truth over the window (translation in metres and rotation in
  radians, weighted; :func:`~torchtrack.learn.rollout.supervised_loss`);
* ``nll``: the negative log-likelihood of the innovations under the filter's predicted innovation covariance
  (:func:`~torchtrack.learn.rollout.nll_loss`) — needs no ground truth, so any recorded RGB-D footage serves
  (self-calibration on the user's sensor); the validation then reports the NLL, and pose errors only over the
  frames that have ground truth (NaN without).

Adam with gradient-norm clipping, seeded and deterministic (one thread); each epoch validates on held-out
sequences and keeps the best checkpoint by the validation loss. A run folder holds ``metrics.csv`` (one row per
epoch), ``loss.png``, ``last.pt`` (model, optimiser, epoch: resume) and ``best.pt`` (the model to use), both in the
checkpoint format of :mod:`torchtrack.learn.checkpoint` with the resolved config.

References: Haarnoja et al., "Backprop KF" (NeurIPS 2016); Abbeel et al., "Discriminative training of Kalman
filters" (RSS 2005).
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn
from tqdm import tqdm

from torchtrack.filter.fusion import FusionEKF
from torchtrack.io import write_atomic
from torchtrack.learn.cache import SequenceObservations
from torchtrack.learn.checkpoint import load_checkpoint, save_checkpoint, weighting_spec
from torchtrack.learn.rollout import (
    PER_WINDOW,
    Windows,
    concat_windows,
    nll_loss,
    pose_errors,
    rollout,
    supervised_loss,
)

log = logging.getLogger(__name__)
LOSSES = ("supervised", "nll")


@dataclass
class TrainConfig:
    """Schema of the ``train`` config group (conf/train/*.yaml).

    Attributes:
        window: T, frames per window (truncated backpropagation); stride: frames between window starts.
        batch: windows per optimiser step (replayed together, batched in the back end).
        epochs, lr, weight_decay, clip: Adam and the gradient-norm clip.
        loss: "supervised" or "nll"; w_trans (1/m), w_rot (1/rad): the supervised loss's weights.
        gate, refit: the back end's chi-square quantiles during training (None = off), as in the tracker.
        seed: torch seed of the initialisation and the window order.
        model: the weighting's config node: ``_target_`` (a dotted path; absent: the shipped
            :class:`~torchtrack.learn.model.LearnedWeighting`) and its constructor arguments, null ones left to
            their defaults (:func:`~torchtrack.learn.checkpoint.build_weighting`).
        max_windows: cap on the training windows per epoch (random subset each epoch; None = all).
        noise_scale: replay the filter's online noise scale as the tracker runs it (R = k R0, k from the scale the
            tracker had at the window's start; needs a filter with the scale on), else the weighting's R0 alone.
    """

    window: int = 8
    stride: int = 4
    batch: int = 32
    epochs: int = 30
    lr: float = 1e-3
    weight_decay: float = 0.0
    clip: float = 1.0
    loss: str = "nll"
    w_trans: float = 1.0
    w_rot: float = 1.0
    gate: float | None = 0.999
    refit: float | None = 0.999
    seed: int = 0
    max_windows: int | None = None
    noise_scale: bool = True
    model: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"train.loss must be one of {LOSSES}, got {self.loss!r}")
        if self.window < 1 or self.stride < 1 or self.batch < 1 or self.epochs < 0 or self.lr <= 0:
            raise ValueError("train: window, stride, batch must be >= 1, epochs >= 0 and lr > 0")


# -- windows ---------------------------------------------------------------------------------------------
def sequence_windows(
    seq: SequenceObservations, window: int, stride: int, *, need_ground_truth: bool = True
) -> Windows | None:
    """All windows of ``window`` updates of one recorded sequence, starting every ``stride`` frames.

    A window starting at frame s replays the updates of frames s+1..s+window from the pose of frame s: the model's
    pose where a model was selected at s (exact), else its ground truth, else (only with ``need_ground_truth``
    False) the tracker's recorded estimate ``T_cam_obj_est[s]`` — the pose the tracker itself had there, so an
    unlabelled window replays what the tracker saw. With ``need_ground_truth`` (the supervised loss), windows whose
    start has no ground truth, or with no ground truth at all, are left out; without it (the innovation NLL, which
    needs none) every window is kept and ``gt_valid`` marks the frames a pose error can be measured on. Returns None
    when no window is left.
    """
    starts = [s for s in range(0, seq.frames - window, stride) if not need_ground_truth or _startable(seq, s)]
    if not starts:
        return None
    s = torch.tensor(starts, device=seq.valid.device)
    rows = s[None, :] + torch.arange(1, window + 1, device=s.device)[:, None]  # T,B: the updates of each window
    gt_or_est = torch.where(seq.T_cam_obj_gt_valid[s][:, None, None], seq.T_cam_obj_gt[s], seq.T_cam_obj_est[s])
    start_pose = torch.where(seq.reselected[s][:, None, None], seq.model_T_cam_obj[s], gt_or_est)
    B = len(starts)
    win = Windows(
        start_T_cam_obj=start_pose,
        dt=seq.dt[rows],
        points_obj=seq.points_obj[rows],
        points_d=seq.points_d[rows],
        pixels=seq.pixels[rows],
        valid=seq.valid[rows],
        has_depth=seq.has_depth[rows],
        cues=seq.cues[rows],
        K=seq.K.expand(B, 3, 3),
        T_color_depth=seq.T_color_depth.expand(B, 4, 4),
        focal=seq.K_depth[0, 0].expand(B),
        reselected=seq.reselected[rows],
        model_T_cam_obj=seq.model_T_cam_obj[rows],
        T_cam_obj_gt=seq.T_cam_obj_gt[rows],
        gt_valid=seq.T_cam_obj_gt_valid[rows],
        start_noise=seq.noise_scale[s],
        start_noise_dof=seq.noise_dof[s],
    )
    if not need_ground_truth:
        return win
    keep = win.gt_valid.any(0)
    return select_windows(win, keep.nonzero().squeeze(1)) if bool(keep.any()) else None


def _startable(seq: SequenceObservations, s: int) -> bool:
    return bool(seq.reselected[s]) or bool(seq.T_cam_obj_gt_valid[s])


def select_windows(win: Windows, index: Tensor) -> Windows:
    """The windows ``index`` (1-D) of a batch."""
    return Windows(**{
        f.name: getattr(win, f.name)[index] if f.name in PER_WINDOW else getattr(win, f.name)[:, index]
        for f in fields(Windows)
    })  # fmt: skip


def windows_of(
    sequences: list[SequenceObservations], window: int, stride: int, *, need_ground_truth: bool = True
) -> Windows | None:
    """The windows of every sequence (:func:`sequence_windows`), concatenated; None when there are none."""
    parts = [sequence_windows(s, window, stride, need_ground_truth=need_ground_truth) for s in sequences]
    parts = [w for w in parts if w is not None]
    return concat_windows(parts) if parts else None


# -- the loop ---------------------------------------------------------------------------------------------
Sums = dict[str, tuple[float, float]]  # diagnostic -> (sum, count): batches add up, then one division (summarise)


def window_loss(ekf: FusionEKF, model: Callable, win: Windows, cfg: TrainConfig) -> tuple[Tensor, Sums]:
    """The configured loss of one batch of windows, and its diagnostics as (sum, count) pairs: the loss over its
    own count (measurements for nll, frames with ground truth for supervised), the pose errors over the frames with
    ground truth, the NLL over the used measurements. :func:`summarise` turns them into means."""
    nll = cfg.loss == "nll"
    out = rollout(ekf, model, win, gate=cfg.gate, refit=cfg.refit, with_nll=nll,
                  noise_scale=ekf.noise if cfg.noise_scale else None)  # fmt: skip
    loss = nll_loss(out) if nll else supervised_loss(out, win, cfg.w_trans, cfg.w_rot)
    with torch.no_grad():
        e_t, e_r = pose_errors(out.T_cam_obj, win.T_cam_obj_gt.to(out.T_cam_obj.dtype))
        m = win.gt_valid
        n_gt, n_used = float(m.sum()), float(out.n_used.sum())
        sums = {
            "loss": (float(out.nll.sum()), n_used) if nll else (float(loss) * n_gt, n_gt),  # nll: the sum itself
            "trans_mm": (1e3 * float(e_t[m].sum()), n_gt),
            "rot_deg": (math.degrees(float(e_r[m].sum())), n_gt),
            "nll": (float(out.nll.sum()), n_used if nll else 0.0),
        }
    return loss, sums


def add_sums(total: Sums, sums: Sums) -> Sums:
    """``total`` plus ``sums``, key by key."""
    for k, (v, n) in sums.items():
        v0, n0 = total.get(k, (0.0, 0.0))
        total[k] = (v0 + v, n0 + n)
    return total


def summarise(total: Sums) -> dict[str, float]:
    """Means of the summed diagnostics; NaN where nothing was counted (e.g. pose errors without ground truth)."""
    return {k: v / n if n > 0 else float("nan") for k, (v, n) in total.items()}


def evaluate(ekf: FusionEKF, model: Callable, win: Windows, cfg: TrainConfig) -> dict[str, float]:
    """Diagnostics over all windows of ``win`` (batches of cfg.batch, no gradient): the loss and the NLL per
    measurement, the pose errors per frame with ground truth (NaN where ``win`` has none)."""
    total: Sums = {}
    B = win.dt.shape[1]
    with torch.no_grad():
        for i in range(0, B, cfg.batch):
            idx = torch.arange(i, min(i + cfg.batch, B), device=win.dt.device)
            add_sums(total, window_loss(ekf, model, select_windows(win, idx), cfg)[1])
    return summarise(total)


def fit(
    model: nn.Module,
    ekf: FusionEKF,
    train: Windows,
    cfg: TrainConfig,
    *,
    val: Windows | None = None,
    out_dir: Path | None = None,
    extra: dict | None = None,
    progress: bool = True,
    spec: Mapping[str, Any] | None = None,
    baselines: Mapping[str, Mapping[str, float]] | None = None,
) -> list[dict]:
    """Train ``model`` (a weighting: WeightingInputs -> Variances, with parameters) on the windows ``train``; returns
    one dict of metrics per epoch.

    ``baselines``: other weightings' :func:`evaluate` on the same validation windows (name -> metrics, e.g. eqs.
    11-14 and the fixed weighting): each epoch's log line and metrics.csv row put the model beside them
    (:func:`epoch_report`).

    With ``out_dir``: metrics.csv, loss.png, last.pt (resumed from when present) and best.pt (lowest validation
    loss, or training loss without ``val``) are written there; ``extra`` (e.g. the resolved config) goes into both
    checkpoints, and ``spec``, the config node ``model`` was built from (``{"_target_": ..., **kwargs}``: None for a
    model with ``.config``), rebuilds it (:func:`~torchtrack.learn.checkpoint.save_checkpoint`).
    """
    torch.manual_seed(cfg.seed)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    if out_dir is not None:  # before the first epoch: a model that cannot be saved fails now, not after one
        spec = weighting_spec(model, spec)
    history, start = _resume(model, opt, out_dir, spec)
    B = train.dt.shape[1]
    best = min((h["select"] for h in history), default=float("inf"))
    epochs = tqdm(range(start, cfg.epochs), desc="training", unit="epoch", disable=not progress, initial=start,
                  total=cfg.epochs)  # fmt: skip
    for epoch in epochs:
        g = torch.Generator().manual_seed(cfg.seed * 100_003 + epoch)  # the order depends on (seed, epoch) only
        order = torch.randperm(B, generator=g)
        if cfg.max_windows is not None:
            order = order[: cfg.max_windows]
        model.train()
        total: Sums = {}
        for i in range(0, len(order), cfg.batch):
            idx = order[i : i + cfg.batch]
            loss, sums = window_loss(ekf, model, select_windows(train, idx), cfg)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip)
            opt.step()
            add_sums(total, sums)
        model.eval()
        row = {"epoch": epoch + 1, **{f"train_{k}": v for k, v in summarise(total).items()}}
        if val is not None:
            row.update({f"val_{k}": v for k, v in evaluate(ekf, model, val, cfg).items()})
        row["select"] = row["val_loss"] if val is not None else row["train_loss"]
        for name, metrics in (baselines or {}).items():
            row.update({f"{name}_{k}": v for k, v in metrics.items()})
        history.append(row)
        epochs.set_postfix(loss=f"{row['train_loss']:.4g}", val=f"{row.get('val_loss', float('nan')):.4g}")
        log.info("%s", epoch_report(row, cfg.epochs, baselines))
        if out_dir is not None:
            meta = {"history": history, **(extra or {})}
            if row["select"] < best:
                best = row["select"]
                save_checkpoint(out_dir / "best.pt", model, spec=spec, extra={**meta, "epoch": epoch + 1})
            last = {**meta, "epoch": epoch + 1, "optimizer": opt.state_dict()}
            save_checkpoint(out_dir / "last.pt", model, spec=spec, extra=last)
            write_metrics(out_dir, history)
    return history


def epoch_report(row: Mapping[str, float], epochs: int, baselines: Mapping[str, Mapping[str, float]] | None) -> str:
    """One line: the epoch's training and validation loss and drift, each validation number beside the baselines'
    on the same windows."""
    line = f"epoch {int(row['epoch'])}/{epochs}: train loss {row['train_loss']:.4g}"
    if "val_loss" not in row:
        return line
    for key, label, fmt in (("loss", "val loss", ".4g"), ("trans_mm", "drift mm", ".3f"), ("rot_deg", "deg", ".3f")):
        others = ", ".join(f"{name} {m[key]:{fmt}}" for name, m in (baselines or {}).items() if key in m)
        line += f"; {label} {row[f'val_{key}']:{fmt}}" + (f" ({others})" if others else "")
    return line


def worse_than(best: Mapping[str, float], baselines: Mapping[str, Mapping[str, float]]) -> list[str]:
    """The baselines whose validation loss or drift the best epoch's row does not beat: one phrase each (empty: it
    beats them all)."""
    out = []
    for name, m in baselines.items():
        for key, what in (("loss", "loss"), ("trans_mm", "drift")):
            ours, theirs = best.get(f"val_{key}", math.nan), m.get(key, math.nan)
            if math.isfinite(ours) and math.isfinite(theirs) and ours >= theirs:
                out.append(f"{what} {ours:.4g} vs {name} {theirs:.4g}")
    return out


def _resume(
    model: nn.Module, opt: torch.optim.Optimizer, out_dir: Path | None, spec: dict | None
) -> tuple[list[dict], int]:
    if out_dir is None or not (out_dir / "last.pt").is_file():
        return [], 0
    saved, meta = load_checkpoint(out_dir / "last.pt")
    if (theirs := {"_target_": meta["target"], **meta["model"]}) != spec:
        raise ValueError(f"{out_dir / 'last.pt'}: a model with other settings ({theirs}); use another out dir")
    model.load_state_dict(saved.state_dict())
    opt.load_state_dict(meta["optimizer"])
    log.info("resuming %s at epoch %d", out_dir, meta["epoch"])
    return list(meta["history"]), int(meta["epoch"])


def write_metrics(out_dir: Path, history: list[dict]) -> None:
    """metrics.csv and loss.png (atomic), and TensorBoard scalars when tensorboard is installed."""
    keys = list(dict.fromkeys(k for row in history for k in row))

    def write(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows(history)

    write_atomic(out_dir / "metrics.csv", write)
    plot_losses(out_dir / "loss.png", history)
    _tensorboard(out_dir, history[-1])


def plot_losses(path: Path, history: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from torchtrack.viz.plots import save_atomic

    epochs = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for key, ax in zip(("loss", "trans_mm"), axes, strict=True):
        for split in ("train", "val"):
            if f"{split}_{key}" in history[-1]:
                ax.plot(epochs, [h[f"{split}_{key}"] for h in history], marker="o", ms=3, label=split)
        others = [
            k[: -len(key) - 1] for k in history[-1] if k.endswith(f"_{key}") and not k.startswith(("train_", "val_"))
        ]
        for name, style in zip(others, (":", "--", "-."), strict=False):  # the baselines on the validation windows
            ax.axhline(history[-1][f"{name}_{key}"], color="k", ls=style, lw=1, label=f"val, {name}")
        ax.set_xlabel("epoch")
        ax.set_ylabel({"loss": "loss", "trans_mm": "mean translation error over windows (mm)"}[key])
        ax.grid(alpha=0.3)
        ax.legend()
    fig.suptitle("learned weighting: training through the fusion EKF")
    fig.tight_layout()
    save_atomic(fig, path)
    plt.close(fig)


def _tensorboard(out_dir: Path, row: dict) -> None:
    try:
        from torch.utils.tensorboard import SummaryWriter
    except Exception:  # tensorboard not installed: the CSV and the PNG are the record
        return
    with SummaryWriter(str(out_dir / "tensorboard")) as w:
        for k, v in row.items():
            if k != "epoch" and isinstance(v, float) and math.isfinite(v):
                w.add_scalar(k, v, row["epoch"])
