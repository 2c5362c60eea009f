"""A streaming voxel-grid point map, batched over B sequences: one coloured point per occupied voxel.

Every voxel keeps the sums of the positions and colours of the points that fell in it and their count; the map's
point is the mean (position and colour). Memory is bounded by the occupied volume, not by the number of frames.

Voxels are keyed by one int64 per (sequence, voxel): ``b << 54 | (ix + 2^17) << 36 | (iy + 2^17) << 18 | (iz + 2^17)``
with ``i = floor(p / voxel_size)`` per axis, so one sorted key array serves all B maps (each map is a contiguous run
of it) and points outside +-2^17 voxels of the world origin (+-1.3 km at 1 cm) are dropped and counted.

The index is a few sorted runs of keys (a log-structured merge: a new frame's new voxels form a run; runs of
similar size are merged, so there are O(log M) runs and a key is re-sorted O(log M) times over the map's life):
a frame of K voxels costs O(K log^2 M) amortised, never O(M). The per-voxel sums (x, y, z, r, g, b, count:
7 float64) live in one append-only buffer that grows by doubling; a run holds each key's row in it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

AXIS_BITS = 18
BATCH_BITS = 63 - 3 * AXIS_BITS  # 9: up to 512 sequences
HALF = 1 << (AXIS_BITS - 1)
MAX_BATCH = 1 << BATCH_BITS


class MapPoints(NamedTuple):
    """One sequence's map: xyz (M, 3) float64 world metres, rgb (M, 3) float32 in [0, 1], count (M,) int64 points
    averaged per voxel; sorted by voxel key."""

    xyz: Tensor
    rgb: Tensor
    count: Tensor


def voxel_keys(points: Tensor, batch: Tensor, voxel_size: float) -> tuple[Tensor, Tensor]:
    """Keys (P,) int64 of points (P, 3) float64 world metres in sequences ``batch`` (P,) int64; inside (P,) bool
    where the voxel is representable (keys of the others are meaningless)."""
    ijk = torch.floor(points / voxel_size).long() + HALF  # 0 .. 2^18 - 1 inside
    inside = ((ijk >= 0) & (ijk < 2 * HALF)).all(-1)  # the keys of the others mix bits: dropped by the caller
    keys = (batch << (3 * AXIS_BITS)) | (ijk[:, 0] << (2 * AXIS_BITS)) | (ijk[:, 1] << AXIS_BITS) | ijk[:, 2]
    return keys, inside


def spatial_hash(keys: Tensor) -> Tensor:
    """(P,) int64 >= 0: a hash of the voxels of ``keys`` (P,) that mixes the three axes (Teschner et al.'s primes), so
    that ``spatial_hash(keys) % k == 0`` picks about one voxel in k with no pattern along an axis; it depends on the
    voxel only, not on the order or the company the keys come in."""
    mask = (1 << AXIS_BITS) - 1
    ix, iy, iz = (keys >> (2 * AXIS_BITS)) & mask, (keys >> AXIS_BITS) & mask, keys & mask
    return (ix * 73856093) ^ (iy * 19349663) ^ (iz * 83492791)


class VoxelPointMap:
    """B voxel-grid point maps fused point by point.

    Args:
        voxel_size: edge of a voxel, metres.
        batch_size: B, the number of maps (<= 512).
        device: where the sums and the index live; the points added must be on it (the tracker's frames' device).
    """

    def __init__(self, *, voxel_size: float = 0.01, batch_size: int = 1, device: torch.device | str = "cpu") -> None:
        if voxel_size <= 0:
            raise ValueError(f"VoxelPointMap: voxel_size must be > 0, got {voxel_size}")
        if not 1 <= batch_size <= MAX_BATCH:
            raise ValueError(f"VoxelPointMap: batch_size must be in [1, {MAX_BATCH}], got {batch_size}")
        self.voxel_size = float(voxel_size)
        self.batch_size = batch_size
        self.dropped = 0  # points outside the representable range
        self._runs: list[tuple[Tensor, Tensor]] = []  # (keys ascending, their rows), largest first; disjoint
        self._n = 0  # rows used in the buffer
        self._sums = torch.empty(0, 7, dtype=torch.float64, device=device)  # by row: sum of x, y, z, r, g, b; count

    def __len__(self) -> int:
        """Occupied voxels over all B maps."""
        return sum(len(k) for k, _ in self._runs)

    @property
    def device(self) -> torch.device:
        """Where the map lives."""
        return self._sums.device

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's buffers (capacity, not only the rows in use)."""
        return self._sums.numel() * 8 + sum(k.numel() * 16 for k, _ in self._runs)

    def add(self, points: Tensor, rgb: Tensor, batch: Tensor) -> tuple[Tensor, Tensor]:
        """Fuse points (P, 3) float64 world metres with colours rgb (P, 3) into the maps of ``batch`` (P,) int64.
        Returns the voxels this created: their keys (K,) ascending and buffer rows (K,) (a key's sequence:
        ``key >> 54``)."""
        if points.dim() != 2 or points.shape[-1] != 3 or rgb.shape != points.shape or batch.shape != points.shape[:1]:
            raise ValueError(
                f"VoxelPointMap.add: need points (P, 3), rgb (P, 3), batch (P,); got {tuple(points.shape)}, "
                f"{tuple(rgb.shape)}, {tuple(batch.shape)}"
            )
        if not points.device == rgb.device == batch.device == self.device:
            raise ValueError(
                f"VoxelPointMap.add: points, rgb and batch must be on the map's device {self.device}; got "
                f"{points.device}, {rgb.device}, {batch.device}"
            )
        if len(batch) and (int(batch.min()) < 0 or int(batch.max()) >= self.batch_size):
            raise ValueError(
                f"VoxelPointMap.add: batch indices must be in [0, {self.batch_size}), got {batch.unique()}"
            )
        keys, inside = voxel_keys(points.double(), batch.long(), self.voxel_size)
        if not bool(inside.all()):
            self.dropped += int((~inside).sum())
            keys, points, rgb = keys[inside], points[inside], rgb[inside]
        if len(keys) == 0:
            return keys, keys.clone()
        uk, inv = torch.unique(keys, sorted=True, return_inverse=True)
        ones = torch.ones(len(keys), 1, dtype=torch.float64, device=keys.device)
        values = torch.cat([points.double(), rgb.double(), ones], 1)
        sums = torch.zeros(len(uk), 7, dtype=torch.float64, device=uk.device).index_add_(0, inv, values)
        new = torch.ones(len(uk), dtype=torch.bool, device=uk.device)
        for run_keys, run_rows in self._runs:
            pos = torch.searchsorted(run_keys, uk).clamp_(max=len(run_keys) - 1)
            hit = run_keys[pos] == uk
            self._sums.index_add_(0, run_rows[pos[hit]], sums[hit])
            new &= ~hit
        return self._append(uk[new], sums[new])

    def _append(self, keys: Tensor, sums: Tensor) -> tuple[Tensor, Tensor]:
        """New voxels: rows for their sums, a run for their sorted keys; merge runs of similar size. Returns the keys
        and their rows."""
        k = len(keys)
        if k == 0:
            return keys, keys.clone()
        rows = torch.arange(self._n, self._n + k, device=keys.device)
        self._reserve(self._n + k)
        self._sums[self._n : self._n + k] = sums
        self._runs.append((keys, rows))
        self._n += k
        while len(self._runs) > 1 and len(self._runs[-2][0]) <= 2 * len(self._runs[-1][0]):
            (ka, ra), (kb, rb) = self._runs.pop(), self._runs.pop()
            merged, order = torch.sort(torch.cat([kb, ka]))
            self._runs.append((merged, torch.cat([rb, ra])[order]))
        return keys, rows

    def _reserve(self, rows: int) -> None:
        cap = len(self._sums)
        if rows <= cap:
            return
        # rows past _n are never read
        new = torch.empty(max(rows, 2 * cap, 1024), 7, dtype=torch.float64, device=self.device)
        new[: self._n] = self._sums[: self._n]
        self._sums = new

    def _bounds(self, b: int) -> Tensor:
        """(2,) int64: sequence b's keys are in [lo, hi)."""
        lo, hi = b << (3 * AXIS_BITS), (b + 1) << (3 * AXIS_BITS) if b + 1 < MAX_BATCH else torch.iinfo(torch.int64).max
        return torch.tensor([lo, hi], dtype=torch.int64, device=self.device)

    def _rows(self, b: int, ordered: bool = True, every: int = 1) -> Tensor:
        """(M_b,) buffer rows of sequence b's voxels, in key order (``ordered``; else run by run); ``every`` > 1: only
        the voxels whose :func:`spatial_hash` is a multiple of it."""
        return self.voxels(b, ordered, every)[1]

    def voxels(self, b: int, ordered: bool = True, every: int = 1) -> tuple[Tensor, Tensor]:
        """Sequence b's voxels: keys (M_b,) and buffer rows (M_b,), in key order (``ordered``; else run by run);
        ``every`` > 1: only those whose :func:`spatial_hash` is a multiple of it."""
        bounds = self._bounds(b)
        keys, rows = [], []
        for run_keys, run_rows in self._runs:
            i, j = torch.searchsorted(run_keys, bounds).tolist()
            keys.append(run_keys[i:j])
            rows.append(run_rows[i:j])
        if not keys:
            empty = torch.empty(0, dtype=torch.int64, device=self.device)
            return empty, empty.clone()
        keys, rows = torch.cat(keys), torch.cat(rows)
        if every > 1:
            pick = spatial_hash(keys) % every == 0
            keys, rows = keys[pick], rows[pick]
        if not ordered:
            return keys, rows
        keys, order = torch.sort(keys)
        return keys, rows[order]

    def points(self, b: int = 0, ordered: bool = True, every: int = 1) -> MapPoints:
        """Sequence b's map: one point per voxel, the mean position and colour of its points; sorted by voxel key
        (``ordered``; else in an order that saves the sort). ``every`` > 1: about one voxel in ``every``, the same ones
        whatever the other sequences in the map and the order they were added in (:func:`spatial_hash`)."""
        sums = self._sums[self._rows(b, ordered, every)]
        n = sums[:, 6:]
        return MapPoints(sums[:, :3] / n, (sums[:, 3:6] / n).float(), n[:, 0].long())

    def xyz(self, rows: Tensor) -> Tensor:
        """The mean positions (M, 3) of the voxels at buffer ``rows`` (M,) (:meth:`voxels`): ``points().xyz`` of
        those voxels, without the colours."""
        sums = self._sums[rows]
        return sums[:, :3] / sums[:, 6:]

    def size(self, b: int) -> int:
        """Occupied voxels of sequence b."""
        bounds = self._bounds(b)
        return sum(int(torch.diff(torch.searchsorted(run_keys, bounds))) for run_keys, _ in self._runs)

    def clear(self, b: int) -> None:
        """Forget sequence b's map and compact the buffer (a finished sequence's memory is released)."""
        drop = torch.zeros(self._n, dtype=torch.bool, device=self.device)
        drop[self._rows(b)] = True
        if not bool(drop.any()):
            return
        new_row = torch.cumsum(~drop, 0) - 1  # old row -> compacted row (where kept)
        self._sums = self._sums[: self._n][~drop]
        self._n = len(self._sums)
        runs = []
        for run_keys, run_rows in self._runs:
            keep = ~drop[run_rows]
            if bool(keep.any()):
                runs.append((run_keys[keep], new_row[run_rows[keep]]))
        self._runs = sorted(runs, key=lambda r: -len(r[0]))
