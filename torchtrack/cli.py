"""Hydra entry point ``torchtrack``: track sequences and write one folder per sequence.

torchtrack                                   # synthetic sequence (rendered once, cached)
torchtrack data=tum data.root=DIR            # a TUM-layout folder
torchtrack data=tum 'data.root=[DIR1,DIR2]'  # B sequences tracked together
torchtrack tracker=icp hydra.run.dir=OUT     # another estimator, chosen output folder
torchtrack data=tum data.root=DIR mapping=panorama  # + map.ply, map.png (mapping=tsdf: + mesh.ply)
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from torchtrack.config import CONF_DIR, validate
from torchtrack.console import exit_on_bad_overrides
from torchtrack.data.errors import DataError
from torchtrack.factory import build_mapper, build_tracker, load_sequences
from torchtrack.run import run_tracker
from torchtrack.runtime import configure

log = logging.getLogger("torchtrack")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def app(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    configure(cfg.threads)
    try:
        validate(cfg)
        sequences, load_failed = load_sequences(cfg.data)  # a batch-mate that fails to load costs only itself
        results = []
        if sequences:
            tracker = build_tracker(cfg)
            log.info("tracking %d sequence(s) into %s", len(sequences), out)
            results = run_tracker(tracker, sequences, out, plots=cfg.plots, mapper=build_mapper(cfg))
    except (DataError, OSError) as e:  # bad input or an unwritable output folder, found before tracking
        if HydraConfig.get().mode == RunMode.MULTIRUN:
            raise  # let the launcher record this job's failure and run the others
        log.error("%s", e)
        sys.exit(2)
    for r in results:
        keys = ("frames", "fps", "ate_rmse_m", "rpe_trans_m", "rpe_rot_deg", "reselections")
        log.info("%s: %s", r["sequence"], "  ".join(f"{k}={r[k]:.4g}" for k in keys if k in r))
    for f in load_failed:  # written nowhere
        log.error("FAILED %s at load: %s", f.name, f.error)
    failed = [r for r in results if not r["complete"]]
    for r in failed:  # one summary line each; their outputs up to the last good frame are written
        log.error("FAILED %s after %d frames: %s", r["sequence"], r.get("frames", 0), r["error"])
    if failed or load_failed:
        raise SystemExit(1)


def main() -> None:
    logging.getLogger("PIL").setLevel(logging.WARNING)
    exit_on_bad_overrides("torchtrack", "config")
    app()


if __name__ == "__main__":
    main()
