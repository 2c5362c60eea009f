"""TUM RGB-D file IO: list files, trajectories (``timestamp tx ty tz qx qy qz qw``, camera-to-world; quaternions
are converted here and nowhere else), intrinsics.txt, timestamp association, colour and depth images.

The sequence built from these files is :class:`torchtrack.data.tum.TumSequence`.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.data.errors import DataError

try:  # a faster PNG decoder than OpenCV's (same pixels); optional: without it OpenCV decodes everything
    import imagecodecs
except ImportError:  # pragma: no cover - installed with torchtrack
    imagecodecs = None
from torchtrack.geometry import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from torchtrack.io import write_text

log = logging.getLogger(__name__)

# A corrupt image makes OpenCV's decoder print its own "[ERROR...] readHeader ..." line on stderr beside our warning,
# which already names the file and the reason (a missing, unreadable or corrupt image is a dropped frame).
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

PathLike = str | os.PathLike


class Trajectory(NamedTuple):
    """timestamps (F,) float64 seconds; T_world_cam (F, 4, 4) float64 camera-to-world."""

    timestamps: np.ndarray
    T_world_cam: np.ndarray


# ----------------------------------------------------------------------------------------------- text files


def _read_rows(path: Path, n_fields: int) -> tuple[list[list[str]], list[int]]:
    """Whitespace-split rows of a text file, skipping blank and '#' lines; each row has >= n_fields fields.

    Returns (rows, their 1-based line numbers)."""
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    rows, linenos = [], []
    with open(path, errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").split()
            if len(fields) < n_fields:
                raise DataError(f"{path}:{lineno}: expected {n_fields} fields, got {len(fields)}: {line!r}")
            rows.append(fields)
            linenos.append(lineno)
    if not rows:
        raise DataError(f"{path}: no entries (empty or only comments)")
    return rows, linenos


def _floats(path: Path, rows: list[list[str]], cols: slice, linenos: list[int]) -> np.ndarray:
    """The numeric columns ``cols`` of ``rows`` (F, C) float64; a non-numeric or non-finite value is an error."""
    try:
        v = np.array([[float(x) for x in r[cols]] for r in rows], dtype=np.float64)
    except ValueError as e:
        raise DataError(f"{path}: non-numeric value ({e})") from None
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        k = int(bad.nonzero()[0][0])
        raise DataError(f"{path}:{linenos[k]}: non-finite value in {' '.join(rows[k][cols])!r}")
    return v


def _in_time_order(path: Path, t: np.ndarray, linenos: list[int]) -> np.ndarray:
    """Indices that put rows in time order (stable) without repeated timestamps (the first one is kept), with one
    warning line each when the file was not sorted or repeated a timestamp (TUM files are ordered by time)."""
    order = np.argsort(t, kind="stable")
    if (np.diff(t) < 0).any():
        k = int((np.diff(t) < 0).nonzero()[0][0])
        log.warning("%s:%d: not sorted by time (%.6f after %.6f); sorted", path, linenos[k + 1], t[k + 1], t[k])
    ts = t[order]
    dup = np.concatenate([[False], ts[1:] == ts[:-1]])
    if dup.any():
        first = linenos[int(order[int(dup.nonzero()[0][0])])]
        log.warning("%s:%d: %d repeated timestamp(s) (first %.6f); the later rows are dropped",
                    path, first, int(dup.sum()), ts[dup][0])  # fmt: skip
    return order[~dup]


def read_list_file(path: PathLike) -> tuple[np.ndarray, list[str]]:
    """TUM image list "timestamp filename" -> (timestamps (F,) float64 increasing, filenames relative to the file's
    folder). Unsorted rows are sorted and repeated timestamps dropped, with a warning (:func:`_in_time_order`)."""
    path = Path(path)
    rows, linenos = _read_rows(path, 2)
    t = _floats(path, rows, slice(0, 1), linenos)[:, 0]
    keep = _in_time_order(path, t, linenos)
    return t[keep], [rows[i][1] for i in keep]


def read_tum_trajectory(path: PathLike, unit_tol: float = 1e-2) -> Trajectory:
    """TUM trajectory "timestamp tx ty tz qx qy qz qw" -> Trajectory(timestamps (F,), T_world_cam (F, 4, 4)).

    Rows come out in time order without repeated timestamps (:func:`_in_time_order`). A non-finite value, or a
    quaternion whose norm is off 1 by more than ``unit_tol`` (rounded files are within 1e-3), is an error naming
    the file and line."""
    path = Path(path)
    rows, linenos = _read_rows(path, 8)
    v = _floats(path, rows, slice(0, 8), linenos)
    norm = np.linalg.norm(v[:, 4:8], axis=1)
    bad = np.abs(norm - 1.0) > unit_tol
    if bad.any():
        k = int(bad.nonzero()[0][0])
        what = "zero quaternion" if norm[k] < 1e-6 else f"quaternion not of unit norm ({norm[k]:.6g})"
        raise DataError(f"{path}:{linenos[k]}: {what}")
    v = v[_in_time_order(path, v[:, 0], linenos)]
    q = torch.from_numpy(v[:, 4:8])  # xyzw, converted here and only here
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = quat_xyzw_to_matrix(q).numpy()
    T[:, :3, 3] = v[:, 1:4]
    return Trajectory(v[:, 0].copy(), T)


def write_tum_trajectory(path: PathLike, timestamps, T_world_cam) -> Path:
    """Write (F,) timestamps and (F, 4, 4) camera-to-world poses as a TUM trajectory, atomically.

    Quaternions are xyzw with w >= 0; 9 decimals. Writes a temporary file in the target folder, then renames it,
    so that a reader never sees a half-written file.
    """
    path = Path(path)
    t = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    T = torch.as_tensor(np.asarray(T_world_cam, dtype=np.float64))
    if T.shape != (len(t), 4, 4):
        raise ValueError(
            f"write_tum_trajectory({path}): need T_world_cam (F, 4, 4) for F={len(t)}, got {tuple(T.shape)}"
        )
    q = matrix_to_quat_xyzw(T[:, :3, :3]).numpy()
    rows = np.concatenate([t[:, None], T[:, :3, 3].numpy(), q], axis=1)
    text = "# timestamp tx ty tz qx qy qz qw\n" + "".join(" ".join(f"{x:.9f}" for x in r) + "\n" for r in rows)
    return write_text(path, text)


def read_intrinsics_file(path: PathLike) -> tuple[tuple[float, float, float, float], float | None]:
    """intrinsics.txt "fx fy cx cy [depth_scale]" -> ((fx, fy, cx, cy), depth_scale or None)."""
    path = Path(path)
    rows, linenos = _read_rows(path, 4)
    v = _floats(path, rows[:1], slice(0, 5), linenos)[0]
    if not (v[0] > 0 and v[1] > 0) or (len(v) == 5 and v[4] <= 0):
        raise DataError(f"{path}: focal lengths and depth_scale must be positive, got {v.tolist()}")
    return (v[0], v[1], v[2], v[3]), (float(v[4]) if len(v) == 5 else None)


# ----------------------------------------------------------------------------------------------- association


def associate(t_a: np.ndarray, t_b: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one timestamp matching, greedy by smallest |t_a - t_b| < max_dt (TUM associate.py).

    Returns index arrays (ia, ib), sorted by ia; empty when nothing matches.
    """
    t_a, t_b = np.asarray(t_a, np.float64), np.asarray(t_b, np.float64)
    order = np.argsort(t_b, kind="stable")
    lo = np.searchsorted(t_b[order], t_a - max_dt, side="left")
    hi = np.searchsorted(t_b[order], t_a + max_dt, side="right")
    ia = np.repeat(np.arange(len(t_a)), hi - lo)  # candidate pairs inside the window only
    ib = order[np.concatenate([np.arange(s, e) for s, e in zip(lo, hi, strict=True)] or [np.zeros(0, int)])]
    dt = np.abs(t_a[ia] - t_b[ib])
    keep = dt < max_dt
    ia, ib, dt = ia[keep], ib[keep], dt[keep]
    used_a, used_b = np.zeros(len(t_a), bool), np.zeros(len(t_b), bool)
    pairs = []
    for k in np.lexsort((ib, ia, dt)):  # smallest difference first, ties by index: deterministic
        if not used_a[ia[k]] and not used_b[ib[k]]:
            used_a[ia[k]] = used_b[ib[k]] = True
            pairs.append((ia[k], ib[k]))
    pairs.sort()
    out = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    return out[:, 0], out[:, 1]


