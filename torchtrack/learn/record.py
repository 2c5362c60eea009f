"""Record the front end once per sequence into the observation cache (:mod:`torchtrack.learn.cache`).

torchtrack-record data=tum data.root=DIR out=CACHE_DIR              # one file CACHE_DIR/<name>.pt per sequence
torchtrack-record data=tum 'data.root=[DIR1,DIR2]' out=CACHE_DIR    # B sequences tracked in lockstep
torchtrack-record +dataset=synthetic out=CACHE_DIR                  # the synthetic training set (learn/dataset.py)

The command composes the same config groups as ``torchtrack`` (conf/config.yaml) plus ``out``. It is resumable:
a sequence whose file exists, loads, and was recorded from the same source with the same config is skipped.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor
from tqdm import tqdm

from torchtrack.data.batching import FrameCursor, RGBDSequence, iterate_batched
from torchtrack.data.frame import FrameBatch
from torchtrack.factory import build_tracker
from torchtrack.filter.cues import CUE_NAMES
from torchtrack.learn.cache import SequenceObservations, load_observations, object_poses_gt, save_observations
from torchtrack.pipeline import StepResult
from torchtrack.run import unique_names

log = logging.getLogger("torchtrack.record")

# The config groups that build the tracker and read the sequences (conf/config.yaml): what a recording depends on.
# Other keys (out, threads, plots, a trainer's settings) do not change it; nor do the folders the sequences come
# from (the file's ``source`` names them).
RECORDED_GROUPS = (
    "data",
    "frontend",
    "region",
    "select",
    "flow",
    "filter",
    "weighting",
    "estimator",
    "pipeline",
    "reselect",
    "outliers",
    "keyframes",
    "landmarks",
    "relocalise",
)
_DATA_LOCATION = ("root", "cache_dir")
_PER_FRAME = (
    "timestamp",
    "T_world_color_gt",
    "gt_valid",
    "reselected",
    "T_cam_obj_est",
    "model_T_cam_obj",
    "noise_scale",
    "noise_dof",
)


def recording_config(cfg: DictConfig) -> str:
    """The resolved config that determines a recording, as YAML text (stored in, and compared with, each file)."""
    c = {k: OmegaConf.to_container(cfg[k], resolve=True) for k in RECORDED_GROUPS if cfg.get(k) is not None}
    for k in _DATA_LOCATION:
        c.get("data", {}).pop(k, None)
    return OmegaConf.to_yaml(OmegaConf.create(c), sort_keys=True)


def source_of(sequence: RGBDSequence) -> str:
    root = getattr(sequence, "root", None)
    return str(Path(root).resolve()) if root is not None else sequence.name


class ObservationLog:
    """Accumulates one sequence's per-frame back-end inputs from the tracker's StepResults (recording on)."""

    def __init__(self, sequence: str, source: str, config: str, weighting: str) -> None:
        self.meta = dict(sequence=sequence, source=source, config=config, weighting=weighting)
        self.rows: list[dict[str, Tensor]] = []
        self.camera: dict[str, Tensor] = {}
        self.last_index = -1

    def add(self, b: int, frame: FrameBatch, res: StepResult) -> None:
        """Frame ``frame.index[b]`` of this sequence: row b of the batch."""
        i = int(frame.index[b])  # dropped frames leave gaps; dt spans them, as in the tracker
        if self.rows and i <= self.last_index:
            raise ValueError(f"{self.meta['sequence']}: frame {i} recorded after frame {self.last_index}")
        self.last_index = i
        if not self.camera:
            self.camera = {k: getattr(frame, k)[b].double() for k in ("K", "K_depth", "T_color_depth")}
        eye = torch.eye(4, dtype=torch.float64, device="cpu")
        row = dict(
            timestamp=frame.timestamp[b].double(), T_world_color_gt=frame.T_world_color_gt[b].double(),
            gt_valid=frame.gt_valid[b], reselected=res.reselected[b], T_cam_obj_est=res.T_cam_obj[b].double(),
            model_T_cam_obj=res.model_T_cam_obj[b].double() if bool(res.reselected[b]) else eye,
            **_scale_state(res, b),
        )  # fmt: skip
        obs = res.observation
        if obs is not None:
            if res.cues is None:
                raise ValueError("ObservationLog: no cues in the step's result (register it with needs_cues = True)")
            row |= dict(
                dt=obs.dt[b].double(), points_obj=obs.points_obj[b], points_d=obs.points_d[b], pixels=obs.pixels[b],
                valid=obs.valid[b], has_depth=obs.valid_xyz[b], cues=res.cues[b], var_pix=res.variances.var_pix[b],
                var_xyz=res.variances.var_xyz[b],
            )  # fmt: skip
        self.rows.append({k: v.detach().clone() for k, v in row.items()})

    def finish(self) -> SequenceObservations:
        """The sequence's observations, feature rows padded to the widest frame (zeros / False)."""
        rows, T = self.rows, len(self.rows)
        N = max((r["valid"].shape[0] for r in rows if "valid" in r), default=0)
        like = next((r for r in rows if "valid" in r), None)
        shapes = {"points_obj": 3, "points_d": 3, "pixels": 2, "valid": 0, "has_depth": 0, "cues": len(CUE_NAMES)}
        shapes |= {"var_pix": 0, "var_xyz": 0}
        features = {}
        for k, c in shapes.items():
            dtype = (
                like[k].dtype if like is not None else (torch.bool if k in ("valid", "has_depth") else torch.float32)
            )
            out = torch.zeros(T, N, *((c,) if c else ()), dtype=dtype, device="cpu")
            for t, r in enumerate(rows):
                if k in r:
                    out[t, : r[k].shape[0]] = r[k]
            features[k] = out
        per_frame = {k: torch.stack([r[k] for r in rows]) for k in rows[0] if k in _PER_FRAME}
        per_frame["dt"] = torch.stack([r.get("dt", torch.zeros((), dtype=torch.float64, device="cpu")) for r in rows])
        model_frame, T_cam_obj_gt, gt_ok = object_poses_gt(
            per_frame["T_world_color_gt"],
            per_frame["gt_valid"],
            per_frame["reselected"],
            per_frame["model_T_cam_obj"],
            self.camera["T_color_depth"],
        )
        return SequenceObservations(
            **self.meta, **self.camera, **per_frame, **features,
            model_frame=model_frame, T_cam_obj_gt=T_cam_obj_gt, T_cam_obj_gt_valid=gt_ok,
        )  # fmt: skip


