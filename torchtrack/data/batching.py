"""Lockstep iteration over B RGB-D sequences -> FrameBatch, with background decoding of the next step."""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Protocol

import torch
from torch import Tensor

from torchtrack.data.errors import DataError
from torchtrack.data.frame import FrameBatch
from torchtrack.data.tum import RGBDFrame


class RGBDSequence(Protocol):
    """What iterate_batched needs from a sequence (TumSequence, or any in-memory sequence)."""

    name: str
    K: Tensor  # (3, 3)
    K_depth: Tensor  # (3, 3)
    T_color_depth: Tensor  # (4, 4)

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> RGBDFrame: ...


def _batch(images: Sequence[Tensor]) -> Tensor:
    """Stack images along a new batch dimension; one image becomes a view (no copy of a whole frame)."""
    return images[0].unsqueeze(0) if len(images) == 1 else torch.stack(list(images))


def _stack(frames: Sequence[RGBDFrame], seqs: Sequence[RGBDSequence], active: list[bool]) -> FrameBatch:
    """B frames (one per sequence) -> FrameBatch; checks that all share H, W."""
    sizes = {tuple(f.rgb.shape[1:]) for f in frames} | {tuple(f.depth.shape[1:]) for f in frames}
    if len(sizes) > 1:
        got = ", ".join(f"{s.name}: {tuple(f.rgb.shape[1:])}" for s, f in zip(seqs, frames, strict=True))
        raise DataError(f"sequences batched together must share the image size (H, W); got {got}")
    return FrameBatch(
        rgb=_batch([f.rgb for f in frames]),
        depth=_batch([f.depth for f in frames]),
        K=torch.stack([s.K for s in seqs]).float(),
        K_depth=torch.stack([s.K_depth for s in seqs]).float(),
        T_color_depth=torch.stack([s.T_color_depth for s in seqs]).float(),
        timestamp=torch.tensor([f.timestamp for f in frames], dtype=torch.float64),
        T_world_cam_gt=torch.stack([f.T_world_cam_gt for f in frames]).double(),
        gt_valid=torch.tensor([f.gt_valid for f in frames], dtype=torch.bool),
        active=torch.tensor(active, dtype=torch.bool),
        index=torch.tensor([f.index for f in frames], dtype=torch.int64),
    )


def iterate_batched(
    sequences: Sequence[RGBDSequence], *, prefetch: bool = True, num_workers: int | None = None
) -> Iterator[FrameBatch]:
    """Yield one FrameBatch per step t = 0 .. max length - 1, the B sequences in lockstep.

    A sequence that has ended is inactive (``active`` False) and repeats its last frame (not reloaded). With
    ``prefetch`` a thread pool (``num_workers``, default min(B, cpu count)) decodes step t + 1 while the caller
    works on step t; OpenCV's decoders release the GIL, so decoding overlaps compute. Errors raised while
    loading surface at the step that needs the frame.
    """
    if len(sequences) == 0:
        raise ValueError("iterate_batched: need at least one sequence")
    for s in sequences:
        if len(s) == 0:
            raise DataError(f"{s.name}: sequence has no frames")
    T = max(len(s) for s in sequences)
    if not prefetch:
        last: list[RGBDFrame | None] = [None] * len(sequences)
        for t in range(T):
            last = [s[t] if t < len(s) else f for s, f in zip(sequences, last, strict=True)]
            yield _stack(last, sequences, [t < len(s) for s in sequences])
        return
    workers = num_workers or min(len(sequences), os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="torchtrack-load") as pool:

        def submit(t: int) -> list[Future | None]:
            return [pool.submit(s.__getitem__, t) if t < len(s) else None for s in sequences]

        pending = submit(0)
        last = [None] * len(sequences)
        try:
            for t in range(T):
                done = [f.result() if f is not None else None for f in pending]
                last = [d if d is not None else f for d, f in zip(done, last, strict=True)]
                if t + 1 < T:
                    pending = submit(t + 1)  # decode the next step while the caller consumes this one
                yield _stack(last, sequences, [t < len(s) for s in sequences])
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
