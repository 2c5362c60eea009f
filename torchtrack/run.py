"""Run a tracker over B sequences in lockstep and write each sequence's outputs as soon as it ends.

Per sequence, in ``out_dir/<name>/``: ``trajectory.txt`` (TUM, camera-to-world), ``metrics.json``,
``frames.csv`` (per-frame diagnostics), ``trajectory.png`` and ``features.png`` (the paper's Figs.
6/7 as an image strip). Every file is written atomically (:func:`torchtrack.io.write_atomic`), so a
sequence that finished is never lost when a later one fails.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchtrack.data.batching import iterate_batched
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import write_tum_trajectory
from torchtrack.io import write_json, write_text
from torchtrack.tracker import StepResult, Tracker
from torchtrack.viz.overlay import draw_frame, save_strip, snapshot_indices

log = logging.getLogger(__name__)


def world_anchor(T_world_cam_gt: torch.Tensor, gt_valid: torch.Tensor) -> torch.Tensor:
    """(..., 4, 4) float64 the tracker's world (its first camera) in ground truth's world: the first frame's
    ground-truth camera pose ``T_world_cam_gt`` (..., 4, 4) where ``gt_valid`` (...,), else the identity. The
    written trajectory is ``T_world_cam = anchor @ T_world_cam_tracker``, comparable with ground truth unaligned."""
    eye = torch.eye(4, dtype=torch.float64).expand_as(T_world_cam_gt)
    return torch.where(gt_valid[..., None, None], T_world_cam_gt.double(), eye)


@dataclass
class Recorder:
    """Accumulates one sequence's per-frame outputs."""

    sequence: TumSequence
    out_dir: Path
    snapshots: set[int]
    rows: list[dict] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    tiles: list[np.ndarray] = field(default_factory=list)
    T_world_tracker: torch.Tensor | None = None  # (4, 4) the tracker's world in ground truth's, from the first frame

    def add(self, b: int, frame, res: StepResult) -> None:
        i = int(frame.index[b])
        if self.T_world_tracker is None:
            self.T_world_tracker = world_anchor(frame.T_world_cam_gt[b], frame.gt_valid[b])
        self.poses.append((self.T_world_tracker @ res.T_world_cam[b]).numpy())
        win = res.winner[b][res.valid[b]]
        self.rows.append(
            {
                "frame": i,
                "timestamp": float(frame.timestamp[b]),
                "features": int(res.n_features[b]),
                "sim_wins": int((win == 1).sum()),
                "reprojection_px": float(res.reprojection_error[b]),
                "mean_tim_px": float(res.d_tim[b][res.valid[b]].mean()) if res.valid[b].any() else 0.0,
                "reselected": bool(res.reselected[b]),
            }
        )
        if i in self.snapshots:
            T_color_obj = frame.T_color_depth[b].double() @ res.T_cam_obj[b]
            self.tiles.append(
                draw_frame(
                    frame.rgb[b],
                    res.pixels[b],
                    res.valid[b],
                    res.winner[b],
                    frame.K[b],
                    T_color_obj,
                    res.points_obj[b],
                    f"{self.sequence.name} #{i}",
                )  # fmt: skip
            )

    def finish(self, elapsed_s: float, plots: bool = True) -> dict:
        from torchtrack.metrics import trajectory_metrics

        seq, out = self.sequence, self.out_dir
        out.mkdir(parents=True, exist_ok=True)
        ts = np.array([r["timestamp"] for r in self.rows])
        T_est = np.stack(self.poses)
        write_tum_trajectory(out / "trajectory.txt", ts, T_est)
        n = len(self.rows)
        metrics = {
            "sequence": seq.name,
            "frames": n,
            "fps": n / max(elapsed_s, 1e-9),
            "reselections": int(sum(r["reselected"] for r in self.rows[1:])),
            "mean_reprojection_px": float(np.mean([r["reprojection_px"] for r in self.rows])),
            "mean_features": float(np.mean([r["features"] for r in self.rows])),
        }
        gt_valid = np.asarray(seq.gt_valid[:n])
        if gt_valid.sum() >= 3:
            metrics.update(trajectory_metrics(ts, T_est, np.asarray(seq.groundtruth[:n]), gt_valid))
        write_json(out / "metrics.json", metrics)
        self._write_csv(out / "frames.csv")
        if plots:
            self._plots(T_est, gt_valid)
        log.info("%s: %s", seq.name, ", ".join(f"{k}={v:.4g}" for k, v in metrics.items() if isinstance(v, float)))
        return metrics

    def _write_csv(self, path: Path) -> None:
        keys = list(self.rows[0])
        lines = [",".join(keys)] + [",".join(str(r[k]) for k in keys) for r in self.rows]
        write_text(path, "\n".join(lines) + "\n")

    def _plots(self, T_est: np.ndarray, gt_valid: np.ndarray) -> None:
        from torchtrack.viz.plots import plot_trajectory

        ts = np.array([r["timestamp"] for r in self.rows])
        gt = np.asarray(self.sequence.groundtruth[: len(T_est)]) if gt_valid.any() else None
        plot_trajectory(
            self.out_dir / "trajectory.png", T_est, gt, title=self.sequence.name, timestamps=ts, gt_valid=gt_valid
        )
        save_strip(self.out_dir / "features.png", self.tiles)


def unique_names(sequences: list[TumSequence]) -> list[str]:
    names, seen = [], {}
    for s in sequences:
        k = seen.get(s.name, 0)
        seen[s.name] = k + 1
        names.append(s.name if k == 0 else f"{s.name}_{k}")
    return names


def run_tracker(
    tracker: Tracker, sequences: list[TumSequence], out_dir: Path, *, plots: bool = True, mapper=None
) -> list[dict]:
    """Track B sequences in lockstep; write each one's outputs when it ends. Returns their metrics.
    ``mapper`` (a :class:`torchtrack.mapping.PanoramaMapper` or None) is fed every frame and writes each map."""
    out_dir = Path(out_dir)
    recs = [
        Recorder(s, out_dir / name, snapshot_indices(len(s)) if plots else set())
        for s, name in zip(sequences, unique_names(sequences), strict=True)
    ]
    lengths = [len(s) for s in sequences]
    results: list[dict | None] = [None] * len(sequences)
    start = time.perf_counter()
    with torch.inference_mode():
        for frame in tqdm(iterate_batched(sequences), total=max(lengths), desc="tracking", unit="frame"):
            res = tracker.step(frame)
            if mapper is not None:
                mapper.add(frame, res)
            for b in range(len(sequences)):
                if not bool(frame.active[b]):
                    continue
                recs[b].add(b, frame, res)
                if int(frame.index[b]) == lengths[b] - 1:
                    results[b] = recs[b].finish(time.perf_counter() - start, plots)
                    if mapper is not None:
                        mapper.finish(b, recs[b].out_dir)
    return [r for r in results if r is not None]
