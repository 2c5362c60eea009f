"""Lockstep iteration over B RGB-D sequences -> FrameBatch, with background decoding of the next step."""

from __future__ import annotations

import logging
import os
import weakref
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor

from torchtrack.data.errors import DataError
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import RGBDFrame

log = logging.getLogger(__name__)


class RGBDSequence(Protocol):
    """What iterate_batched needs from a sequence (TumSequence, or any in-memory sequence)."""

    name: str
    K: Tensor  # (3, 3)
    K_depth: Tensor  # (3, 3)
    T_color_depth: Tensor  # (4, 4)

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> RGBDFrame: ...


# id(FrameBatch.rgb) -> (a weak reference to that rgb, its (B, 1, H, W) luminance from the loader threads); an entry
# goes with its rgb (see frame_gray)
_GRAY: dict[int, tuple[weakref.ref, Tensor]] = {}


def frame_gray(frame: FrameBatch) -> Tensor:
    """``frame.gray`` (B, 1, H, W): the copy the loader threads computed beside decoding (the same numbers; the main
    thread is spared ~1 ms per 640x480 frame), else computed now."""
    ref, gray = _GRAY.get(id(frame.rgb), (None, None))
    return gray if ref is not None and ref() is frame.rgb else frame.gray


def _decoded(cursor: FrameCursor) -> tuple[RGBDFrame, Tensor] | None:
    """The cursor's next frame with its luminance (runs in a loader thread), or None."""
    f = cursor.read()
    return None if f is None else (f, rgb_to_grayscale(f.rgb))


def _batch(images: Sequence[Tensor]) -> Tensor:
    """Stack images along a new batch dimension; one image becomes a view (no copy of a whole frame)."""
    return images[0].unsqueeze(0) if len(images) == 1 else torch.stack(list(images))


def _stack(frames: Sequence[RGBDFrame], seqs: Sequence[RGBDSequence], active: list[bool]) -> FrameBatch:
    """B frames (one per sequence) -> FrameBatch; checks that all share H, W."""
    sizes = {tuple(f.rgb.shape[1:]) for f in frames} | {tuple(f.depth.shape[1:]) for f in frames}
    if len(sizes) > 1:
        got = ", ".join(f"{s.name}: {tuple(f.rgb.shape[1:])}" for s, f in zip(seqs, frames, strict=True))
        raise DataError(f"sequences batched together must share the image size (H, W); got {got}")
    dev = frames[0].rgb.device  # the per-frame scalars go where the images are
    return FrameBatch(
        rgb=_batch([f.rgb for f in frames]),
        depth=_batch([f.depth for f in frames]),
        K=torch.stack([s.K for s in seqs]).float(),
        K_depth=torch.stack([s.K_depth for s in seqs]).float(),
        T_color_depth=torch.stack([s.T_color_depth for s in seqs]).float(),
        timestamp=torch.tensor([f.timestamp for f in frames], dtype=torch.float64, device=dev),
        T_world_color_gt=torch.stack([f.T_world_color_gt for f in frames]).double(),
        gt_valid=torch.tensor([f.gt_valid for f in frames], dtype=torch.bool, device=dev),
        active=torch.tensor(active, dtype=torch.bool, device=dev),
        index=torch.tensor([f.index for f in frames], dtype=torch.int64, device=dev),
    )


@dataclass
class DroppedFrame:
    """A frame skipped because it could not be used: its index, timestamp (nan if unknown) and the reason."""

    index: int
    timestamp: float
    reason: str


class FrameCursor:
    """One sequence's usable frames in order: a frame whose loading raises :class:`DataError` (unreadable or corrupt
    image, wrong bit depth or size, too little depth) is dropped with one warning line, as a sensor drops a frame.

    The policy comes from the sequence (attributes of :class:`~torchtrack.data.tum.TumSequence`, with these
    defaults) unless given: ``on_bad_frame`` "drop" | "error" (the first bad frame fails the sequence),
    ``max_bad_fraction`` (more bad frames than this fraction of the sequence fail it). A failure raises, or with ``isolate`` is kept in
    ``failure`` (one line) and ends the cursor, so that the other sequences of a batch go on.
    """

    def __init__(self, sequence: RGBDSequence, *, isolate: bool = False, on_bad_frame: str | None = None) -> None:
        self.sequence, self.isolate = sequence, isolate
        self.on_bad_frame = on_bad_frame or getattr(sequence, "on_bad_frame", "drop")
        self.max_bad_fraction = float(getattr(sequence, "max_bad_fraction", 1.0))
        self.next, self.dropped, self.failure = 0, [], None

    @property
    def done(self) -> bool:
        return self.failure is not None or self.next >= len(self.sequence)

    def read(self) -> RGBDFrame | None:
        """The next usable frame, or None when the sequence has ended or failed (runs in the loader thread)."""
        try:
            return self._read()
        except Exception as e:
            if not self.isolate:
                raise
            self.failure = f"{type(e).__name__}: {e}" if not isinstance(e, DataError) else str(e)
            return None

    def _read(self) -> RGBDFrame | None:
        seq = self.sequence
        while self.failure is None and self.next < len(seq):
            i, self.next = self.next, self.next + 1
            try:
                return seq[i]
            except DataError as e:
                if self.on_bad_frame == "error":
                    raise
                t = float(seq.timestamps[i]) if hasattr(seq, "timestamps") else float("nan")
                self.dropped.append(DroppedFrame(i, t, str(e)))
                log.warning("%s: frame %d dropped: %s", seq.name, i, e)
                if len(self.dropped) > self.max_bad_fraction * len(seq):
                    raise DataError(
                        f"{seq.name}: {len(self.dropped)} bad frames, more than max_bad_fraction="
                        f"{self.max_bad_fraction:g} of its {len(seq)}; the last: {e}"
                    ) from None
        return None


