"""Hydra entry point ``torchtrack``: track sequences and write one folder per sequence.

torchtrack                                   # synthetic sequence (rendered once, cached)
torchtrack data=tum data.root=DIR            # a TUM-layout folder
torchtrack data=tum 'data.root=[DIR1,DIR2]'  # B sequences tracked together
torchtrack estimator=icp hydra.run.dir=OUT   # another estimator, chosen output folder
torchtrack data=tum data.root=DIR mapping=panorama  # + map.ply, map.png (mapping=tsdf: + mesh.ply)
torchtrack conf_dir=myconf weighting=mine    # myconf/weighting/mine.yaml
torchtrack device=cuda                       # track on the GPU

Hydra, the pipeline and the runner are imported when a run starts, not when the module is: ``--help`` and a bad
override answer without them.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from torchtrack.config import CONF_DIR
from torchtrack.console import console_main

log = logging.getLogger("torchtrack")


def tracker_help() -> str:
    """``torchtrack --help``: the template of conf/hydra/help/torchtrack.yaml, resolved as Hydra resolves it (Hydra's
    own ``--help`` first lists every config group's options, which costs seconds of composing; the template does not
    show them)."""
    from omegaconf import OmegaConf

    node = OmegaConf.create({"hydra": {"help": OmegaConf.load(CONF_DIR / "hydra" / "help" / "torchtrack.yaml")}})
    return node.hydra.help.template + "\n"


def app(cfg) -> None:
    """One run: the sequences of ``cfg.data`` tracked in lockstep into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    from torchtrack.config import validate
    from torchtrack.data.errors import DataError
    from torchtrack.factory import build_mapper, load_sequences
    from torchtrack.run import run_tracker
    from torchtrack.runtime import configure, resolve_device
    from torchtrack.stream import RGBDTracker

    out = Path(HydraConfig.get().runtime.output_dir)
    configure(cfg.threads)
    try:
        validate(cfg)
        device = resolve_device(cfg.device)
        sequences, load_failed = load_sequences(cfg.data)  # a batch-mate that fails to load costs only itself
        results = []
        if sequences:
            tracker = RGBDTracker.from_config(cfg, device=device)  # a first-run build of the operators happens here
            log.info("tracking %d sequence(s) on %s into %s", len(sequences), device, out)
            results = run_tracker(tracker, sequences, out, plots=cfg.plots, mapper=build_mapper(cfg))
    except (DataError, OSError, ValueError) as e:  # bad input, device or output folder, found before tracking
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


def hydra_app() -> None:
    """``app`` under Hydra (command line, output folder, logging, sweeps)."""
    import hydra

    hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")(app)()


def main() -> None:
    console_main("torchtrack", "config", tracker_help, hydra_app)


if __name__ == "__main__":
    main()
