"""Reader for RGB-D sequences in TUM RGB-D layout (the files themselves: :mod:`torchtrack.data.tum_io`).

Layout (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats)::

    rgb.txt / depth.txt   "timestamp filename" per image (comment lines start with '#')
    groundtruth.txt       "timestamp tx ty tz qx qy qz qw", camera-to-world (optional)
    intrinsics.txt        "fx fy cx cy depth_scale" (optional; explicit intrinsics override it, else a camera preset)
    rgb/, depth/          PNG or JPEG colour; 16-bit PNG depth, metres = value / depth_scale, 0 = no measurement

Colour and depth are associated one-to-one by timestamp (greedy nearest, as TUM's associate.py) with a maximum
difference; each frame gets the nearest ground-truth pose within the same maximum difference.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from torchtrack.data.alignment import colour_intrinsics, depth_intrinsics, resolve_depth_alignment
from torchtrack.data.cameras import TUM_DEPTH_SCALE, get_camera
from torchtrack.data.errors import DataError
from torchtrack.data.tum_io import (
    associate,
    load_depth,
    load_rgb,
    nearest_within,
    read_intrinsics_file,
    read_list_file,
    read_tum_trajectory,
)
from torchtrack.geometry import intrinsics_matrix

log = logging.getLogger(__name__)

PathLike = str | os.PathLike


@dataclass
class RGBDFrame:
    """One frame of one sequence.

    Attributes:
        rgb: (3, H, W) float32 colour in [0, 1].
        depth: (1, H, W) float32 metres in the depth camera's pixel grid, 0 = no measurement.
        timestamp: colour timestamp in seconds.
        T_world_color_gt: (4, 4) float64 ground truth: the colour camera's pose, camera-to-world (identity where absent).
        gt_valid: ground truth present for this frame.
        index: frame index within the sequence.
    """

    rgb: Tensor
    depth: Tensor
    timestamp: float
    T_world_color_gt: Tensor
    gt_valid: bool
    index: int


# ----------------------------------------------------------------------------------------------- sequence


def _resolve_intrinsics(root: Path, camera, intrinsics, depth_scale) -> tuple[tuple, float, str]:
    """((fx, fy, cx, cy), depth_scale, source). Explicit values > intrinsics.txt > camera preset; an explicit value
    that disagrees with intrinsics.txt overrides it, with a warning (never silently ignored)."""
    file = root / "intrinsics.txt"
    preset = get_camera(camera) if camera is not None else None
    file_k, file_scale = read_intrinsics_file(file) if file.is_file() else (None, None)
    if intrinsics is not None:
        if len(intrinsics) != 4:
            raise DataError(f"{root}: intrinsics must be (fx, fy, cx, cy), got {intrinsics!r}")
        k, source = tuple(float(x) for x in intrinsics), "explicit intrinsics"
        if file_k is not None and tuple(file_k) != k:
            log.warning("%s: explicit intrinsics %s override the file's %s", file, list(k), [float(x) for x in file_k])
    elif file_k is not None:
        k, source = file_k, str(file)
    elif preset is not None:
        k, source = (preset.fx, preset.fy, preset.cx, preset.cy), f"camera preset {camera!r}"
    else:
        raise DataError(f"{root}: no intrinsics.txt, and neither a camera preset nor intrinsics were given")
    if depth_scale is not None and file_scale is not None and float(depth_scale) != file_scale:
        log.warning("%s: explicit depth_scale %g overrides the file's %g", file, depth_scale, file_scale)
    scale = depth_scale or file_scale or (preset.depth_scale if preset else TUM_DEPTH_SCALE)
    if scale <= 0:
        raise DataError(f"{root}: depth_scale must be positive, got {scale}")
    return k, float(scale), source


class TumSequence:
    """A TUM-layout RGB-D sequence: frames are loaded on demand by ``seq[i]`` -> RGBDFrame.

    Args:
        root: the sequence folder (holding rgb.txt, depth.txt, optional groundtruth.txt and intrinsics.txt).
        camera: camera preset name (cameras.CAMERAS), used when there is no intrinsics.txt.
        intrinsics: (fx, fy, cx, cy); overrides intrinsics.txt (with a warning when they differ) and the preset.
        depth_scale: stored depth value per metre; this > intrinsics.txt (a warning when they differ) > preset
            (TUM: 5000).
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
        min_depth_fraction: loading a frame with fewer pixels with depth than this fraction raises DataError.
        on_bad_frame, max_bad_fraction: what lockstep iteration does with a frame that fails to load
            (:class:`torchtrack.data.batching.FrameCursor`): "drop" it (unless more than ``max_bad_fraction`` of
            the frames are bad) or "error".

    Attributes: name, timestamps (F,) float64, unpaired (colour images listed without a depth image within
    ``max_dt``: left out, before ``stride`` and ``max_frames``), groundtruth (F, 4, 4) float64 (identity where absent),
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
        min_depth_fraction: float = 0.0,
        on_bad_frame: str = "drop",
        max_bad_fraction: float = 0.25,
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DataError(f"{self.root}: sequence folder not found")
        if stride < 1 or (max_frames is not None and max_frames < 1) or max_dt <= 0:
            raise ValueError(f"{self.root}: need stride >= 1, max_frames >= 1, max_dt > 0")
        if on_bad_frame not in ("drop", "error"):
            raise ValueError(f"{self.root}: on_bad_frame must be 'drop' or 'error', got {on_bad_frame!r}")
        self.min_depth_fraction, self.on_bad_frame, self.max_bad_fraction = (
            min_depth_fraction,
            on_bad_frame,
            max_bad_fraction,
        )
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
        n = self.unpaired
        unpaired = f", {n} colour frame{'s' * (n != 1)} without depth within {max_dt:g} s left out" if n else ""
        log.info(
            "%s: %d frames, ground truth for %d, intrinsics from %s, depth_scale %g%s",
            self.name, len(self), int(self.gt_valid.sum()), source, self.depth_scale, unpaired,
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
        self.unpaired = len(t_rgb) - len(ia)
        ia, ib = ia[::stride][:max_frames], ib[::stride][:max_frames]
        self.timestamps = t_rgb[ia]
        self.depth_timestamps = t_d[ib]
        self.rgb_paths = [self.root / f_rgb[i] for i in ia]
        self.depth_paths = [self.root / f_d[i] for i in ib]
        self._check_listed_files(rgb_txt, depth_txt)

    def _check_listed_files(self, rgb_txt: Path, depth_txt: Path) -> None:
        """A listed image whose file is missing is a dropped frame, like an unreadable one (one warning line here,
        one per frame when it is reached); it is an error with ``on_bad_frame="error"`` or when more than
        ``max_bad_fraction`` of the frames miss a file, or all of them do."""
        missing = [i for i, (a, b) in enumerate(zip(self.rgb_paths, self.depth_paths, strict=True))
                   if not (a.is_file() and b.is_file())]  # fmt: skip
        if not missing:
            return
        i = missing[0]
        listing, first = (
            (rgb_txt, self.rgb_paths[i]) if not self.rgb_paths[i].is_file() else (depth_txt, self.depth_paths[i])
        )
        what = f"{first}: image listed in {listing.name} not found"
        n = len(self.rgb_paths)
        if self.on_bad_frame == "error" or len(missing) == n or len(missing) > self.max_bad_fraction * n:
            extra = "" if len(missing) == 1 else f" ({len(missing)} of {n} frames miss a file)"
            raise DataError(what + extra)
        log.warning("%s (%d of %d frames miss a file: they will be dropped)", what, len(missing), n)

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
        if T is None:  # the reader's tensors are host tensors; the runner moves the batch
            return torch.eye(4, device="cpu")
        T = torch.as_tensor(np.asarray(T, dtype=np.float64)).float()
        if T.shape != (4, 4) or not torch.allclose(T[3], torch.tensor([0.0, 0, 0, 1], device="cpu")):
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
        """(rgb (3, H, W), depth (1, H, W), T_world_color_gt (4, 4)) of frame i in [0, len); DataError when unusable."""
        rgb = load_rgb(self.rgb_paths[i])
        depth = load_depth(self.depth_paths[i], self.depth_scale)
        self._check_size(i, rgb, depth)
        if self.min_depth_fraction > 0:
            fraction = float(torch.count_nonzero(depth)) / depth.numel()
            if fraction < self.min_depth_fraction:
                raise DataError(
                    f"{self.depth_paths[i]}: only {fraction:.2%} of the pixels have depth "
                    f"(min_depth_fraction={self.min_depth_fraction:g})"
                )
        return rgb, depth, torch.from_numpy(self.groundtruth[i].copy())

    def _check_size(self, i: int, rgb: Tensor, depth: Tensor) -> None:
        """Each image against the sequence's size (H, W) (the first frame's whose two images agree): the error names
        the file that differs, or both when they disagree before the size is known."""
        hw_rgb, hw_depth = tuple(rgb.shape[1:]), tuple(depth.shape[1:])
        if self._hw is None and hw_rgb == hw_depth:
            self._hw = hw_rgb
        if self._hw is None:
            raise DataError(
                f"{self.depth_paths[i]}: depth size {hw_depth} differs from colour {hw_rgb} ({self.rgb_paths[i].name})"
            )
        for path, hw, what in ((self.rgb_paths[i], hw_rgb, "colour"), (self.depth_paths[i], hw_depth, "depth")):
            if hw != self._hw:
                raise DataError(f"{path}: {what} image size {hw} differs from the sequence's {self._hw}")

    def __repr__(self) -> str:
        return f"TumSequence({str(self.root)!r}, frames={len(self)}, gt={int(self.gt_valid.sum())})"
