"""Frames from Python: track RGB-D frames given as arrays, frame by frame, one stream or B streams in lockstep.

    from torchtrack.stream import RGBDTracker

    tracker = RGBDTracker(K, depth_scale=1000.0)  # the CLI's config (overrides=[...]), on device="cpu" | "cuda"
    for color, depth in camera:  # (H, W, 3) uint8 RGB, (H, W) uint16 depth
        out = tracker.track(color, depth)  # out.T_world_color: (4, 4) camera-to-world

Frames in, poses out, no ground truth: the world is the first frame's colour camera. A TUM-layout folder's frames, paired
as the CLI pairs them, come from :func:`tum_frames`. The CLI's runner (:func:`torchtrack.run.run_tracker`) steps the
same :class:`~torchtrack.pipeline.Tracker` on the same frames; it owns ground truth and anchors the world there.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack.data.batching import FrameCursor
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import TumSequence
from torchtrack.geometry.rig import T_world_depth_from_color, color_poses
from torchtrack.runtime import configure, resolve_device

if TYPE_CHECKING:
    from omegaconf import DictConfig

    from torchtrack.pipeline import StepResult


class FramePose(NamedTuple):
    """One frame's result from :meth:`RGBDTracker.track`: numpy where the colour came as numpy, else torch on the
    colour's device; with a leading B for B streams, else plain numbers.

    Attributes:
        T_world_color: (4, 4) or (B, 4, 4) float64 the colour camera's pose, camera-to-world; the world is the first
            frame's colour camera.
        features: features tracked into this frame.
        reprojection_px: their mean reprojection error, eq. (16), in pixels.
        reselected: a new model (new features) was taken at this frame.
        lost: the loss check found tracking lost here (the pose is then the relocalised one, or a guess).
    """

    T_world_color: Any
    features: Any
    reprojection_px: Any
    reselected: Any
    lost: Any


class TrackedFrame(NamedTuple):
    """:meth:`RGBDTracker.step`'s result: the B poses and diagnostics (CPU tensors, as :class:`FramePose`'s) and the
    tracker's whole :class:`~torchtrack.pipeline.StepResult` (features, pixels, variances, loss check)."""

    T_world_color: Tensor  # (B, 4, 4) float64
    features: Tensor  # (B,) int64
    reprojection_px: Tensor  # (B,) float32
    reselected: Tensor  # (B,) bool
    lost: Tensor  # (B,) bool
    result: StepResult


def _intrinsics(K, name: str) -> Tensor:
    """(3, 3) or (B, 3, 3) float32 from a matrix or (fx, fy, cx, cy), with or without a leading B."""
    K = torch.as_tensor(np.asarray(K) if not isinstance(K, Tensor) else K, dtype=torch.float32).cpu()
    if K.shape[-1:] == (4,) and K.ndim in (1, 2):
        fx, fy, cx, cy = K.unbind(-1)
        zero, one = torch.zeros_like(fx), torch.ones_like(fx)
        K = torch.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1).reshape(*K.shape[:-1], 3, 3)
    if K.shape[-2:] != (3, 3) or K.ndim not in (2, 3):
        raise ValueError(
            f"{name}: need a (3, 3) matrix or (fx, fy, cx, cy), optionally with a leading B; got {tuple(K.shape)}"
        )
    if not (torch.isfinite(K).all() and (K[..., 0, 0] > 0).all() and (K[..., 1, 1] > 0).all()):
        raise ValueError(f"{name}: focal lengths must be finite and positive, got\n{K}")
    return K


def _per_stream(x: Tensor, b: int, name: str) -> Tensor:
    """(B, ...) from one value for every stream (...) or one per stream (B, ...)."""
    if x.ndim == 3:
        if x.shape[0] != b:
            raise ValueError(f"{name}: {x.shape[0]} given for {b} streams")
        return x
    return x.expand(b, *x.shape).contiguous()


