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
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from torchtrack.config import CONF_DIR, validate
from torchtrack.data.errors import DataError
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.run import run_tracker
from torchtrack.runtime import configure

log = logging.getLogger("torchtrack")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="config")
def app(cfg: DictConfig) -> None:
    out = Path(HydraConfig.get().runtime.output_dir)
    configure(cfg.threads)
    try:
        validate(cfg)
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


def check_overrides(config_name: str, argv: list[str]) -> str | None:
    """The one-line reason why ``argv``'s overrides do not compose into a valid config (types, ranges), else None.

    Hydra reports composition errors over several lines with exit code 1; the CLI checks first and exits with 2.
    Multirun sweeps and Hydra's own flags are left to Hydra.
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    if any(a.startswith("-") for a in argv):
        return None
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            validate(compose(config_name, overrides=argv))
    except (HydraException, OmegaConfBaseException, DataError) as e:
        cause = e.__cause__ if isinstance(e.__cause__, OmegaConfBaseException) else e
        lines = [
            ln.strip() for ln in str(cause).splitlines() if ln.strip() and not ln.strip().startswith("object_type")
        ]
        return "; ".join(lines[:2])
    return None


def exit_on_bad_overrides(prog: str, config_name: str) -> None:
    """Exit with code 2 and one line on stderr when the command line's overrides do not compose."""
    error = check_overrides(config_name, sys.argv[1:])
    if error is not None:
        print(f"{prog}: error: {error}", file=sys.stderr)
        sys.exit(2)


def main() -> None:
    logging.getLogger("PIL").setLevel(logging.WARNING)
    exit_on_bad_overrides("torchtrack", "config")
    app()


if __name__ == "__main__":
    main()