def nearest_within(t_query: np.ndarray, t_ref: np.ndarray, max_dt: float) -> tuple[np.ndarray, np.ndarray]:
    """For each query time, the index of the nearest reference time and whether it is within max_dt.

    Returns (idx (F,) int64, valid (F,) bool); idx is 0 where not valid. Not one-to-one (ground truth is
    usually denser than the images).
    """
    t_query, t_ref = np.asarray(t_query, np.float64), np.asarray(t_ref, np.float64)
    order = np.argsort(t_ref, kind="stable")
    s = t_ref[order]
    j = np.clip(np.searchsorted(s, t_query), 1, max(len(s) - 1, 1))
    left = np.abs(t_query - s[j - 1]) <= np.abs(s[np.minimum(j, len(s) - 1)] - t_query)
    j = np.where(left, j - 1, np.minimum(j, len(s) - 1))
    valid = np.abs(s[j] - t_query) < max_dt
    return np.where(valid, order[j], 0), valid


# ----------------------------------------------------------------------------------------------- images


def _unreadable(path: PathLike, kind: str) -> DataError:
    """Why OpenCV could not decode ``path`` (checked only after it failed: no extra system call per frame)."""
    why = f"{kind} image not found" if not Path(path).is_file() else f"unreadable or corrupt {kind} image"
    return DataError(f"{path}: {why}")


