"""A streaming voxel-grid point map, batched over B sequences: one coloured point per occupied voxel.

Every voxel keeps the sums of the positions and colours of the points that fell in it and their count; the map's
point is the mean (position and colour). Memory is bounded by the occupied volume, not by the number of frames.

Voxels are keyed by one int64 per (sequence, voxel): ``b << 54 | (ix + 2^17) << 36 | (iy + 2^17) << 18 | (iz + 2^17)``
with ``i = floor(p / voxel_size)`` per axis, so one sorted key array serves all B maps (each map is a contiguous run
of it) and points outside +-2^17 voxels of the world origin (+-1.3 km at 1 cm) are dropped and counted. Insertion
merges the new sorted keys into the old ones in O(M + K log M) (no re-sort of the map); the per-voxel sums
(x, y, z, r, g, b, count: 7 float64) live in one append-only buffer that grows by doubling.
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
    idx = torch.floor(points / voxel_size)
    inside = ((idx >= -HALF) & (idx < HALF)).all(-1)
    ijk = (idx.clamp(-HALF, HALF - 1) + HALF).long()  # 0 .. 2^18 - 1
    keys = (batch << (3 * AXIS_BITS)) | (ijk[:, 0] << (2 * AXIS_BITS)) | (ijk[:, 1] << AXIS_BITS) | ijk[:, 2]
    return keys, inside


class VoxelPointMap:
    """B voxel-grid point maps fused point by point.

    Args:
        voxel_size: edge of a voxel, metres.
        batch_size: B, the number of maps (<= 512).
    """

    def __init__(self, *, voxel_size: float = 0.01, batch_size: int = 1) -> None:
        if voxel_size <= 0:
            raise ValueError(f"VoxelPointMap: voxel_size must be > 0, got {voxel_size}")
        if not 1 <= batch_size <= MAX_BATCH:
            raise ValueError(f"VoxelPointMap: batch_size must be in [1, {MAX_BATCH}], got {batch_size}")
        self.voxel_size = float(voxel_size)
        self.batch_size = batch_size
        self.dropped = 0  # points outside the representable range
        self._sorted = torch.empty(0, dtype=torch.int64)  # (M,) keys, ascending
        self._slot = torch.empty(0, dtype=torch.int64)  # (M,) buffer row of each sorted key
        self._n = 0  # rows used in the buffer
        self._sums = torch.empty(0, 7, dtype=torch.float64)  # by row: sum of x, y, z, r, g, b; count

    def __len__(self) -> int:
        """Occupied voxels over all B maps."""
        return len(self._sorted)

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's buffers (capacity, not only the rows in use)."""
        return sum(t.numel() * t.element_size() for t in (self._sorted, self._slot, self._sums))

    def add(self, points: Tensor, rgb: Tensor, batch: Tensor) -> None:
        """Fuse points (P, 3) float64 world metres with colours rgb (P, 3) into the maps of ``batch`` (P,) int64."""
        if points.dim() != 2 or points.shape[-1] != 3 or rgb.shape != points.shape or batch.shape != points.shape[:1]:
            raise ValueError(
                f"VoxelPointMap.add: need points (P, 3), rgb (P, 3), batch (P,); got {tuple(points.shape)}, "
                f"{tuple(rgb.shape)}, {tuple(batch.shape)}"
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
            return
        uk, inv = torch.unique(keys, sorted=True, return_inverse=True)
        values = torch.cat([points.double(), rgb.double(), torch.ones(len(keys), 1, dtype=torch.float64)], 1)
        sums = torch.zeros(len(uk), 7, dtype=torch.float64).index_add_(0, inv, values)
        pos = torch.searchsorted(self._sorted, uk)
        found = pos < len(self._sorted)
        found[found.clone()] = self._sorted[pos[found]] == uk[found]
        self._sums.index_add_(0, self._slot[pos[found]], sums[found])
        new = ~found
        self._insert(uk[new], pos[new], sums[new])

    def _insert(self, keys: Tensor, pos: Tensor, sums: Tensor) -> None:
        """Append rows for new sorted ``keys`` whose insertion points in the sorted keys are ``pos``; merge."""
        k = len(keys)
        if k == 0:
            return
        self._reserve(self._n + k)
        rows = torch.arange(self._n, self._n + k)
        self._sums[self._n : self._n + k] = sums
        self._n += k
        m = len(self._sorted)
        dest = pos + torch.arange(k)  # where the new keys land in the merged array
        old = torch.ones(m + k, dtype=torch.bool)
        old[dest] = False
        merged, slot = torch.empty(m + k, dtype=torch.int64), torch.empty(m + k, dtype=torch.int64)
        merged[dest], slot[dest] = keys, rows
        merged[old], slot[old] = self._sorted, self._slot
        self._sorted, self._slot = merged, slot

    def _reserve(self, rows: int) -> None:
        cap = len(self._sums)
        if rows <= cap:
            return
        new = self._sums.new_zeros(max(rows, 2 * cap, 1024), 7)
        new[: self._n] = self._sums[: self._n]
        self._sums = new

    def _range(self, b: int) -> tuple[int, int]:
        """The run [lo, hi) of sequence b's keys in the sorted keys."""
        bounds = torch.tensor([b << (3 * AXIS_BITS), (b + 1) << (3 * AXIS_BITS)], dtype=torch.int64)
        if b + 1 == MAX_BATCH:
            bounds[1] = torch.iinfo(torch.int64).max
        lo, hi = torch.searchsorted(self._sorted, bounds).tolist()
        return lo, hi

    def points(self, b: int = 0) -> MapPoints:
        """Sequence b's map: one point per voxel, the mean position and colour of its points."""
        lo, hi = self._range(b)
        sums = self._sums[self._slot[lo:hi]]
        n = sums[:, 6:]
        return MapPoints(sums[:, :3] / n, (sums[:, 3:6] / n).float(), n[:, 0].long())

    def size(self, b: int) -> int:
        """Occupied voxels of sequence b."""
        lo, hi = self._range(b)
        return hi - lo

    def clear(self, b: int) -> None:
        """Forget sequence b's map and compact the buffers (a finished sequence's memory is released)."""
        lo, hi = self._range(b)
        if hi == lo:
            return
        keep = torch.cat([self._slot[:lo], self._slot[hi:]])
        self._sorted = torch.cat([self._sorted[:lo], self._sorted[hi:]])
        order = torch.argsort(keep)  # keep the rows' arrival order
        rows = keep[order]
        self._sums, self._n = self._sums[rows], len(rows)
        slot = torch.empty_like(keep)
        slot[order] = torch.arange(len(rows))
        self._slot = slot
