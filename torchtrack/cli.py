"""Hydra entry point ``torchtrack``: track sequences and write one folder per sequence.

torchtrack                                   # synthetic sequence (rendered once, cached)
torchtrack data=tum data.root=DIR            # a TUM-layout folder
torchtrack data=tum 'data.root=[DIR1,DIR2]'  # B sequences tracked together
torchtrack tracker=icp hydra.run.dir=OUT     # another estimator, chosen output folder
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, ListConfig, OmegaConf

from torchtrack.data.errors import DataError
from torchtrack.data.tum import TumSequence
from torchtrack.run import run_tracker
from torchtrack.runtime import configure
from torchtrack.tracker import Tracker

log = logging.getLogger("torchtrack")
# The configs live beside the package (top-level conf/); torchtrack is installed in editable mode.
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"


def build_sequences(data: DictConfig) -> list[TumSequence]:
    """TUM-layout sequences from ``data`` (kind tum: one or several roots; kind synthetic: rendered and cached)."""
    opts = dict(max_frames=data.get("max_frames"), stride=data.get("stride", 1))
    if data.kind == "synthetic":
        from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence

        params = OmegaConf.to_container(data.scene, resolve=True)
        root = ensure_sequence(SyntheticConfig(**params), Path(data.cache_dir).expanduser())
        return [TumSequence(root, **opts)]  # registered by construction
    if data.kind != "tum":
        raise DataError(f"data.kind must be 'tum' or 'synthetic', got {data.kind!r}")
    if data.root is None:
        raise DataError("data.root is not set: pass data.root=DIR (or data.root=[DIR1,DIR2])")
    roots = list(data.root) if isinstance(data.root, ListConfig) else [data.root]
    extra = {
        k: data.get(k) for k in ("camera", "depth_scale", "max_dt", "intrinsics_camera") if data.get(k) is not None
    }
    if data.get("depth_alignment") is not None:
        align = data.depth_alignment
        extra["depth_alignment"] = tuple(align) if isinstance(align, ListConfig) else align
    if data.get("intrinsics") is not None:
        extra["intrinsics"] = tuple(data.intrinsics)
    if data.get("T_color_depth") is not None:
        extra["T_color_depth"] = OmegaConf.to_container(data.T_color_depth)
    return [TumSequence(Path(r).expanduser(), **opts, **extra) for r in roots]


def build_tracker(cfg: DictConfig, *, record: bool = False) -> Tracker:
    """The pipeline from the config groups (one per stage); ``record``: see :class:`Tracker`."""
    return Tracker(
        frontend=instantiate(cfg.frontend),
        region=instantiate(cfg.region),
        select=instantiate(cfg.select),
        flow=instantiate(cfg.flow),
        weighting=instantiate(cfg.weighting),
        backend=instantiate(cfg.tracker.backend),
        reselect_fraction=cfg.tracker.reselect_fraction,
        min_features=cfg.tracker.min_features,
        edge_step=cfg.tracker.get("edge_step"),
        max_residual_px=cfg.tracker.get("max_residual_px"),
        keep_survivors=cfg.tracker.get("keep_survivors", False),
        min_separation_px=cfg.tracker.get("min_separation_px", 8.0),
        record=record,
    )


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def app(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    configure(cfg.threads)
    try:
        sequences = build_sequences(cfg.data)
        tracker = build_tracker(cfg)
        log.info("tracking %d sequence(s) into %s", len(sequences), out)
        results = run_tracker(tracker, sequences, out, plots=cfg.plots)
    except (DataError, FileNotFoundError) as e:
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise  # let the launcher record this job's failure and run the others
        log.error("%s", e)
        sys.exit(2)
    for r in results:
        keys = ("frames", "fps", "ate_rmse_m", "rpe_trans_m", "rpe_rot_deg", "reselections")
        log.info("%s: %s", r["sequence"], "  ".join(f"{k}={r[k]:.4g}" for k in keys if k in r))


def main() -> None:
    logging.getLogger("PIL").setLevel(logging.WARNING)
    app()


if __name__ == "__main__":
    main()
