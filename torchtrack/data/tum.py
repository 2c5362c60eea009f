"""Reader for RGB-D sequences in TUM RGB-D layout, and TUM trajectory file IO.

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgb.txt / depth.txt   "timestamp filename" per image (comment lines start with '#')
    groundtruth.txt       "timestamp tx ty tz qx qy qz qw", camera-to-world (optional)
    intrinsics.txt        "fx fy cx cy depth_scale" (optional; else a camera preset or explicit intrinsics)
    rgb/, depth/          PNG or JPEG colour; 16-bit PNG depth, metres = value / depth_scale, 0 = no measurement

Colour and depth are associated one-to-one by timestamp (greedy nearest, as TUM's associate.py) with a maximum
difference; each frame gets the nearest ground-truth pose within the same maximum difference.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.data.alignment import colour_intrinsics, depth_intrinsics, resolve_depth_alignment
from torchtrack.data.cameras import TUM_DEPTH_SCALE, get_camera
from torchtrack.data.errors import DataError
from torchtrack.geometry import intrinsics_matrix, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from torchtrack.io import write_text

log = logging.getLogger(__name__)

PathLike = str | os.PathLike


@dataclass
class RGBDFrame:
    """One frame of one sequence.

    Attributes:
        rgb: (3, H, W) float32 colour in [0, 1].
        depth: (1, H, W) float32 metres in the depth camera's pixel grid, 0 = no measurement.
        timestamp: colour timestamp in seconds.
        T_world_cam_gt: (4, 4) float64 ground-truth camera-to-world pose (identity where absent).
        gt_valid: ground truth present for this frame.
        index: frame index within the sequence.
    """

    rgb: Tensor
    depth: Tensor
    timestamp: float
    T_world_cam_gt: Tensor
    gt_valid: bool
    index: int


class Trajectory(NamedTuple):
    """timestamps (F,) float64 seconds; T_world_cam (F, 4, 4) float64 camera-to-world."""

    timestamps: np.ndarray
    T_world_cam: np.ndarray


# ----------------------------------------------------------------------------------------------- text files


def _read_rows(path: Path, n_fields: int) -> list[list[str]]:
    """Whitespace-split rows of a text file, skipping blank and '#' lines; each row has >= n_fields fields."""
    if not path.is_file():
        raise DataError(f"{path}: file not found")
    rows = []
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            fields = line.replace(",", " ").split()
            if len(fields) < n_fields:
                raise DataError(f"{path}:{lineno}: expected {n_fields} fields, got {len(fields)}: {line!r}")
            rows.append(fields)
    if not rows:
        raise DataError(f"{path}: no entries (empty or only comments)")
    return rows


def _floats(path: Path, rows: list[list[str]], cols: slice) -> np.ndarray:
    try:
        return np.array([[float(v) for v in r[cols]] for r in rows], dtype=np.float64)
    except ValueError as e:
        raise DataError(f"{path}: non-numeric value ({e})") from None


def read_list_file(path: PathLike) -> tuple[np.ndarray, list[str]]:
    """TUM image list "timestamp filename" -> (timestamps (F,) float64, filenames relative to the file's folder)."""
    path = Path(path)
    rows = _read_rows(path, 2)
    return _floats(path, rows, slice(0, 1))[:, 0], [r[1] for r in rows]


def read_tum_trajectory(path: PathLike) -> Trajectory:
    """TUM trajectory "timestamp tx ty tz qx qy qz qw" -> Trajectory(timestamps (F,), T_world_cam (F, 4, 4))."""
    path = Path(path)
    v = _floats(path, _read_rows(path, 8), slice(0, 8))
    q = torch.from_numpy(v[:, 4:8])  # xyzw, converted here and only here
    if (q.norm(dim=-1) < 1e-6).any():
        raise DataError(f"{path}: zero quaternion at row {int((q.norm(dim=-1) < 1e-6).nonzero()[0, 0]) + 1}")
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
    v = _floats(path, _read_rows(path, 4)[:1], slice(0, 5))[0]
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


def load_rgb(path: PathLike) -> Tensor:
    """Colour image (PNG/JPEG, 8 or 16 bit, colour or grayscale) -> (3, H, W) float32 RGB in [0, 1]."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: missing, unreadable or corrupt colour image")
    if img.dtype not in (np.uint8, np.uint16):
        raise DataError(f"{path}: colour image must be 8- or 16-bit, got {img.dtype}")
    if img.ndim == 2:
        chans = (img, img, img)
    elif img.shape[2] in (3, 4):
        chans = (img[..., 2], img[..., 1], img[..., 0])  # OpenCV stores BGR(A)
    else:
        raise DataError(f"{path}: colour image must have 1, 3 or 4 channels, got {img.shape[2]}")
    rgb = torch.from_numpy(np.stack(chans))  # 3,H,W; the stack copies into contiguous channel planes
    return rgb.float().div_(255.0 if img.dtype == np.uint8 else 65535.0)


def load_depth(path: PathLike, depth_scale: float) -> Tensor:
    """16-bit depth PNG -> (1, H, W) float32 metres (value / depth_scale), 0 = no measurement."""
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise DataError(f"{path}: missing, unreadable or corrupt depth image")
    if d.dtype != np.uint16 or d.ndim != 2:
        bits = 8 * d.dtype.itemsize
        raise DataError(f"{path}: depth must be single-channel 16-bit, got {bits}-bit with shape {d.shape}")
    if not d.any():
        raise DataError(f"{path}: depth image has no valid pixel (all zero)")
    return torch.from_numpy(d.astype(np.float32)).div_(depth_scale)[None]


# ----------------------------------------------------------------------------------------------- sequence


def _resolve_intrinsics(root: Path, camera, intrinsics, depth_scale) -> tuple[tuple, float, str]:
    """((fx, fy, cx, cy), depth_scale, source). intrinsics.txt > camera preset > explicit intrinsics."""
    file = root / "intrinsics.txt"
    preset = get_camera(camera) if camera is not None else None
    file_k, file_scale = read_intrinsics_file(file) if file.is_file() else (None, None)
    if file_k is not None:
        k, source = file_k, str(file)
    elif preset is not None:
        k, source = (preset.fx, preset.fy, preset.cx, preset.cy), f"camera preset {camera!r}"
    elif intrinsics is not None:
        if len(intrinsics) != 4:
            raise DataError(f"{root}: intrinsics must be (fx, fy, cx, cy), got {intrinsics!r}")
        k, source = tuple(float(x) for x in intrinsics), "explicit intrinsics"
    else:
        raise DataError(f"{root}: no intrinsics.txt, and neither a camera preset nor intrinsics were given")
    scale = file_scale or depth_scale or (preset.depth_scale if preset else TUM_DEPTH_SCALE)
    if scale <= 0:
        raise DataError(f"{root}: depth_scale must be positive, got {scale}")
    return k, float(scale), source


class TumSequence:
    """A TUM-layout RGB-D sequence: frames are loaded on demand by ``seq[i]`` -> RGBDFrame.

    Args:
        root: the sequence folder (holding rgb.txt, depth.txt, optional groundtruth.txt and intrinsics.txt).
        camera: camera preset name (cameras.CAMERAS), used when there is no intrinsics.txt.
        intrinsics: (fx, fy, cx, cy), used when there is neither intrinsics.txt nor a preset.
        depth_scale: stored depth value per metre; intrinsics.txt > this > preset (TUM: 5000).
        max_dt: maximum colour-depth and colour-ground-truth timestamp difference in seconds.
        T_color_depth: (4, 4) depth-to-colour extrinsic; identity (registered depth) when None.
        intrinsics_depth: (fx, fy, cx, cy) of the depth camera; equal to the colour ones when None.
        max_frames, stride: keep associated frames [::stride][:max_frames].
        depth_alignment: for depth not registered to colour, used only when neither T_color_depth nor
            intrinsics_depth is given. "none": depth as given. "auto": estimate the depth-to-colour pixel map
            from edges on 5 frames spread over the sequence (:func:`torchtrack.data.alignment.estimate_depth_shift`)
            and apply it when confident and it moves some pixel by >= 2 px. (dx, dy) or (dx, dy, scale): apply
            colour pixel = c + scale (depth pixel - c) + (dx, dy), c = (cx, cy). Applying sets K_depth
            (:func:`torchtrack.data.alignment.depth_intrinsics`), T_color_depth stays identity.
        intrinsics_camera: which camera the given intrinsics (file, preset or explicit) describe when a depth
            alignment is applied: "colour" (TUM convention; K_depth is derived) or "depth" (K_depth keeps them and
            the colour K is derived, :func:`torchtrack.data.alignment.colour_intrinsics`; metric for 7-Scenes,
            whose nominal 585 px are the depth camera's). Only the metric back-projection differs, not the map.

    Attributes: name, timestamps (F,) float64, groundtruth (F, 4, 4) float64 (identity where absent),
    gt_valid (F,) bool, K and K_depth (3, 3) float32, T_color_depth (4, 4) float32, depth_scale,
    rgb_paths, depth_paths, depth_shift (the estimated or given ShiftEstimate; None for "none", explicit
    extrinsics or images too small to estimate), depth_aligned (K_depth was set from depth_shift).
    """

    def __init__(
        self,
        root: PathLike,
        *,
        camera: str | None = None,
        intrinsics: tuple[float, float, float, float] | None = None,
        depth_scale: float | None = None,
        max_dt: float = 0.02,
        T_color_depth=None,
        intrinsics_depth: tuple[float, float, float, float] | None = None,
        max_frames: int | None = None,
        stride: int = 1,
        depth_alignment: str | tuple[float, ...] = "none",
        intrinsics_camera: str = "colour",
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(f"{self.root}: sequence folder not found")
        if stride < 1 or (max_frames is not None and max_frames < 1) or max_dt <= 0:
            raise ValueError(f"{self.root}: need stride >= 1, max_frames >= 1, max_dt > 0")
        self.name = self.root.resolve().name
        self._associate_images(max_dt, stride, max_frames)
        self._attach_groundtruth(max_dt)
        k, self.depth_scale, source = _resolve_intrinsics(self.root, camera, intrinsics, depth_scale)
        self.K = intrinsics_matrix(*k)
        self.K_depth = intrinsics_matrix(*intrinsics_depth) if intrinsics_depth is not None else self.K.clone()
        self.T_color_depth = self._extrinsic(T_color_depth)
        self._hw: tuple[int, int] | None = None
        explicit = T_color_depth is not None or intrinsics_depth is not None
        self._align_depth(depth_alignment, intrinsics_camera, explicit=explicit)
        log.info(
            "%s: %d frames, ground truth for %d, intrinsics from %s, depth_scale %g",
            self.name, len(self), int(self.gt_valid.sum()), source, self.depth_scale,
        )  # fmt: skip

    def _associate_images(self, max_dt: float, stride: int, max_frames: int | None) -> None:
        rgb_txt, depth_txt = self.root / "rgb.txt", self.root / "depth.txt"
        t_rgb, f_rgb = read_list_file(rgb_txt)
        t_d, f_d = read_list_file(depth_txt)
        ia, ib = associate(t_rgb, t_d, max_dt)
        if len(ia) == 0:
            raise DataError(
                f"{rgb_txt} / {depth_txt}: no colour-depth pair within max_dt={max_dt} s "
                f"(rgb {t_rgb.min():.6f}..{t_rgb.max():.6f} s, depth {t_d.min():.6f}..{t_d.max():.6f} s)"
            )
        ia, ib = ia[::stride][:max_frames], ib[::stride][:max_frames]
        self.timestamps = t_rgb[ia]
        self.depth_timestamps = t_d[ib]
        self.rgb_paths = [self.root / f_rgb[i] for i in ia]
        self.depth_paths = [self.root / f_d[i] for i in ib]
        for listing, paths in ((rgb_txt, self.rgb_paths), (depth_txt, self.depth_paths)):
            missing = next((p for p in paths if not p.is_file()), None)
            if missing is not None:
                raise DataError(f"{missing}: image listed in {listing.name} not found")

    def _attach_groundtruth(self, max_dt: float) -> None:
        F = len(self.timestamps)
        self.groundtruth = np.tile(np.eye(4), (F, 1, 1))
        self.gt_valid = np.zeros(F, dtype=bool)
        gt_file = self.root / "groundtruth.txt"
        if not gt_file.is_file():
            return
        t_gt, T_gt = read_tum_trajectory(gt_file)
        idx, self.gt_valid = nearest_within(self.timestamps, t_gt, max_dt)
        self.groundtruth[self.gt_valid] = T_gt[idx[self.gt_valid]]
        if not self.gt_valid.any():
            log.warning("%s: no ground-truth pose within max_dt=%g s of any frame", gt_file, max_dt)

    def _extrinsic(self, T) -> Tensor:
        if T is None:
            return torch.eye(4)
        T = torch.as_tensor(np.asarray(T, dtype=np.float64)).float()
        if T.shape != (4, 4) or not torch.allclose(T[3], torch.tensor([0.0, 0, 0, 1])):
            raise DataError(f"{self.root}: T_color_depth must be a 4x4 rigid transform, got shape {tuple(T.shape)}")
        return T

    def _align_depth(self, mode, intrinsics_camera: str, *, explicit: bool) -> None:
        """Set depth_shift, depth_aligned and, when applied, K_depth or K; see the class docstring."""
        if intrinsics_camera not in ("colour", "depth"):
            raise ValueError(f"{self.root}: intrinsics_camera must be 'colour' or 'depth', got {intrinsics_camera!r}")
        if explicit and not isinstance(mode, str):
            raise ValueError(f"{self.root}: give either depth_alignment {mode!r} or T_color_depth/intrinsics_depth")
        self.depth_shift, self.depth_aligned = resolve_depth_alignment(
            "none" if explicit else mode, self.K, lambda i: self._load(i)[:2], len(self), self.name
        )
        if self.depth_aligned and intrinsics_camera == "colour":
            self.K_depth = depth_intrinsics(self.K, self.depth_shift)
        elif self.depth_aligned:
            self.K = colour_intrinsics(self.K_depth, self.depth_shift)

    @property
    def has_groundtruth(self) -> bool:
        return bool(self.gt_valid.any())

    def __len__(self) -> int:
        return len(self.timestamps)

    def __getitem__(self, i: int) -> RGBDFrame:
        """Load frame i: decode colour and depth (the per-frame hot path: two imreads and two conversions)."""
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"{self.name}: frame {i} out of range [0, {n})")
        i = i % n
        rgb, depth, T = self._load(i)
        return RGBDFrame(rgb, depth, float(self.timestamps[i]), T, bool(self.gt_valid[i]), i)

    def _load(self, i: int) -> tuple[Tensor, Tensor, Tensor]:
        """(rgb (3, H, W), depth (1, H, W), T_world_cam_gt (4, 4)) of frame i in [0, len)."""
        rgb = load_rgb(self.rgb_paths[i])
        depth = load_depth(self.depth_paths[i], self.depth_scale)
        self._check_size(i, rgb, depth)
        return rgb, depth, torch.from_numpy(self.groundtruth[i].copy())

    def _check_size(self, i: int, rgb: Tensor, depth: Tensor) -> None:
        if rgb.shape[1:] != depth.shape[1:]:
            raise DataError(
                f"{self.depth_paths[i]}: depth size {tuple(depth.shape[1:])} differs from colour "
                f"{tuple(rgb.shape[1:])} ({self.rgb_paths[i].name})"
            )
        if self._hw is None:
            self._hw = tuple(rgb.shape[1:])
        elif tuple(rgb.shape[1:]) != self._hw:
            raise DataError(
                f"{self.rgb_paths[i]}: image size {tuple(rgb.shape[1:])} differs from the sequence's {self._hw}"
            )

    def __repr__(self) -> str:
        return f"TumSequence({str(self.root)!r}, frames={len(self)}, gt={int(self.gt_valid.sum())})"