class RGBDTracker:
    """The torchtrack pipeline on frames given one at a time as arrays (numpy or torch), for one stream or B streams
    in lockstep (every array with a leading B), built from the CLI's Hydra config.

    Built from the config, it applies the CLI's process settings, as the CLI does: ``torch.set_num_threads(threads)``
    (the config's ``threads``: 1 by default, the fastest for the per-frame tensors; ``overrides=["threads=N"]``;
    ``threads=null`` leaves torch's count) and glibc's allocator kept from returning freed memory to the system
    (:func:`torchtrack.runtime.configure`). Both are process-wide. :meth:`from_config` does the same with its config;
    given a built ``tracker``, the constructor changes neither.

    Args:
        K: colour intrinsics, a (3, 3) matrix or (fx, fy, cx, cy); (B, 3, 3) or (B, 4): one per stream. Only
            :meth:`step` works without (its frames carry their intrinsics).
        depth_scale: depth units per metre of integer depth (1000: millimetres; TUM: 5000). Float depth is metres.
        K_depth: the depth camera's intrinsics when depth is not registered to colour (default: ``K``).
        T_color_depth: (4, 4) or (B, 4, 4) depth-to-colour extrinsic (default: identity, registered depth).
        overrides: Hydra overrides of the CLI's config (conf/config.yaml), e.g. ``["weighting=fixed"]``, or
            ``["conf_dir=DIR", "weighting=mine"]`` for a config of your own; a bad one raises ValueError (one line).
        device: ``cpu``, ``cuda`` or ``cuda:N`` (None: the config's ``device``); each frame is moved there.
        fps: where :meth:`track` gets no timestamp, frame k is at k / fps seconds (the motion model's time step).
        tracker: an already built :class:`~torchtrack.pipeline.Tracker` (anything with ``step(FrameBatch)``) instead
            of one from the config (then ``overrides`` must be empty).
        announce: a first-run build of the compiled operators happens here, not in the first frame, and says so on
            one line of stderr (False: silently).
    """

    def __init__(
        self,
        K=None,
        *,
        depth_scale: float | None = None,
        K_depth=None,
        T_color_depth=None,
        overrides: Sequence[str] = (),
        device: str | torch.device | None = None,
        fps: float = 30.0,
        tracker=None,
        announce: bool = True,
    ) -> None:
        cfg = None
        if tracker is None:
            from torchtrack.cli import build_checked, compose_config

            cfg = compose_config("config", list(overrides))
            tracker = build_checked(cfg)
            configure(cfg.threads)
        elif overrides:
            raise ValueError("RGBDTracker: give overrides or a built tracker, not both")
        self.tracker = tracker
        self.device = resolve_device(device if device is not None else (cfg.device if cfg is not None else "cpu"))
        self.K = None if K is None else _intrinsics(K, "K")
        self.K_depth = None if K_depth is None else _intrinsics(K_depth, "K_depth")
        self.T_color_depth = (
            None if T_color_depth is None else torch.as_tensor(np.asarray(T_color_depth), dtype=torch.float32)
        )
        if self.T_color_depth is not None and self.T_color_depth.shape[-2:] != (4, 4):
            raise ValueError(f"T_color_depth: need (4, 4) or (B, 4, 4), got {tuple(self.T_color_depth.shape)}")
        if depth_scale is not None and not depth_scale > 0:
            raise ValueError(f"depth_scale: depth units per metre must be positive, got {depth_scale}")
        self.depth_scale, self.fps = depth_scale, float(fps)
        from torchtrack.factory import warm_up

        warm_up(self.device, announce=announce)  # built before any frame is timed
        self.reset()

    @classmethod
    def from_config(cls, cfg: DictConfig, **kwargs) -> RGBDTracker:
        """The tracker of an already composed config (the CLI's), on its ``device`` unless ``device`` is given, with
        its ``threads`` applied as the constructor applies them."""
        from torchtrack.factory import build_tracker

        kwargs.setdefault("device", cfg.get("device", "cpu"))
        configure(cfg.get("threads"))
        return cls(tracker=build_tracker(cfg), **kwargs)

    def reset(self) -> None:
        """Forget the streams: the next frame is a first frame (new streams, any number of them)."""
        if hasattr(self.tracker, "reset"):
            self.tracker.reset()
        self._T_world_tracker: Tensor | None = None
        self._frames, self._shape = 0, None

    def track(self, color, depth, *, timestamp=None) -> FramePose:
        """Track one frame of each stream.

        Args:
            color: (H, W, 3) or (B, H, W, 3) RGB, uint8 (or uint16), or float in [0, 1]; numpy or torch.
            depth: (H, W) or (B, H, W) in the depth camera, 0 = no measurement: integer in ``depth_scale`` units per
                metre, or float metres (NaN and inf read as no measurement).
            timestamp: seconds, one for all streams or (B,); None: frame count / ``fps``.

        Returns:
            :class:`FramePose`, numpy or torch as ``color``, with a leading B where ``color`` has one.
        """
        if self.K is None:
            raise ValueError("RGBDTracker.track: no intrinsics: give K when creating the tracker")
        batched = _ndim(color) == 4
        frame = self._frame(color, depth, timestamp, batched)
        out = self.step(frame)
        as_numpy = not isinstance(color, Tensor)
        values = [out.T_world_color, out.features, out.reprojection_px, out.reselected, out.lost]
        if as_numpy:
            values = [v.numpy() for v in values]
        else:
            values = [v.to(color.device) for v in values]
        if not batched:
            values = [values[0][0], *(v[0].item() for v in values[1:])]
        return FramePose(*values)

    def step(self, frame: FrameBatch) -> TrackedFrame:
        """Track one :class:`~torchtrack.data.frame.FrameBatch` (moved to the device; its ground truth is not read):
        :meth:`track`'s path from arrays to poses. The world is the first frame's colour camera."""
        frame = frame.to(self.device)
        res = self.tracker.step(frame)
        if self._T_world_tracker is None:  # the tracker's world is its first depth camera
            eye = torch.eye(4, dtype=torch.float64, device=frame.T_color_depth.device)
            self._T_world_tracker = T_world_depth_from_color(eye, frame.T_color_depth)
        T_world_color = color_poses(self._T_world_tracker, res.T_world_depth, frame.T_color_depth).cpu()
        loss = getattr(res, "loss", None)
        lost = loss.lost.cpu() if loss is not None else torch.zeros(len(T_world_color), dtype=torch.bool, device="cpu")
        return TrackedFrame(
            T_world_color, res.n_features.cpu().long(), res.reprojection_error.cpu(), res.reselected.cpu(), lost, res
        )

    def _frame(self, color, depth, timestamp, batched: bool) -> FrameBatch:
        """The arrays of one frame as a FrameBatch (B, ...) on the CPU, checked."""
        rgb = _color(color if batched else _unsqueeze(color))
        d = _depth(depth if batched else _unsqueeze(depth), self.depth_scale)
        b, _, h, w = rgb.shape
        if d.shape != (b, 1, h, w):
            raise ValueError(
                f"depth {tuple(d.shape[2:])} x {d.shape[0]} does not match colour {(h, w)} x {b}: register or resize "
                "depth to the colour image (and give K_depth for its pixel grid)"
            )
        if self._shape is not None and self._shape != (b, h, w):
            raise ValueError(f"frames of {b} stream(s) of {(h, w)} after {self._shape[0]} of {self._shape[1:]}: "
                             "call reset() to start new streams")  # fmt: skip
        self._shape = (b, h, w)
        K = _per_stream(self.K, b, "K")
        if timestamp is None:
            timestamp = self._frames / self.fps
        t = torch.as_tensor(timestamp, dtype=torch.float64).cpu().expand(b).clone()
        self._frames += 1
        dev = rgb.device  # the frame as given; step moves it to the tracker's device
        T_cd = self.T_color_depth if self.T_color_depth is not None else torch.eye(4, device=dev)
        return FrameBatch(  # no ground truth: identity, not valid
            rgb=rgb,
            depth=d,
            K=K,
            K_depth=_per_stream(self.K_depth, b, "K_depth") if self.K_depth is not None else K.clone(),
            T_color_depth=_per_stream(T_cd, b, "T_color_depth").float(),
            timestamp=t,
            T_world_color_gt=torch.eye(4, dtype=torch.float64, device=dev).repeat(b, 1, 1),
            gt_valid=torch.zeros(b, dtype=torch.bool, device=dev),
            active=torch.ones(b, dtype=torch.bool, device=dev),
            index=torch.full((b,), self._frames - 1, dtype=torch.int64, device=dev),
        )


