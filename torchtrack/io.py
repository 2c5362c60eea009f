"""Atomic file writes: every output goes to a temporary name beside its target and is renamed over it, so a
reader (or a later run that resumes) never sees half a file and a failed write leaves the previous file intact."""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Callable
from pathlib import Path


def _file_mode() -> int:
    """The mode a plain ``open(path, "w")`` gives a new file: 0o666 less the process umask."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


FILE_MODE = _file_mode()  # read once: os.umask is process-wide, so reading it per call would race other threads


def check_writable(folder: str | Path) -> None:
    """Create ``folder`` if needed and write and remove a probe file in it; OSError (one line) when that fails.

    Run before long work, so that an unwritable output folder is found before the results exist."""
    folder = Path(folder)
    probe = folder / f".write-probe.{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise OSError(f"{folder}: output folder not writable ({e.strerror or e})") from None


def write_atomic(path: str | Path, writer: Callable[[Path], object]) -> Path:
    """Call ``writer(tmp)`` on a temporary path in ``path``'s folder (created if needed), then rename it to ``path``.

    The temporary name keeps ``path``'s suffix (writers such as ``cv2.imwrite`` choose the format by it) and is
    unique per process and call; it is removed when ``writer`` or the rename fails. The file gets the normal mode
    (:data:`FILE_MODE`) whatever mode ``writer`` created it with. Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}-{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        writer(tmp)
        os.chmod(tmp, FILE_MODE)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (:func:`write_atomic`)."""
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def write_json(path: str | Path, data: dict, indent: int | None = 2) -> Path:
    """Write ``data`` as JSON (and a final newline) to ``path`` atomically (:func:`write_atomic`)."""
    return write_text(path, json.dumps(data, indent=indent) + "\n")
