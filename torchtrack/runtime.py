"""Process-level settings for fast per-frame work on CPU, and the device a run tracks on."""

from __future__ import annotations

import ctypes
import logging
import sys

import torch

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4  # glibc mallopt parameters


def tune_allocator() -> bool:
    """Keep freed memory in the heap instead of returning it to the OS (glibc only).

    The per-frame stages allocate image-sized temporaries; by default glibc serves each with a fresh
    ``mmap`` and unmaps it on free, so every frame pays page faults for the same buffers again (measured
    here: the selection stage's time halves and stops fluctuating). Returns whether it was applied.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_MAX, 0) == 1 and libc.mallopt(_M_TRIM_THRESHOLD, 1 << 30) == 1
    except (OSError, AttributeError):
        return False
    log.debug("glibc allocator tuned: %s", ok)
    return ok


def configure(threads: int | None) -> None:
    """Apply the run's CPU settings: allocator tuning and torch's intra-op thread count."""
    tune_allocator()
    if threads:
        torch.set_num_threads(int(threads))


def resolve_device(device: str | torch.device | None) -> torch.device:
    """The ``torch.device`` that ``device`` names (``cpu``, ``cuda``, ``cuda:N``; None: cpu). ValueError (one line)
    for another name, or for CUDA where this torch or machine has none."""
    try:
        dev = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError) as e:
        raise ValueError(f"device={device}: not a torch device ({e}); use cpu or cuda") from None
    if dev.type not in ("cpu", "cuda"):
        raise ValueError(f"device={device}: use cpu or cuda")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            why = "this torch is built without CUDA" if torch.version.cuda is None else "no CUDA GPU is visible"
            raise ValueError(
                f"device={device}: CUDA is not available ({why}, torch {torch.__version__}); use device=cpu"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device={device}: only {torch.cuda.device_count()} CUDA device(s) here")
    return dev
