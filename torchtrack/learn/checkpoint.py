"""Checkpoints of the learned weighting: one ``.pt`` file that rebuilds the module and says what it expects.

Layout (a plain dict, loadable with ``torch.load(weights_only=True)``)::

    {"format": "torchtrack-weighting", "version": 1,
     "cue_names": [...], "cue_version": int,      # the cues the model was trained on (torchtrack.filter.cues)
     "model": {constructor kwargs},               # LearnedWeighting(**model): mode, sigma2s, width, bounds
     "state_dict": {...},
     **extra}                                     # the trainer's resolved config, metrics, ...

The module's variances and mode are part of what it learned, so they come from the checkpoint only:
:func:`learned_weighting` (the Hydra factory) refuses a config that disagrees with them.
"""

from __future__ import annotations

from pathlib import Path

import torch

from torchtrack.filter.cues import CUE_NAMES, CUE_VERSION, check_cue_names
from torchtrack.io import write_atomic
from torchtrack.learn.model import LearnedWeighting

FORMAT = "torchtrack-weighting"
VERSION = 1  # bump when the layout or the model's fixed definition (e.g. model.CUE_TRANSFORMS) changes
DEFAULT_CHECKPOINT = Path(__file__).parent / "weights" / "default.pt"
_RESERVED = ("format", "version", "cue_names", "cue_version", "model", "state_dict")


def save_checkpoint(path: str | Path, model: LearnedWeighting, *, extra: dict | None = None) -> Path:
    """Write ``model`` (and ``extra``: plain containers, numbers, strings, tensors) to ``path`` atomically.

    The file is written beside ``path``, read back with ``weights_only=True`` (so an ``extra`` that cannot be
    loaded fails here, not at load time), then renamed over ``path``. Returns ``path``.
    """
    path = Path(path)
    extra = dict(extra or {})
    if clash := sorted(set(extra) & set(_RESERVED)):
        raise ValueError(f"save_checkpoint: extra may not set the reserved keys {clash}")
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    blob = dict(
        format=FORMAT, version=VERSION, cue_names=list(CUE_NAMES), cue_version=CUE_VERSION,
        model=model.config, state_dict=state, **extra,
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


def load_checkpoint(path: str | Path) -> tuple[LearnedWeighting, dict]:
    """Read a checkpoint -> (module in eval mode, meta: every key but ``state_dict``).

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: not a torchtrack weighting checkpoint, another format version, or other cues.
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
    model = LearnedWeighting(**blob["model"])
    model.load_state_dict(blob["state_dict"])
    meta = {k: v for k, v in blob.items() if k != "state_dict"}
    return model.eval(), meta


def learned_weighting(checkpoint: str | Path | None = None, **expected) -> LearnedWeighting:
    """Hydra factory (``conf/weighting/learned.yaml``): the frozen module of ``checkpoint`` (None: the shipped
    :data:`DEFAULT_CHECKPOINT`).

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
    model, _ = load_checkpoint(checkpoint)
    config = model.config
    expected = {k: v for k, v in expected.items() if v is not None}  # null in the config: not checked
    if unknown := sorted(set(expected) - set(config)):
        raise ValueError(f"learned_weighting: unknown arguments {unknown}; a checkpoint defines {sorted(config)}")
    if diff := {k: (v, config[k]) for k, v in expected.items() if v != config[k]}:
        pairs = ", ".join(f"{k}: config {a!r} vs checkpoint {b!r}" for k, (a, b) in diff.items())
        raise ValueError(f"learned_weighting: {checkpoint} was trained with other settings ({pairs})")
    return model.requires_grad_(False)
