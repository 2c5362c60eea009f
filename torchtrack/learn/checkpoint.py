"""Checkpoints of a learned weighting: one ``.pt`` file that rebuilds the module and says what it expects.

Layout (a plain dict, loadable with ``torch.load(weights_only=True)``)::

    {"format": "torchtrack-weighting", "version": 1,
     "cue_names": [...], "cue_version": int,      # the cues the model was trained on (torchtrack.filter.cues)
     "target": "pkg.module.Class",                # the module's class (absent in older files: LearnedWeighting)
     "model": {constructor kwargs},               # target(**model) rebuilds the architecture
     "state_dict": {...},
     **extra}                                     # the trainer's resolved config, metrics, ...

Any ``torch.nn.Module`` that maps :class:`~torchtrack.filter.weighting.WeightingInputs` to
:class:`~torchtrack.filter.weighting.Variances` can be saved and loaded, given the config node it was built from
(``{"_target_": dotted path, **constructor kwargs}``, :func:`build_weighting`); the shipped
:class:`~torchtrack.learn.model.LearnedWeighting` describes itself (``.config``). The module's constructor arguments
are part of what it learned, so they come from the checkpoint only: :func:`learned_weighting` (the Hydra factory)
refuses a config that disagrees with them.
"""

from __future__ import annotations

import importlib
import inspect
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchtrack.filter.cues import CUE_NAMES, CUE_VERSION, check_cue_names
from torchtrack.io import write_atomic
from torchtrack.learn.model import LearnedWeighting

log = logging.getLogger(__name__)
FORMAT = "torchtrack-weighting"
VERSION = 1  # bump when the layout or the model's fixed definition (e.g. model.CUE_TRANSFORMS) changes
DEFAULT_CHECKPOINT = Path(__file__).parent / "weights" / "default.pt"
DEFAULT_TARGET = f"{LearnedWeighting.__module__}.{LearnedWeighting.__qualname__}"  # files without "target"
_RESERVED = ("format", "version", "cue_names", "cue_version", "target", "model", "state_dict")


def import_target(target: str) -> Any:
    """The object at the dotted path ``target`` (``package.module.Name``); ImportError (one line naming it) when
    there is none."""
    parts = str(target).split(".")
    if len(parts) < 2 or not all(p.isidentifier() for p in parts):
        raise ImportError(f"weighting _target_ {target!r} is not a dotted path (package.module.Name)")
    for i in range(len(parts) - 1, 0, -1):  # the longest prefix that is a module; the rest are attributes
        name = ".".join(parts[:i])
        try:
            obj = importlib.import_module(name)
            break
        except ModuleNotFoundError as e:
            if e.name is None or not (name == e.name or name.startswith(e.name + ".")):
                raise ImportError(f"weighting _target_ {target!r}: importing {name} failed: {e}") from e
    else:
        raise ImportError(f"weighting _target_ {target!r} is not importable: no module {parts[0]!r} on the path")
    for attr in parts[i:]:
        if not hasattr(obj, attr):
            raise ImportError(f"weighting _target_ {target!r} is not importable: {name} has no {attr!r}")
        obj = getattr(obj, attr)
    return obj


def _split(node: Mapping[str, Any]) -> tuple[str, dict]:
    """(target, arguments) of a node; no ``_target_``: LearnedWeighting; a null argument: the constructor's default
    (left out, so that the recipe's LearnedWeighting keys left null do not reach a class that does not take them)."""
    args = {k: v for k, v in node.items() if v is not None}
    return args.pop("_target_", None) or DEFAULT_TARGET, args


def build_weighting(node: Mapping[str, Any]) -> nn.Module:
    """The module of a config node ``{"_target_": dotted path, **constructor kwargs}`` (no ``_target_``: the
    shipped :class:`~torchtrack.learn.model.LearnedWeighting`; null arguments: the constructor's defaults), e.g.
    ``train.model`` of torchtrack-train."""
    target, args = _split(node)
    model = import_target(target)(**args)
    if not isinstance(model, nn.Module):
        raise TypeError(f"weighting _target_ {target!r} built a {type(model).__name__}, not a torch.nn.Module")
    return model


_PLAIN = (type(None), bool, int, float, str)


def _with_defaults(factory: Any, args: dict) -> dict:
    """``args`` and the plain (None, bool, number, string) defaults of the other arguments of ``factory``: a
    checkpoint states every value the module was built with, so a default changed later does not change it."""
    try:
        params = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):  # no signature to read (a builtin): the given arguments are all there is
        return args
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    defaults = {p.name: p.default for p in params if p.kind in kinds and isinstance(p.default, _PLAIN)}
    return {**defaults, **args}


def weighting_spec(model: nn.Module, spec: Mapping[str, Any] | None = None) -> dict:
    """The config node that rebuilds ``model``: ``spec`` (the node it was built from) when given, else what the
    model says of itself (``{"_target_": its class, **model.config}``, as LearnedWeighting does)."""
    if spec is not None:
        target, args = _split(spec)
        return {"_target_": target, **_with_defaults(import_target(target), args)}
    cls = type(model)
    if not hasattr(model, "config"):
        raise ValueError(
            f"{cls.__qualname__} has no .config: pass the node it was built from, spec={{'_target_': ..., **kwargs}}"
        )
    if cls.__module__ == "__main__" or "<locals>" in cls.__qualname__:
        raise ValueError(f"{cls.__qualname__} is defined in a script or a function: define it in an importable module")
    return {"_target_": f"{cls.__module__}.{cls.__qualname__}", **model.config}