_PNG = b"\x89PNG\r\n\x1a\n"


def imread(path: PathLike, decoder: str = "auto") -> tuple[np.ndarray | None, bool]:
    """``cv2.imread(path, IMREAD_UNCHANGED)``'s pixels and whether its channels are in RGB(A) order (else OpenCV's
    BGR(A)). ``decoder="auto"``: 8- and 16-bit grayscale, RGB and RGBA PNGs are decoded by imagecodecs where installed
    (the same pixels, ``tests/test_tum_io.py``; measured 4.8 vs 6.7 ms of CPU per 640x480 colour frame, 2.1 vs 2.4 ms
    per depth frame), everything else by OpenCV; ``"opencv"``: OpenCV only. None where unreadable."""
    if decoder == "auto" and imagecodecs is not None:
        try:
            data = Path(path).read_bytes()
        except OSError:
            data = b""
        # IHDR: bit depth at byte 24, colour type at 25 (0 grey, 2 RGB, 6 RGBA; palettes and grey+alpha go to OpenCV)
        if data[:8] == _PNG and len(data) > 25 and data[24] in (8, 16) and data[25] in (0, 2, 6):
            try:
                return imagecodecs.png_decode(data), True
            except Exception:  # noqa: BLE001 - any decoder error: OpenCV decides below
                pass
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED), False


def load_rgb(path: PathLike, decoder: str = "auto") -> Tensor:
    """Colour image (PNG/JPEG, 8 or 16 bit, colour or grayscale) -> (3, H, W) float32 RGB in [0, 1] (``decoder``:
    :func:`imread`'s)."""
    img, rgb_order = imread(path, decoder)
    if img is None:
        raise _unreadable(path, "colour")
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: colour image must be 8- or 16-bit, got {img.dtype}")
    if img.ndim == 2:
        chans = (img, img, img)
    elif img.shape[2] in (3, 4):
        chans = (img[..., 0], img[..., 1], img[..., 2]) if rgb_order else (img[..., 2], img[..., 1], img[..., 0])
    else:
        raise DataError(f"{path}: colour image must have 1, 3 or 4 channels, got {img.shape[2]}")
    rgb = torch.from_numpy(np.stack(chans))  # 3,H,W; the stack copies into contiguous channel planes
    return rgb.float().div_(255.0 if img.dtype == np.uint8 else 65535.0)


def load_depth(path: PathLike, depth_scale: float, decoder: str = "auto") -> Tensor:
    """16-bit depth PNG -> (1, H, W) float32 metres (value / depth_scale), 0 = no measurement (``decoder``:
    :func:`imread`'s)."""
    d = imread(path, decoder)[0]
    if d is None:
        raise _unreadable(path, "depth")
    if d.dtype != np.uint16 or d.ndim != 2:
        bits = 8 * d.dtype.itemsize
        raise DataError(f"{path}: depth must be single-channel 16-bit, got {bits}-bit with shape {d.shape}")
    if not d.any():
        raise DataError(f"{path}: depth image has no valid pixel (all zero)")
    return torch.from_numpy(d.astype(np.float32)).div_(depth_scale)[None]
