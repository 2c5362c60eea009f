"""Run a tracker over B sequences in lockstep and write each sequence's outputs as soon as it ends.

Per sequence, in ``out_dir/<name>/``: ``trajectory.txt`` (TUM, the colour camera's pose camera-to-world, as ground
truth; :mod:`torchtrack.geometry.rig` converts the tracker's depth-camera poses), ``metrics.json``,
``frames.csv`` (per-frame diagnostics), ``trajectory.png`` and ``features.png`` (the paper's Figs.
6/7 as an image strip). Every file is written atomically (:func:`torchtrack.io.write_atomic`), so a
sequence that finished is never lost when a later one fails.

The runner owns ground truth: each frame is moved to the tracking device and stepped through
:meth:`torchtrack.pipeline.Tracker.step`, and the tracker's world (its first depth camera) is anchored at the first
frame's ground-truth colour pose (where there is none, the first colour camera is the world). ``fps`` in
``metrics.json`` and on the progress bar is the batch's tracking rate: lockstep steps per second of loading and
tracking the frames (not writing outputs, not a first-run build of the compiled operators), one number for every
sequence of a batch.

Faults cost only what failed: output folders are checked for writability before tracking; bad frames are dropped
(:class:`torchtrack.data.batching.FrameCursor`; ``metrics.json`` lists them); a sequence that fails mid-way becomes
inactive in the lockstep batch and writes its outputs up to its last good frame with ``"complete": false`` and the
reason, while the others go on.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from torchtrack.data.batching import DroppedFrame, FrameCursor, iterate_batched
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import write_tum_trajectory
from torchtrack.geometry.rig import color_poses, tracker_world
from torchtrack.io import check_writable, write_json, write_text
from torchtrack.pipeline import StepResult, Tracker
from torchtrack.viz.overlay import TRAIL, draw_frame, save_strip, snapshot_indices

log = logging.getLogger(__name__)


@dataclass
class Recorder:
    """Accumulates one sequence's per-frame outputs."""

    sequence: TumSequence
    out_dir: Path
    snapshots: set[int]
    rows: list[dict] = field(default_factory=list)
    poses: list[np.ndarray] = field(default_factory=list)
    tiles: list[np.ndarray] = field(default_factory=list)
    trail: list[torch.Tensor] = field(default_factory=list)  # (N, 2) pixels of the current model's last frames

    def add(self, b: int, frame: FrameBatch, T_world_color: torch.Tensor, res: StepResult) -> None:
        """Row b of a step: its frame, the colour camera's pose (B, 4, 4) in ground truth's world, the result."""
        i = int(frame.index[b])
        self.poses.append(T_world_color[b].numpy())
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
                **self._noise_scale(b, res),
                **self._loss(b, i, res.loss),
            }
        )
        if self.snapshots:
            self.trail = [*self.trail[-(TRAIL - 1) :], res.pixels[b].cpu().clone()]
        if i in self.snapshots:  # drawn from CPU copies, whatever the tracking device
            T_color_obj = (frame.T_color_depth[b].double() @ res.T_cam_obj[b]).cpu()
            self.tiles.append(
                draw_frame(
                    frame.rgb[b].cpu(),
                    res.pixels[b].cpu(),
                    res.valid[b].cpu(),
                    res.winner[b].cpu(),
                    frame.K[b].cpu(),
                    T_color_obj,
                    res.points_obj[b].cpu(),
                    f"frame {i}",
                    trail=self.trail,
                )  # fmt: skip
            )
        if bool(res.reselected[b]):
            self.trail = []  # the next frame tracks the new model's features

    @staticmethod
    def _noise_scale(b: int, res: StepResult) -> dict:
        """frames.csv's online noise scale of the pixel and 3D blocks after this frame (1.0 where off)."""
        scale = getattr(res.estimate, "noise_scale", None)  # (B, 2) [pix, xyz]; None when off or on the first frame
        pix, xyz = (float(scale[b, 0]), float(scale[b, 1])) if scale is not None else (1.0, 1.0)
        return {"noise_scale_pix": pix, "noise_scale_xyz": xyz}

    def _loss(self, b: int, i: int, loss) -> dict:
        """frames.csv's loss columns for sequence b at frame i (all False without a relocaliser); a warning when lost."""
        if loss is None:
            return {"lost": False, "relocalised": False, "interrupted": False}
        lost, reloc, interrupted = bool(loss.lost[b]), bool(loss.relocalised[b]), bool(loss.interrupted[b])
        if lost:
            h = loss.health
            why = f"survival {float(h.survival[b]):.2f}, rejected {float(h.rejected[b]):.2f}, pos std {float(h.pos_std[b]):.3g} m"
            then = (
                f"relocalised ({int(loss.inliers[b])} inliers)" if reloc
                else "not relocalised: trajectory interrupted" if interrupted
                else f"the tracked pose confirmed ({int(loss.inliers[b])} inliers)" if int(loss.inliers[b]) > 0
                else "no recovery (relocalise.recover=false)"
            )  # fmt: skip
            log.warning("%s: frame %d: tracking lost (%s); %s", self.sequence.name, i, why, then)
        elif reloc:
            log.warning(
                "%s: frame %d: relocalised (%d inliers), trajectory resumes",
                self.sequence.name,
                i,
                int(loss.inliers[b]),
            )
        return {"lost": lost, "relocalised": reloc, "interrupted": interrupted}

    def finish(
        self, fps: float, plots: bool = True, *, dropped: list[DroppedFrame] = (), failure: str | None = None
    ) -> dict:
        """Write the outputs of the frames recorded so far; ``failure`` (one line) marks them incomplete."""
        seq, out = self.sequence, self.out_dir
        out.mkdir(parents=True, exist_ok=True)
        n = len(self.rows)
        metrics = {"sequence": seq.name, "complete": failure is None, "frames": n}
        if failure is not None:
            metrics["error"] = failure
        metrics.update(dropped_frames=len(dropped), dropped_timestamps=[d.timestamp for d in dropped])
        if n > 0:
            metrics.update(self._write_tracked(fps, plots))
        write_json(out / "metrics.json", metrics)  # last: a sweep counts a job with metrics.json as finished
        return metrics

    def _write_tracked(self, fps: float, plots: bool) -> dict:
        """trajectory.txt, frames.csv and the plots of the recorded frames; returns their metrics."""
        from torchtrack.metrics import trajectory_metrics

        seq, out = self.sequence, self.out_dir
        trusted = np.array([not r["interrupted"] for r in self.rows])  # interrupted poses are not written
        ts = np.array([r["timestamp"] for r in self.rows])[trusted]
        T_est = np.stack(self.poses)[trusted]
        write_tum_trajectory(out / "trajectory.txt", ts, T_est)
        metrics = {
            "lost_frames": int(sum(r["lost"] for r in self.rows)),
            "relocalisations": int(sum(r["relocalised"] for r in self.rows)),
            "interrupted_frames": int((~trusted).sum()),
            "fps": fps,
            "reselections": int(sum(r["reselected"] for r in self.rows[1:])),
            "mean_reprojection_px": float(np.mean([r["reprojection_px"] for r in self.rows])),
            "mean_features": float(np.mean([r["features"] for r in self.rows])),
        }
        self._write_csv(out / "frames.csv")
        idx = np.array([r["frame"] for r in self.rows])[trusted]  # dropped and interrupted frames leave gaps
        gt_valid = np.asarray(seq.gt_valid)[idx]
        if gt_valid.sum() >= 3:
            metrics.update(trajectory_metrics(ts, T_est, np.asarray(seq.groundtruth)[idx], gt_valid))
        if plots:
            self._plots(T_est, gt_valid, idx)
        return metrics

    def _write_csv(self, path: Path) -> None:
        keys = list(self.rows[0])
        lines = [",".join(keys)] + [",".join(str(r[k]) for k in keys) for r in self.rows]
        write_text(path, "\n".join(lines) + "\n")

    def _plots(self, T_est: np.ndarray, gt_valid: np.ndarray, idx: np.ndarray) -> None:
        from torchtrack.viz.plots import plot_trajectory

        ts = np.array([r["timestamp"] for r in self.rows if not r["interrupted"]])
        gt = np.asarray(self.sequence.groundtruth)[idx] if gt_valid.any() else None
        plot_trajectory(
            self.out_dir / "trajectory.png", T_est, gt, title=self.sequence.name, timestamps=ts, gt_valid=gt_valid
        )
        save_strip(self.out_dir / "features.png", self.tiles, title=self.sequence.name)