def tum_frames(sequence: TumSequence | str | os.PathLike, **options) -> Iterator[tuple[Tensor, Tensor, float]]:
    """The frames of a TUM-layout folder for :meth:`RGBDTracker.track`, read and paired as the CLI reads them.

        seq = TumSequence("DIR")  # the CLI's reader: colour and depth paired by timestamp within max_dt
        tracker = RGBDTracker(seq.K, K_depth=seq.K_depth, T_color_depth=seq.T_color_depth)
        for color, depth, timestamp in tum_frames(seq):
            out = tracker.track(color, depth, timestamp=timestamp)

    Args:
        sequence: a :class:`~torchtrack.data.tum.TumSequence`, or its folder (then read with ``options``, the
            reader's keywords: ``max_dt``, ``depth_scale``, ``camera``, ... as the CLI's ``data.*`` keys).

    Yields:
        (colour (H, W, 3) float32 RGB in [0, 1], depth (H, W) float32 metres in the depth camera (0: none), colour
        timestamp in seconds) per frame, in order. A frame that fails to load is dropped with a warning, as the CLI
        drops it (:class:`~torchtrack.data.batching.FrameCursor`); the next frame is decoded in a thread while the
        caller tracks this one.
    """
    seq = sequence if isinstance(sequence, TumSequence) else TumSequence(sequence, **options)
    cursor = FrameCursor(seq)
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="tum_frames") as pool:
        ahead = pool.submit(cursor.read)
        while (frame := ahead.result()) is not None:
            ahead = pool.submit(cursor.read)
            yield frame.rgb.permute(1, 2, 0), frame.depth[0], frame.timestamp