def save_checkpoint(
    path: str | Path, model: nn.Module, *, spec: Mapping[str, Any] | None = None, extra: dict | None = None
) -> Path:
    """Write ``model`` (and ``extra``: plain containers, numbers, strings, tensors) to ``path`` atomically.

    ``spec``: the config node ``model`` was built from (``{"_target_": dotted path, **constructor kwargs}``,
    :func:`build_weighting`); None for a model that describes itself with ``.config`` (LearnedWeighting). The file is
    written beside ``path``, read back with ``weights_only=True`` (so an ``extra`` that cannot be loaded fails here,
    not at load time), then renamed over ``path``. Returns ``path``.
    """
    path = Path(path)
    extra = dict(extra or {})
    if clash := sorted(set(extra) & set(_RESERVED)):
        raise ValueError(f"save_checkpoint: extra may not set the reserved keys {clash}")
    args = weighting_spec(model, spec)
    target = args.pop("_target_")
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    blob = dict(
        format=FORMAT, version=VERSION, cue_names=list(CUE_NAMES), cue_version=CUE_VERSION,
        target=target, model=args, state_dict=state, **extra,
    )  # fmt: skip

    def write(tmp: Path) -> None:
        torch.save(blob, tmp)
        try:
            torch.load(tmp, map_location="cpu", weights_only=True)
        except Exception as e:
            raise ValueError(
                f"save_checkpoint: {path}: extra must hold only plain Python containers, numbers, strings and "
                f"tensors (weights_only loading failed: {e})"
            ) from e

    return write_atomic(path, write)


def load_checkpoint(path: str | Path) -> tuple[nn.Module, dict]:
    """Read a checkpoint -> (module in eval mode, meta: every key but ``state_dict``; ``meta["target"]`` is the
    module's class, LearnedWeighting's for files written before checkpoints named it).

    Raises:
        FileNotFoundError: no file at ``path``.
        ImportError: the checkpoint's class cannot be imported here.
        ValueError: not a torchtrack weighting checkpoint, another format version, other cues, or weights that do
            not fit the rebuilt module.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"weighting checkpoint not found: {path}")
    blob = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        got = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise ValueError(f"{path}: not a {FORMAT!r} checkpoint (format {got!r})")
    if blob.get("version") != VERSION:
        raise ValueError(f"{path}: checkpoint version {blob.get('version')!r}; this torchtrack reads version {VERSION}")
    check_cue_names(blob["cue_names"], blob["cue_version"], str(path))
    blob.setdefault("target", DEFAULT_TARGET)
    try:
        model = build_weighting({"_target_": blob["target"], **blob["model"]})
    except ImportError as e:
        raise ImportError(f"{path}: {e}") from e
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as e:  # torch lists every key on a line of its own: the first one says what is wrong
        first = [ln.strip() for ln in str(e).splitlines() if ln.strip()][1:2] or [str(e)]
        raise ValueError(f"{path}: the weights do not fit {blob['target']}(**{blob['model']}): {first[0]}") from e
    meta = {k: v for k, v in blob.items() if k != "state_dict"}
    return model.eval(), meta


def learned_weighting(checkpoint: str | Path | None = None, **expected) -> nn.Module:
    """Hydra factory (``conf/weighting/learned.yaml``): the frozen module of ``checkpoint`` (None: the shipped
    :data:`DEFAULT_CHECKPOINT`), of the class the checkpoint names.

    Args:
        checkpoint: path of a ``.pt`` written by :func:`save_checkpoint`; None for the default model.
        **expected: constructor arguments (``mode``, ``sigma2_pix``, ...) the caller relies on. They do not
            override the checkpoint — a model is defined by what it was trained with — and a value that differs
            from the checkpoint's is a ValueError rather than a silent disagreement; None is not checked.
    """
    if checkpoint is None:
        if not DEFAULT_CHECKPOINT.is_file():
            raise FileNotFoundError(
                f"no trained model shipped ({DEFAULT_CHECKPOINT} is missing); train one with torchtrack-train "
                "or pass weighting.checkpoint=PATH"
            )
        checkpoint = DEFAULT_CHECKPOINT
    model, meta = load_checkpoint(checkpoint)
    config = meta["model"]
    expected = {k: v for k, v in expected.items() if v is not None}  # null in the config: not checked
    if unknown := sorted(set(expected) - set(config)):
        raise ValueError(f"learned_weighting: unknown arguments {unknown}; a checkpoint defines {sorted(config)}")
    if diff := {k: (v, config[k]) for k, v in expected.items() if v != config[k]}:
        pairs = ", ".join(f"{k}: config {a!r} vs checkpoint {b!r}" for k, (a, b) in diff.items())
        raise ValueError(f"learned_weighting: {checkpoint} was trained with other settings ({pairs})")
    cls = type(model)
    log.info("weighting: %s.%s from %s", cls.__module__, cls.__qualname__, checkpoint)
    return model.requires_grad_(False)