def _placeholder(like: RGBDFrame) -> RGBDFrame:
    """A blank frame of ``like``'s size for a sequence that failed before its first usable frame (inactive)."""
    T = torch.eye(4, dtype=torch.float64, device=like.rgb.device)
    return RGBDFrame(torch.zeros_like(like.rgb), torch.zeros_like(like.depth), 0.0, T, False, -1)


def iterate_batched(
    sequences: Sequence[RGBDSequence],
    *,
    prefetch: bool = True,
    num_workers: int | None = None,
    cursors: Sequence[FrameCursor] | None = None,
) -> Iterator[FrameBatch]:
    """Yield one FrameBatch per step, the B sequences in lockstep, until every sequence has ended.

    Each step takes every sequence's next usable frame (:class:`FrameCursor`: bad frames are dropped, so a
    sequence's ``index`` can skip). A sequence that has ended (or failed) is inactive (``active`` False) and repeats
    its last frame (not reloaded). ``cursors`` (one per sequence) lets the caller see drops and failures; without
    them every frame is strict (``on_bad_frame="error"``: indices never skip) and a failure raises at the step
    that needs the frame. With ``prefetch`` a thread pool (``num_workers``, default
    min(B, cpu count)) decodes and validates step t + 1 while the caller works on step t; OpenCV's decoders release
    the GIL, so decoding overlaps compute.
    """
    if len(sequences) == 0:
        raise ValueError("iterate_batched: need at least one sequence")
    for s in sequences:
        if len(s) == 0:
            raise DataError(f"{s.name}: sequence has no frames")
    cursors = list(cursors) if cursors is not None else [FrameCursor(s, on_bad_frame="error") for s in sequences]
    last: list[tuple[RGBDFrame, Tensor] | None] = [None] * len(sequences)  # (frame, luminance) per sequence

    def batch(got: list[tuple[RGBDFrame, Tensor] | None]) -> FrameBatch | None:
        active = [g is not None for g in got]
        if not any(active):
            return None
        last[:] = [g if g is not None else f for g, f in zip(got, last, strict=True)]
        like = next(f for f, _ in (x for x in last if x is not None))
        blank = (_placeholder(like), torch.zeros_like(like.rgb[:1]))
        frames, grays = zip(*(x if x is not None else blank for x in last), strict=True)
        out = _stack(frames, sequences, active)
        key = id(out.rgb)
        _GRAY[key] = (weakref.ref(out.rgb, lambda _, key=key: _GRAY.pop(key, None)), _batch(grays))
        return out

    if not prefetch:
        while (b := batch([_decoded(c) if not c.done else None for c in cursors])) is not None:
            yield b
        return
    workers = num_workers or min(len(sequences), os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="torchtrack-load") as pool:

        def submit() -> list[Future | None]:
            return [pool.submit(_decoded, c) if not c.done else None for c in cursors]

        pending = submit()
        try:
            while True:
                b = batch([f.result() if f is not None else None for f in pending])
                if b is None:
                    return
                pending = submit()  # decode the next step while the caller consumes this one
                yield b
        finally:
            for f in pending:
                if f is not None:
                    f.cancel()


class SequenceBatch:
    """B sequences tracked together: names, lengths, and lockstep iteration over FrameBatches."""

    def __init__(self, sequences: Sequence[RGBDSequence], *, prefetch: bool = True) -> None:
        if len(sequences) == 0:
            raise ValueError("SequenceBatch: need at least one sequence")
        self.sequences = list(sequences)
        self.prefetch = prefetch

    @property
    def names(self) -> list[str]:
        return [s.name for s in self.sequences]

    @property
    def lengths(self) -> list[int]:
        return [len(s) for s in self.sequences]

    def __len__(self) -> int:
        """Number of lockstep steps (the longest sequence)."""
        return max(self.lengths)

    def __iter__(self) -> Iterator[FrameBatch]:
        return iterate_batched(self.sequences, prefetch=self.prefetch)