def _scale_state(res: StepResult, b: int) -> dict[str, Tensor]:
    """Row b's online noise scale after this frame (:class:`~torchtrack.filter.noise_scale.ScaleState`): k = 1 with no
    weight where the scale is off or before the first update, as the back end starts it."""
    noise = getattr(res.estimate, "noise", None)
    if noise is None:
        off = torch.ones(2, dtype=torch.float64, device="cpu")
        return {"noise_scale": off, "noise_dof": torch.zeros_like(off)}
    return {"noise_scale": noise.scale[b].double(), "noise_dof": noise.dof[b].double()}


def _is_current(path: Path, config: str, source: str) -> bool:
    try:
        obs = load_observations(path)
    except ValueError as e:
        log.info("%s: re-recording (%s)", path.name, e)
        return False
    if obs.config != config or obs.source != source:
        what = "config" if obs.config != config else "source"
        log.info("%s: re-recording (recorded with another %s)", path.name, what)
        return False
    return True


def record_sequences(
    cfg: DictConfig,
    sequences: Sequence[RGBDSequence],
    out_dir: str | Path,
    *,
    names: Sequence[str] | None = None,
    batch: int | None = None,
    progress: bool = True,
) -> list[Path]:
    """Track ``sequences`` with the pipeline of ``cfg`` (as ``torchtrack``) and write ``out_dir/<name>.pt`` each.

    Args:
        cfg: composed config (conf/config.yaml's groups); the tracker is :func:`torchtrack.cli.build_tracker`'s.
        sequences: TUM-layout (or any :class:`~torchtrack.data.batching.RGBDSequence`) sequences.
        names: file names (default: the sequences' names, made unique).
        batch: sequences tracked in lockstep (default ``cfg.batch`` or 1); a batch must share the image size.
        progress: a tqdm bar per batch.

    Returns:
        The files, one per sequence, in order. Existing files of the same source and config are kept (resume).
    """
    out_dir = Path(out_dir)
    names = list(names) if names is not None else unique_names(list(sequences))
    if len(names) != len(sequences) or len(set(names)) != len(names):
        raise ValueError(f"record_sequences: need one unique name per sequence, got {names}")
    config = recording_config(cfg)
    paths = [out_dir / f"{n}.pt" for n in names]
    todo = []
    for i, (seq, path) in enumerate(zip(sequences, paths, strict=True)):
        if path.is_file() and _is_current(path, config, source_of(seq)):
            log.info("%s: already recorded in %s, skipped", names[i], path)
        else:
            todo.append(i)
    size = max(1, int(batch or cfg.get("batch") or 1))
    for start in range(0, len(todo), size):
        chunk = todo[start : start + size]
        _record_batch(cfg, [sequences[i] for i in chunk], [names[i] for i in chunk], [paths[i] for i in chunk],
                      config, progress)  # fmt: skip
    return paths


class Recording:
    """The observer of the tracker's step that records it (``tracker.observers.append(Recording(logs))``): each active
    sequence's row of the step's result into its :class:`ObservationLog`. It asks for the cues (``needs_cues``), so
    the tracker computes them every frame, whatever its weighting needs."""

    needs_cues = True

    def __init__(self, logs: Sequence[ObservationLog]) -> None:
        self.logs = list(logs)

    def __call__(self, frame: FrameBatch, res: StepResult) -> None:
        for b, rec in enumerate(self.logs):
            if bool(frame.active[b]):
                rec.add(b, frame, res)


def _record_batch(cfg, sequences, names, paths, config: str, progress: bool) -> None:
    tracker = build_tracker(cfg)
    w = type(tracker.weighting)
    weighting = f"{w.__module__}.{w.__qualname__}"
    logs = [ObservationLog(n, source_of(s), config, weighting) for n, s in zip(names, sequences, strict=True)]
    tracker.observers.append(Recording(logs))
    cursors = [FrameCursor(s) for s in sequences]  # bad or missing frames are dropped, as in a run; a failure raises
    saved = [False] * len(sequences)
    desc = f"recording {names[0]}" + (f" (+{len(names) - 1})" if len(names) > 1 else "")
    with torch.inference_mode():
        frames = iterate_batched(sequences, cursors=cursors)
        for frame in tqdm(frames, total=max(len(s) for s in sequences), desc=desc, unit="frame", disable=not progress):
            tracker.step(frame)
            for b, rec in enumerate(logs):
                if not bool(frame.active[b]) and not saved[b]:  # the sequence has ended: written while the others go on
                    saved[b] = _save(rec, paths[b])
    for rec, path, done in zip(logs, paths, saved, strict=True):
        if not done:
            _save(rec, path)


def _save(rec: ObservationLog, path: Path) -> bool:
    save_observations(rec.finish(), path)
    log.info("%s: %d frames recorded into %s", rec.meta["sequence"], len(rec.rows), path)
    return True