def unique_names(sequences: list[TumSequence]) -> list[str]:
    names, seen = [], {}
    for s in sequences:
        k = seen.get(s.name, 0)
        seen[s.name] = k + 1
        names.append(s.name if k == 0 else f"{s.name}_{k}")
    return names


def _prepared_ahead(tracker, frames):
    """The frames, prepared a step ahead in the front end's thread (``frontend.ahead``; the same results)."""
    ahead = getattr(getattr(tracker, "frontend", None), "prepared_ahead", None)
    return ahead(frames) if ahead is not None else frames


# The bar shows the tracking rate (``fps=``, as metrics.json and the result line), not tqdm's own rate, which counts
# the time spent writing each sequence's outputs too.
BAR_FORMAT = "{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}<{remaining}{postfix}]"


class _Clock:
    """The batch's tracking time: wall time since the start less the time spent writing outputs. ``fps`` is read once
    per step, so that the sequences that end at one step report the same rate."""

    def __init__(self) -> None:
        self.t0, self.paused, self.steps, self.fps = time.perf_counter(), 0.0, 0, 0.0

    def tick(self) -> None:
        """One lockstep step done (one frame of every active sequence): the rate so far."""
        self.steps += 1
        self.fps = self.steps / max(time.perf_counter() - self.t0 - self.paused, 1e-9)


