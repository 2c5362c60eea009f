"""Per-frame preparation shared by every tracker, computed once per frame.

Depth is registered to the colour camera first (z-buffered forward warp with the depth-to-colour
extrinsic; a no-op for registered depth), so that intensity, depth and the Shape Index Map share one
pixel grid: a feature tracked at colour pixel x reads its depth and its SIM at x.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from torchtrack.geometry import warp_depth
from torchtrack.image.flow import FlowFrame, prepare_frame
from torchtrack.image.shape_index import SIM, compute_sim


@dataclass
class PreparedFrame:
    """Attributes: gray (B,1,H,W); depth (B,1,H,W) in the colour grid; sim (SI, mask, LK image) or None; flow."""

    gray: Tensor
    depth: Tensor
    sim: SIM | None
    flow: FlowFrame


class FrameLike(Protocol):
    """What the front end reads of a frame batch (:class:`torchtrack.data.frame.FrameBatch` has it): rgb (B, 3, H, W)
    in [0, 1], depth (B, 1, H, W) metres in the depth camera's grid, K and K_depth (B, 3, 3), T_color_depth (B, 4, 4)
    and gray (B, 1, H, W) luminance. A protocol, so that the kernels do not import the data layer."""

    rgb: Tensor
    depth: Tensor
    K: Tensor
    K_depth: Tensor
    T_color_depth: Tensor

    @property
    def gray(self) -> Tensor: ...


def _gray(frame: FrameLike) -> Tensor:
    return frame.gray


def is_registered(frame: FrameLike) -> bool:
    eye = torch.eye(4, dtype=frame.T_color_depth.dtype, device=frame.T_color_depth.device)
    return bool(torch.allclose(frame.T_color_depth, eye) and torch.allclose(frame.K_depth, frame.K))


def depth_in_colour(frame: FrameLike) -> Tensor:
    """Depth (B, 1, H, W) seen from the colour camera; the input itself when depth is registered."""
    if is_registered(frame):
        return frame.depth
    H, W = frame.rgb.shape[-2:]
    return warp_depth(frame.depth, frame.K_depth, frame.K, frame.T_color_depth, (H, W))


class FrontEnd:
    """Builds a :class:`PreparedFrame`: gray, colour-registered depth, SIM (eq. 8) and LK pyramids.

    The preparation depends on the frame only, not on the tracking state, so :meth:`prepared_ahead` can run it in a
    thread of its own a step ahead of the tracker (torch releases the GIL inside its operators): at B=1 the SIM and
    the pyramids then use the second core beside the decoder threads instead of the tracker's.

    Args:
        levels: pyramid levels of the LK tracker.
        use_sim: compute the SIM (needed by SIM-assisted tracking and lambda < 1 selection).
        sim_kwargs: keyword arguments of :func:`torchtrack.image.shape_index`.
        ahead: :meth:`prepared_ahead` prepares frames in its thread (False: it passes the frames through, and each
            is prepared when the tracker asks for it; the same results).
        gray: the frame's (B, 1, H, W) intensity (default ``frame.gray``); the application passes
            :func:`torchtrack.data.batching.frame_gray`, which returns the copy its loader threads computed beside
            decoding (the same numbers, ~1 ms per 640x480 frame off this thread).
    """

    def __init__(
        self,
        *,
        levels: int = 3,
        use_sim: bool = True,
        sim_kwargs: dict | None = None,
        ahead: bool = True,
        gray: Callable[[FrameLike], Tensor] = _gray,
    ) -> None:
        self.levels = levels
        self.use_sim = use_sim
        self.sim_kwargs = dict(sim_kwargs or {})
        self.ahead = ahead
        self.gray = gray
        self._ready: dict[int, tuple[FrameLike, PreparedFrame | BaseException]] = {}  # by id(frame)

    def __call__(self, frame: FrameLike) -> PreparedFrame:
        """The frame prepared: by :meth:`prepared_ahead`'s thread when it yielded this frame, else now."""
        ready = self._ready.pop(id(frame), None)
        if ready is None or ready[0] is not frame:
            return self.prepare(frame)
        if isinstance(ready[1], BaseException):  # it fails here, at this frame's step, as without the thread
            raise ready[1]
        return ready[1]

    def prepare(self, frame: FrameLike) -> PreparedFrame:
        """Prepare ``frame`` now, in the calling thread."""
        gray = self.gray(frame)
        depth = depth_in_colour(frame)
        sim = compute_sim(depth, frame.K, **self.sim_kwargs) if self.use_sim else None  # eq. (8)
        flow = prepare_frame(gray, sim.image if sim is not None else None, self.levels)
        return PreparedFrame(gray, depth, sim, flow)

    def prepared_ahead(self, frames: Iterable[FrameLike], depth: int = 1) -> Iterator[FrameLike]:
        """Yield ``frames`` in order while a thread takes them from ``frames`` and prepares them, at most ``depth``
        frames beyond the one being prepared; calling this front end on a yielded frame returns its preparation.

        An error raised by ``frames`` is raised here, after the frames before it; one raised by a preparation is
        raised when the front end is called on that frame. The thread runs in the caller's inference mode.
        """
        if not self.ahead:
            yield from frames
            return
        out: queue.Queue = queue.Queue(maxsize=depth)
        stop = threading.Event()
        mode = torch.is_inference_mode_enabled()

        def put(item) -> bool:
            while not stop.is_set():
                try:
                    out.put(item, timeout=0.05)
                    return True
                except queue.Full:
                    continue
            return False

        def produce() -> None:
            with torch.inference_mode(mode):
                try:
                    for frame in frames:
                        try:
                            prepared = self.prepare(frame)
                        except Exception as e:  # noqa: BLE001 - handed to the step that needs this frame
                            prepared = e
                        if not put((frame, prepared)):
                            return
                    put((None, None))
                except BaseException as e:  # noqa: BLE001 - the caller's iteration raises it
                    put((None, e))
                finally:
                    close = getattr(frames, "close", None)  # a generator's clean-up runs in the thread that ran it
                    if close is not None:
                        close()

        worker = threading.Thread(target=produce, name="torchtrack-frontend", daemon=True)
        worker.start()
        try:
            while True:
                frame, prepared = out.get()
                if frame is None:
                    if prepared is not None:
                        raise prepared
                    return
                self._ready[id(frame)] = (frame, prepared)
                yield frame
        finally:
            stop.set()
            worker.join()
            self._ready.clear()


