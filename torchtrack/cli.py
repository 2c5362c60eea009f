"""The command line: the Hydra entry point ``torchtrack`` and the checks every console script (``torchtrack``,
``torchtrack-record``, ``torchtrack-train``) makes before Hydra runs: its own help, ``conf_dir=DIR`` as a config
folder of the user's, and overrides that do not compose as one line (with the options Hydra lists, or the nearest
name) and exit code 2.

torchtrack                                   # synthetic sequence (rendered once, cached)
torchtrack data=tum data.root=DIR            # a TUM-layout folder
torchtrack data=tum 'data.root=[DIR1,DIR2]'  # B sequences tracked together
torchtrack estimator=icp hydra.run.dir=OUT   # another estimator, chosen output folder
torchtrack data=tum data.root=DIR mapping=panorama  # + map.ply, map.png (mapping=tsdf: + mesh.ply)
torchtrack conf_dir=myconf weighting=mine    # myconf/weighting/mine.yaml
torchtrack device=cuda                       # track on the GPU

A run builds its objects (:mod:`torchtrack.factory`) and hands the sequences to the runner
(:func:`torchtrack.run.run_tracker`), which steps the tracker. Hydra, the pipeline and the runner are imported when a
run starts, not when the module is: ``--help`` and a bad override answer without them.
"""

from __future__ import annotations

import difflib
import logging
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from torchtrack.config import CONF_DIR, RENAMED_GROUPS

log = logging.getLogger("torchtrack")

CONF_DIR_KEY = "conf_dir"
_MISSING = object()


def with_conf_dir(argv: Sequence[str]) -> list[str]:
    """``argv`` with ``conf_dir=DIR`` replaced by ``hydra.searchpath=[file:///abs/DIR]`` (joined with a searchpath the
    command line already gives), so that ``group=name`` finds ``DIR/group/name.yaml``. ValueError (one line) when DIR
    is not a folder."""
    dirs = [a.partition("=")[2] for a in argv if a.startswith(f"{CONF_DIR_KEY}=")]
    if not dirs:
        return list(argv)
    paths = []
    for d in dirs:
        path = Path(d).expanduser().resolve()
        if not path.is_dir():
            raise ValueError(f"{CONF_DIR_KEY}={d}: {path} is not a folder")
        paths.append(f"file://{path}")
    given = [a for a in argv if a.startswith("hydra.searchpath=")]
    entries = [e.strip() for a in given for e in a.partition("=")[2].strip("[]").split(",") if e.strip()]
    merged = f"hydra.searchpath=[{','.join(paths + entries)}]"
    out, placed = [], False
    for a in argv:  # in the first one's place: Hydra's argparse takes no override after a flag such as --cfg job
        if a.startswith((f"{CONF_DIR_KEY}=", "hydra.searchpath=")):
            out += [] if placed else [merged]
            placed = True
        else:
            out.append(a)
    return out


def config_dirs(argv: Sequence[str]) -> list[Path]:
    """The config folders a composition with ``argv`` searches: conf/ and the ``file://`` entries of
    ``hydra.searchpath``."""
    dirs = [CONF_DIR]
    for a in argv:
        if a.startswith("hydra.searchpath="):
            entries = a.partition("=")[2].strip("[]").split(",")
            dirs += [Path(e.strip()[len("file://") :]) for e in entries if e.strip().startswith("file://")]
    return dirs


def compose_config(config_name: str, overrides: Sequence[str] = ()):
    """The config ``config_name`` composed with ``overrides`` (``conf_dir=DIR`` included) and validated; ValueError
    with the one-line reason (:func:`explain`) when it does not compose."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from torchtrack.config import validate
    from torchtrack.data.errors import DataError
    from torchtrack.runtime import resolve_device

    overrides = with_conf_dir(overrides)
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose(config_name, overrides=overrides)
        validate(cfg)
        if "device" in cfg:
            resolve_device(cfg.device)
    except (HydraException, OmegaConfBaseException, DataError) as e:
        raise ValueError(explain(e, config_name, overrides)) from None
    return cfg


def build_checked(cfg):
    """The tracker of ``cfg`` (:func:`torchtrack.factory.build_tracker`; cheap: no data, no compiled operator); a
    stage's own range check (``filter.iterations=0``, ``flow.mode=foo``, a weighting class that does not import) is a
    ValueError with the innermost cause's one line, not Hydra's instantiation traceback."""
    from hydra.errors import InstantiationException

    from torchtrack.factory import build_tracker

    try:
        return build_tracker(cfg)
    except (InstantiationException, ValueError, TypeError, ImportError, FileNotFoundError) as e:
        cause = e
        while cause.__cause__ is not None:
            cause = cause.__cause__
        text = str(cause).strip().splitlines()
        raise ValueError(text[0] if text else type(cause).__name__) from None


def check_overrides(config_name: str, argv: list[str]) -> str | None:
    """The one-line reason why ``argv``'s overrides do not compose into a valid config (types, ranges, device), else
    None. Hydra reports composition errors over several lines with exit code 1; the CLI checks first and exits with
    2. Multirun sweeps and Hydra's own flags are left to Hydra."""
    if any(a.startswith("-") for a in argv):
        return None
    try:
        cfg = compose_config(config_name, argv)
        if "pipeline" in cfg:  # the stages' range checks, before any data is read
            build_checked(cfg)
    except ValueError as e:
        return str(e)
    return None