def _ndim(x) -> int:
    return x.ndim if hasattr(x, "ndim") else np.asarray(x).ndim


def _unsqueeze(x):
    return x[None] if isinstance(x, Tensor | np.ndarray) else np.asarray(x)[None]


def _as_float(x) -> tuple[Tensor, float | None]:
    """(float32 tensor, the integer type's largest value, or None for float input) of a numpy array or tensor."""
    if isinstance(x, Tensor):
        top = None if x.is_floating_point() else float(torch.iinfo(x.dtype).max) if x.dtype != torch.bool else None
        if x.dtype == torch.bool:
            raise ValueError("need numbers, got a bool array")
        return x.float(), top
    a = np.asarray(x)
    if a.dtype.kind not in "uif":
        raise ValueError(f"need numbers, got a {a.dtype} array")
    top = float(np.iinfo(a.dtype).max) if a.dtype.kind in "ui" else None
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)), top


def _color(color) -> Tensor:
    """(B, H, W, 3) integer or [0, 1] float RGB -> (B, 3, H, W) float32 in [0, 1] (the TUM reader's arithmetic)."""
    c, top = _as_float(color)
    if c.ndim != 4 or c.shape[-1] != 3:
        raise ValueError(f"color: need (H, W, 3) or (B, H, W, 3) RGB, got {tuple(c.shape)}")
    c = c.permute(0, 3, 1, 2)
    if top is not None:
        if top not in (255.0, 65535.0):
            raise ValueError(f"color: integer colour must be uint8 or uint16, got one with maximum {top:g}")
        return c.div(top)
    if c.numel() and not (c.min() >= 0 and c.max() <= 1):
        raise ValueError(f"color: float colour must be in [0, 1], got [{float(c.min()):g}, {float(c.max()):g}] "
                         "(divide by 255, or pass uint8)")  # fmt: skip
    return c


def _depth(depth, depth_scale: float | None) -> Tensor:
    """(B, H, W) integer (``depth_scale`` units per metre) or float (metres) depth -> (B, 1, H, W) float32 metres."""
    d, top = _as_float(depth)
    if d.ndim == 4 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 3:
        raise ValueError(f"depth: need (H, W) or (B, H, W), got {tuple(d.shape)}")
    if top is None:
        d = torch.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0)
    elif depth_scale is None:
        raise ValueError("depth: integer depth needs depth_scale (units per metre, e.g. 1000 for millimetres)")
    else:
        d = d.div(depth_scale)
    if d.numel() and d.min() < 0:
        raise ValueError(f"depth: negative depth ({float(d.min()):g} m); 0 means no measurement")
    return d[:, None].contiguous()