def smooth_depth_mask(depth: Tensor, max_rel_step: float = 0.03, radius: int = 2) -> Tensor:
    """(B, 1, H, W) bool: depth present in the whole (2r+1)^2 window and within ``max_rel_step`` of its range.

    Features on occlusion boundaries get the depth of the wrong surface: their model point then drifts
    away from the 2D track under parallax. This mask keeps the selection off such pixels.
    """
    hi = _window_max(depth, radius)
    neg_lo = _window_max(torch.where(depth > 0, -depth, float("inf")), radius)  # -min depth; inf: a hole in the window
    return hi + neg_lo <= max_rel_step * depth


def _window_max(x: Tensor, radius: int) -> Tensor:
    """Max of (..., H, W) over (2r+1)^2 windows clipped at the border (``max_pool2d(x, 2r+1, 1, r)``):
    separable, by shifted maxima (max_pool2d is ~10x slower on CPU for one channel)."""
    for dim in (-1, -2):
        n, y = x.shape[dim], x.clone()
        for s in range(1, min(radius, n - 1) + 1):
            torch.maximum(y.narrow(dim, s, n - s), x.narrow(dim, 0, n - s), out=y.narrow(dim, s, n - s))
            torch.maximum(y.narrow(dim, 0, n - s), x.narrow(dim, s, n - s), out=y.narrow(dim, 0, n - s))
        x = y
    return x