def run_tracker(
    tracker: Tracker,
    sequences: list[TumSequence],
    out_dir: Path,
    *,
    plots: bool = True,
    mapper=None,
    device: str | torch.device = "cpu",
) -> list[dict]:
    """Track B sequences in lockstep on ``device``; write each one's outputs when it ends. Returns their metrics, one
    per sequence in order; a failed sequence's say ``"complete": False`` and ``"error"``. Raises OSError (one line)
    before tracking when an output folder is not writable. ``tracker``: a :class:`Tracker` (or anything with
    ``step(FrameBatch) -> StepResult``), started anew. ``mapper`` (a :class:`torchtrack.map.PanoramaMapper` or
    None) is fed every frame and writes each sequence's map when it ends."""
    if hasattr(tracker, "reset"):
        tracker.reset()
    out_dir = Path(out_dir)
    recs = [
        Recorder(s, out_dir / name, snapshot_indices(len(s)) if plots else set())
        for s, name in zip(sequences, unique_names(sequences), strict=True)
    ]
    for r in recs:
        check_writable(r.out_dir)
    cursors = [FrameCursor(s, isolate=True) for s in sequences]
    lengths = [len(s) for s in sequences]
    results: list[dict | None] = [None] * len(sequences)
    clock = _Clock()

    def finish(b: int, failure: str | None = None) -> None:
        t0 = time.perf_counter()
        failure = failure or cursors[b].failure
        if failure is not None:
            log.error("%s: failed: %s", sequences[b].name, failure)
        try:
            results[b] = recs[b].finish(clock.fps, plots, dropped=cursors[b].dropped, failure=failure)
            if mapper is not None:
                mapper.finish(b, recs[b].out_dir)
        except Exception as e:  # writing or evaluating this sequence failed: the others still finish
            log.exception("%s: writing the outputs failed", sequences[b].name)
            results[b] = {"sequence": sequences[b].name, "complete": False, "error": f"{type(e).__name__}: {e}"}
        clock.paused += time.perf_counter() - t0

    frames = (f.to(device) for f in iterate_batched(sequences, cursors=cursors))
    T_world_tracker = None  # the tracker's world (its first depth camera) in ground truth's, from the first frame
    with torch.inference_mode(), logging_redirect_tqdm():  # log lines above the bar, not glued onto it
        bar = tqdm(_prepared_ahead(tracker, frames), total=max(lengths), desc="tracking", unit="frame",
                   bar_format=BAR_FORMAT)  # fmt: skip
        for t, frame in enumerate(bar):
            try:
                res = tracker.step(frame)
                if T_world_tracker is None:
                    T_world_tracker = tracker_world(frame.T_world_color_gt, frame.gt_valid, frame.T_color_depth)
                T_world_color = color_poses(T_world_tracker, res.T_world_depth, frame.T_color_depth).cpu()
            except Exception as e:  # the batch's step failed: no sequence can go on, but what was tracked is kept
                log.exception("tracking failed at step %d", t)
                for b in range(len(sequences)):
                    if results[b] is None:
                        finish(b, f"tracking failed at step {t}: {type(e).__name__}: {e}")
                break
            clock.tick()
            bar.set_postfix_str(f"fps={clock.fps:.4g}", refresh=False)  # the rate metrics.json and the result line say
            if mapper is not None:
                mapper.add(frame, res)
            for b in range(len(sequences)):
                if results[b] is not None:
                    continue
                if bool(frame.active[b]):
                    recs[b].add(b, frame, T_world_color, res)
                if not bool(frame.active[b]) or int(frame.index[b]) == lengths[b] - 1:
                    finish(b)
    for b in range(len(sequences)):
        if results[b] is None:
            finish(b)
    return results
