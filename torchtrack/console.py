"""The command line's checks before Hydra runs: overrides that do not compose are one line and exit code 2, and each
console script prints its own help. Shared by ``torchtrack``, ``torchtrack-record`` and ``torchtrack-train``."""

from __future__ import annotations

import sys

from torchtrack.config import CONF_DIR, validate
from torchtrack.data.errors import DataError


def check_overrides(config_name: str, argv: list[str]) -> str | None:
    """The one-line reason why ``argv``'s overrides do not compose into a valid config (types, ranges), else None.

    Hydra reports composition errors over several lines with exit code 1; the CLI checks first and exits with 2.
    Multirun sweeps and Hydra's own flags are left to Hydra.
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

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


def console_main(prog: str, config_name: str, help_text: str, app) -> None:
    """A console script's entry: its own ``help_text`` for ``--help``/``-h`` (the tool's keys, not the tracker's help
    of conf/config.yaml), one line and exit code 2 for overrides that do not compose, else the Hydra ``app``."""
    if any(a in ("--help", "-h") for a in sys.argv[1:]):
        print(help_text, end="")
        return
    import logging

    logging.getLogger("PIL").setLevel(logging.WARNING)
    exit_on_bad_overrides(prog, config_name)
    app()