def explain(error: Exception, config_name: str, overrides: Sequence[str]) -> str:
    """One line for a composition error: Hydra's list of a group's options kept on the line, and for an unknown key
    or group the option of its group that has it (``add data=tum``) or the nearest name
    (:func:`difflib.get_close_matches`)."""
    from omegaconf.errors import OmegaConfBaseException

    text = str(error)
    if "Could not find '" in text:
        return _missing_option(text)
    cause = error.__cause__ if isinstance(error.__cause__, OmegaConfBaseException) else error
    lines = [ln.strip() for ln in str(cause).splitlines() if ln.strip() and not ln.strip().startswith("object_type")]
    full_key = getattr(cause, "full_key", None)
    if full_key and re.match(r"Key '[^']+' (is )?not in", lines[0]):
        hint = _key_hint(str(full_key), config_name, overrides)
        return f"Could not override '{full_key}': {lines[0]}" + (f"; {hint}" if hint else "")
    return "; ".join(lines[:2])


def _missing_option(text: str) -> str:
    """ "Could not find 'group/name'; available options in 'group': a, b, c; did you mean 'b'?" from Hydra's text."""
    missing = re.search(r"Could not find '([^']+)'", text).group(1)
    found = re.search(r"Available options in '([^']+)':\n((?:\t.*\n?)*)", text)
    if found is None:
        return f"Could not find '{missing}'"
    options = [o.strip() for o in found.group(2).splitlines() if o.strip()]
    line = f"Could not find '{missing}'; available options in '{found.group(1)}': {', '.join(options)}"
    close = difflib.get_close_matches(missing.rsplit("/", 1)[-1], options, n=1)
    return line + (f"; did you mean '{close[0]}'?" if close else "")


def _quiet_compose(config_name: str, overrides: Sequence[str]):
    """The composed config, or None where it does not compose."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return compose(config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException):
        return None


def _key_hint(full_key: str, config_name: str, overrides: Sequence[str]) -> str | None:
    """For a key or group name that is not in the config: the option of its group that has the key (``add
    data=tum``), else the nearest name at its place (groups and keys), else None."""
    from omegaconf import DictConfig, OmegaConf

    def bare(o: str) -> str:
        return o.partition("=")[0].lstrip("+~")

    if (old := full_key.split(".")[0]) in RENAMED_GROUPS:
        return f"the {old}= group is now {RENAMED_GROUPS[old]}= (its keys: {RENAMED_GROUPS[old]}.KEY)"

    rest = [o for o in overrides if bare(o) != full_key and not bare(o).startswith(full_key + ".")]
    base = _quiet_compose(config_name, rest)
    if base is None:
        return None
    parent, _, key = full_key.rpartition(".")
    group = full_key.split(".")[0]
    dirs = config_dirs(overrides)
    if parent:
        others = [o for o in rest if not bare(o).startswith(group + ".")]  # the chosen option's other keys may not fit
        for option in sorted({p.stem for d in dirs for p in (d / group).glob("*.yaml")}):
            cfg = _quiet_compose(config_name, [*others, f"{group}={option}"])
            if cfg is not None and OmegaConf.select(cfg, full_key, default=_MISSING) is not _MISSING:
                return f"{full_key} is a key of {group}={option}: add {group}={option}"
    node = OmegaConf.select(base, parent) if parent else base
    names = list(node.keys()) if isinstance(node, DictConfig) else []
    if not parent:
        names += [p.name for d in dirs if d.is_dir() for p in d.iterdir() if p.is_dir() and p.name != "hydra"]
    close = difflib.get_close_matches(key, sorted(set(map(str, names))), n=1)
    return f"did you mean '{parent + '.' if parent else ''}{close[0]}'?" if close else None


def exit_on_bad_overrides(prog: str, config_name: str) -> None:
    """Exit with code 2 and one line on stderr when the command line's overrides do not compose. Without overrides
    there is nothing to check: the default config composes (the tests hold it), and checking costs a composition."""
    error = check_overrides(config_name, sys.argv[1:]) if sys.argv[1:] else None
    if error is not None:
        print(f"{prog}: error: {error}", file=sys.stderr)
        sys.exit(2)


def console_main(prog: str, config_name: str, help_text: str | Callable[[], str], app) -> None:
    """A console script's entry: its own ``help_text`` for ``--help``/``-h`` (the tool's keys, not Hydra's generated
    help), ``conf_dir=DIR`` turned into Hydra's search path, one line and exit code 2 for overrides that do not
    compose, else the Hydra ``app``."""
    if any(a in ("--help", "-h") for a in sys.argv[1:]):
        print(help_text() if callable(help_text) else help_text, end="")
        return
    try:
        sys.argv[1:] = with_conf_dir(sys.argv[1:])
    except ValueError as e:
        print(f"{prog}: error: {e}", file=sys.stderr)
        sys.exit(2)
    logging.getLogger("PIL").setLevel(logging.WARNING)
    exit_on_bad_overrides(prog, config_name)
    app()


# ---------------------------------------------------------------------------------------------- torchtrack
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
    from torchtrack.factory import build_mapper, build_tracker, load_sequences, warm_up
    from torchtrack.run import run_tracker
    from torchtrack.runtime import configure, resolve_device

    out = Path(HydraConfig.get().runtime.output_dir)
    configure(cfg.threads)
    try:
        validate(cfg)
        device = resolve_device(cfg.device)
        sequences, load_failed = load_sequences(cfg.data)  # a batch-mate that fails to load costs only itself
        results = []
        if sequences:
            tracker = build_tracker(cfg)
            warm_up(device)  # a first-run build of the compiled operators: here, not in the first frame's time
            log.info("tracking %d sequence(s) on %s into %s", len(sequences), device, out)
            results = run_tracker(tracker, sequences, out, plots=cfg.plots, mapper=build_mapper(cfg), device=device)
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
