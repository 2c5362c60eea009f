"""Builders from a composed config: the sequences of ``data``, the tracker of the stage nodes, its compiled operators
and the mapper. The command line and the streaming API both build here; no frame passes through.

Every object is built by its node's ``_target_`` (schemas in :mod:`torchtrack.config`); the only knob derived here
is the front end's pyramid levels, which are the LK tracker's (``flow.levels``). Keys that contradict each other are
refused here, before any data (:func:`build_tracker`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchtrack.data.batching import frame_gray
from torchtrack.data.errors import DataError
from torchtrack.data.tum import TumSequence
from torchtrack.pipeline import Tracker

log = logging.getLogger(__name__)


@contextmanager
def _quiet(logger: logging.Logger) -> Iterator[None]:
    """``logger`` without its INFO lines (warnings stay) for the ``with`` block."""
    level = logger.level
    logger.setLevel(max(level, logging.WARNING))
    try:
        yield
    finally:
        logger.setLevel(level)


class LoadFailure(NamedTuple):
    """A sequence of a batch that failed its load checks: its name (the folder's) and the one-line reason."""

    name: str
    error: str


class Sequences(NamedTuple):
    """The sequences of ``data`` that loaded, in order, and the batch-mates that failed to load."""

    loaded: list[TumSequence]
    failed: list[LoadFailure]


def build_sequences(data: DictConfig) -> list[TumSequence]:
    """TUM-layout sequences from ``data`` (kind tum: one or several roots; kind synthetic: rendered and cached).
    Raises DataError (one line) when any of them fails its load checks; :func:`load_sequences` keeps the others."""
    seqs = load_sequences(data)
    if seqs.failed:
        raise DataError(seqs.failed[0].error)
    return seqs.loaded


def load_sequences(data: DictConfig) -> Sequences:
    """The sequences of ``data``; in a batch of several roots, one that fails its load checks (DataError: a broken
    groundtruth.txt or intrinsics.txt, an empty list, a missing folder) is a :class:`LoadFailure` and the others
    load. A single sequence's failure, and a bad ``data`` node, raise DataError."""
    opts = dict(
        max_frames=data.max_frames, stride=data.stride, on_bad_frame=data.on_bad_frame,
        min_depth_fraction=data.min_depth_fraction, max_bad_fraction=data.max_bad_fraction,
    )  # fmt: skip
    if data.kind == "synthetic":
        from torchtrack.data.synthetic import SyntheticConfig, display_name, ensure_sequence

        scene = SyntheticConfig(**OmegaConf.to_container(data.scene, resolve=True))
        root = ensure_sequence(scene, Path(data.cache_dir).expanduser())
        with _quiet(logging.getLogger("torchtrack.data.tum")):  # its load line names the cache folder: said below
            seq = TumSequence(root, **opts)  # registered
        seq.name = display_name(scene)  # the run folder's name and the log's; the cache folder's carries the digest
        log.info(
            "%s: %d frames, ground truth for %d, rendered into %s", seq.name, len(seq), int(seq.gt_valid.sum()), root
        )
        return Sequences([seq], [])
    if data.kind != "tum":
        raise DataError(f"data.kind must be 'tum' or 'synthetic', got {data.kind!r}")
    if data.root is None:
        raise DataError("data.root is not set: pass data.root=DIR (or data.root=[DIR1,DIR2])")
    roots = list(data.root) if isinstance(data.root, ListConfig) else [data.root]
    align = data.depth_alignment
    extra = dict(
        camera=data.camera, depth_scale=data.depth_scale, max_dt=data.max_dt, intrinsics_camera=data.intrinsics_camera,
        depth_alignment=tuple(align) if isinstance(align, ListConfig) else align,
        intrinsics=None if data.intrinsics is None else tuple(data.intrinsics),
        intrinsics_depth=None if data.depth_intrinsics is None else tuple(data.depth_intrinsics),
        T_color_depth=None if data.T_color_depth is None else OmegaConf.to_container(data.T_color_depth),
    )  # fmt: skip
    loaded, failed = [], []
    for r in roots:
        try:
            loaded.append(TumSequence(Path(r).expanduser(), **opts, **extra))
        except DataError as e:
            if len(roots) == 1:
                raise
            failed.append(LoadFailure(Path(r).expanduser().resolve().name, str(e)))
    return Sequences(loaded, failed)


def build_tracker(cfg: DictConfig) -> Tracker:
    """The pipeline (``cfg.pipeline``) composed of its stages, each built from its own node. ValueError (one line)
    where two keys contradict each other so that the first frames would fail (:func:`_contradictions`)."""
    _contradictions(cfg)
    weighting = instantiate(cfg.weighting)
    # the SIM (eq. 8) only where a stage reads it: SIM-assisted tracking, lambda < 1 selection, a weighting's cues
    use_sim = cfg.flow.mode != "intensity" or cfg.select.lam < 1 or getattr(weighting, "needs_cues", False)
    return instantiate(
        cfg.pipeline,
        frontend=instantiate(cfg.frontend, levels=cfg.flow.levels, gray=frame_gray, use_sim=use_sim),
        flow=instantiate(cfg.flow),
        weighting=weighting,
        backend=instantiate(cfg.estimator),
        reselect=instantiate(cfg.reselect, region=instantiate(cfg.region), select=instantiate(cfg.select)),
        outliers=instantiate(cfg.outliers),
        keyframes=instantiate(cfg.keyframes),
        landmarks=build_landmarks(cfg),
        relocaliser=build_relocaliser(cfg),
        dense=build_dense(cfg),
    )


def _contradictions(cfg: DictConfig) -> None:
    """ValueError for keys that the stages would refuse together only when a frame runs: a fixed grid of patches
    (``select.grid``) with patches sized to the region (``select.roi_fraction``)."""
    if cfg.select.get("grid") is not None and cfg.select.get("roi_fraction") is not None:
        raise ValueError("select.grid fixes the patches, select.roi_fraction sizes them to the region: give "
                         "select.roi_fraction=null with select.grid")  # fmt: skip


def warm_up(device, *, announce: bool = True) -> None:
    """Build (first run only) and load the compiled CPU operators for a tracker on ``device``, so that a first-run
    build happens before any frame is timed; ``announce``: say so on one line of stderr."""
    if torch.device(device).type == "cpu":
        from torchtrack import ops

        if announce:
            ops.warm_up()
        else:
            ops.available()


def build_landmarks(cfg: DictConfig):
    """The tracker's landmark stage (:class:`torchtrack.pipeline.landmarks.LandmarkMap`) from ``cfg.landmarks``, or
    None with ``landmarks=none``."""
    return _stage(cfg.get("landmarks"))


def build_dense(cfg: DictConfig):
    """The tracker's dense map (:class:`torchtrack.map.dense_map.DenseMap`) from ``cfg.dense``, or None with
    ``dense=none``."""
    return _stage(cfg.get("dense"))


def _stage(node: DictConfig | None):
    """The object of ``node``, or None when there is no node or it is an option's empty node (``none``)."""
    return None if node is None or "_target_" not in node else instantiate(node)


def build_relocaliser(cfg: DictConfig):
    """The tracker's loss check (:class:`torchtrack.pipeline.relocalise.Relocaliser`) from ``cfg.relocalise``, if
    any."""
    return instantiate(cfg.relocalise) if "relocalise" in cfg else None


def build_mapper(cfg: DictConfig):
    """The ``mapping`` node's :class:`torchtrack.map.PanoramaMapper`, or None with ``mapping=none``."""
    return _stage(cfg.get("mapping"))
