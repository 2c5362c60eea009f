"""A streaming voxel-grid point map, batched over B sequences: one coloured point per occupied voxel.

Every voxel keeps the sums of the positions and colours of the points that fell in it and their count; the map's
point is the mean (position and colour). Memory is bounded by the occupied volume, not by the number of frames, and
where that is too large by :meth:`VoxelPointMap.prune`, which keeps the voxels with the most support.

Voxels are keyed by one int64 per (sequence, voxel): ``b << 54 | (ix + 2^17) << 36 | (iy + 2^17) << 18 | (iz + 2^17)``
with ``i = floor(p / voxel_size)`` per axis, so one index serves all B maps and points outside +-2^17 voxels of the
world origin (+-1.3 km at 1 cm) are dropped and counted.

The index is a hash table with open addressing (linear probing, at most half full; a slot holds a voxel's row, its key
is read from the rows' keys): a frame of K voxels costs O(K) expected, whatever the map's size. A frame's fusion runs
as the compiled ``torch.ops.torchtrack.voxel_add`` (csrc/voxel.cpp) where it builds, else in torch with vectorised
probing (:meth:`VoxelPointMap._add_torch`, its reference). The per-voxel sums (x, y, z, r, g, b, count: 7 float64) and the
keys live in append-only buffers, one row per voxel, that grow by doubling; the table doubles (and is filled anew,
compiled as ``torch.ops.torchtrack.voxel_rehash`` where the fusion is) when it would be more than half full.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack import ops

AXIS_BITS = 18
BATCH_BITS = 63 - 3 * AXIS_BITS  # 9: up to 512 sequences
HALF = 1 << (AXIS_BITS - 1)
MAX_BATCH = 1 << BATCH_BITS
EMPTY = -1  # a free slot of the table


class Added(NamedTuple):
    """What one :meth:`VoxelPointMap.add` did: the voxels it created, keys (K,) ascending and buffer rows (K,), and
    the voxels the map had that took points, keys (G,) and rows (G,) in no set order (a key's sequence: ``key >> 54``)."""

    keys: Tensor
    rows: Tensor
    known_keys: Tensor
    known_rows: Tensor


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


def _slot(keys: Tensor, size: int) -> Tensor:
    """The first slot (P,) of ``keys`` (P,) in a table of ``size`` (a power of two) slots: Fibonacci hashing, the top
    log2(size) bits of key x 0x9E3779B97F4A7C15 (2^64 / the golden ratio; int64, wrapping), which scatters
    neighbouring voxels over the table (csrc/voxel.cpp computes the same)."""
    bits = size.bit_length() - 1
    return ((keys * -0x61C8864680B583EB) >> (64 - bits)) & (size - 1)


class VoxelPointMap:
    """B voxel-grid point maps fused point by point.

    Args:
        voxel_size: edge of a voxel, metres.
        batch_size: B, the number of maps (<= 512).
        device: where the sums and the index live; the points added must be on it (the tracker's frames' device).
            The fusion runs as the compiled ``torch.ops.torchtrack.voxel_add`` where it runs on that device
            (:func:`torchtrack.ops.compiled`), else as its reference :meth:`_add_torch`.
    """

    def __init__(
        self,
        *,
        voxel_size: float = 0.01,
        batch_size: int = 1,
        device: torch.device | str = "cpu",
    ) -> None:
        if voxel_size <= 0:
            raise ValueError(f"VoxelPointMap: voxel_size must be > 0, got {voxel_size}")
        if not 1 <= batch_size <= MAX_BATCH:
            raise ValueError(f"VoxelPointMap: batch_size must be in [1, {MAX_BATCH}], got {batch_size}")
        self.voxel_size = float(voxel_size)
        self.batch_size = batch_size
        self.dropped = 0  # points outside the representable range
        self._n = 0  # rows used in the buffers
        self._sums = torch.empty(0, 7, dtype=torch.float64, device=device)  # by row: sum of x, y, z, r, g, b; count
        self._keys = torch.empty(0, dtype=torch.int64, device=device)  # by row: the voxel's key
        self._table = torch.full((1024,), EMPTY, dtype=torch.int64, device=device)  # slot -> row, or EMPTY
        self._sizes = [0] * batch_size  # voxels per sequence

    def __len__(self) -> int:
        """Occupied voxels over all B maps."""
        return self._n

    @property
    def device(self) -> torch.device:
        """Where the map lives."""
        return self._sums.device

    @property
    def nbytes(self) -> int:
        """Bytes held by the map's buffers (capacity, not only the rows in use)."""
        return (self._sums.numel() + self._keys.numel() + self._table.numel()) * 8

    def add(self, points: Tensor, rgb: Tensor, batch: Tensor) -> Added:
        """Fuse points (P, 3) float64 world metres with colours rgb (P, 3) into the maps of ``batch`` (P,) int64.
        Returns the voxels this created and those it added to (:class:`Added`)."""
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
        if ops.compiled(self._sums):
            self._reserve(self._n + len(points))  # room for every point as a new voxel
            *out, dropped = torch.ops.torchtrack.voxel_add(
                self._table, self._keys, self._sums, self._n, points.double().contiguous(),
                rgb.double().contiguous(), batch.long().contiguous(), self.voxel_size,
            )  # fmt: skip
            self.dropped += dropped
            added = Added(*out)
        else:
            added = self._add_torch(points, rgb, batch)
        self._n += len(added.keys)
        for b, count in enumerate(torch.bincount(added.keys >> (3 * AXIS_BITS), minlength=self.batch_size).tolist()):
            self._sizes[b] += count
        return added

    def _add_torch(self, points: Tensor, rgb: Tensor, batch: Tensor) -> Added:
        """:meth:`add`'s fusion in torch: the compiled ``voxel_add``'s reference (tests/test_mapping.py) and the path
        where it does not build (``_n`` not advanced)."""
        keys, inside = voxel_keys(points.double(), batch.long(), self.voxel_size)
        if not bool(inside.all()):
            self.dropped += int((~inside).sum())
            keys, points, rgb = keys[inside], points[inside], rgb[inside]
        if len(keys) == 0:
            return Added(keys, keys.clone(), keys.clone(), keys.clone())
        uk, inv = torch.unique(keys, sorted=True, return_inverse=True)
        ones = torch.ones(len(keys), 1, dtype=torch.float64, device=keys.device)
        values = torch.cat([points.double(), rgb.double(), ones], 1)
        sums = torch.zeros(len(uk), 7, dtype=torch.float64, device=uk.device).index_add_(0, inv, values)
        self._reserve(self._n + len(uk))  # room for every voxel as a new one
        rows = self._index_torch(uk)
        new = rows >= self._n
        self._sums[self._n : self._n + int(new.sum())] = 0.0
        self._sums.index_add_(0, rows, sums)
        return Added(uk[new], rows[new], uk[~new], rows[~new])

    def _index_torch(self, keys: Tensor) -> Tensor:
        """The rows (P,) of the voxels ``keys`` (P,) (distinct): each one's row where the map has it, else a new row
        (``_n``, ``_n`` + 1, ... in the order of ``keys``; ``_n`` not advanced), its key written and entered in the
        table. The buffers must have room (:meth:`_reserve`)."""
        rows = self._find(keys)
        new = (rows < 0).nonzero().squeeze(1)
        rows[new] = torch.arange(self._n, self._n + len(new), device=keys.device)
        self._keys[rows[new]] = keys[new]
        self._insert(rows[new])
        return rows

    def _find(self, keys: Tensor) -> Tensor:
        """The rows (P,) of the voxels ``keys`` (P,) (EMPTY where the map has none): all probed at once, slot after
        slot, each until its key or a free slot."""
        rows = torch.full_like(keys, EMPTY)
        todo = torch.arange(len(keys) if self._n else 0, device=keys.device)
        slot = _slot(keys, len(self._table))
        while len(todo):
            r = self._table[slot]
            hit = (r >= 0) & (self._keys[r.clamp_min(0)] == keys[todo])
            rows[todo[hit]] = r[hit]
            more = (r >= 0) & ~hit  # another voxel's slot: the next one
            todo, slot = todo[more], (slot[more] + 1) & (len(self._table) - 1)
        return rows

    def _insert(self, rows: Tensor) -> None:
        """Enter the voxels of ``rows`` (their keys not in the table yet) into the table: each takes the first free
        slot from its own; of several that reach one free slot together one takes it, the others probe on."""
        slot = _slot(self._keys[rows], len(self._table))
        while len(rows):
            free = self._table[slot] < 0
            self._table[slot[free]] = rows[free]
            took = self._table[slot] == rows
            rows, slot = rows[~took], (slot[~took] + 1) & (len(self._table) - 1)

    def _reserve(self, rows: int) -> None:
        """Room for ``rows`` voxels: the buffers (doubling) and the table (at most half full: probes stay short;
        doubled and filled anew)."""
        cap = len(self._sums)
        if rows > cap:  # rows past _n are never read
            size = max(rows, 2 * cap, 1024)
            sums = torch.empty(size, 7, dtype=torch.float64, device=self.device)
            keys = torch.empty(size, dtype=torch.int64, device=self.device)
            sums[: self._n], keys[: self._n] = self._sums[: self._n], self._keys[: self._n]
            self._sums, self._keys = sums, keys
        if 2 * rows > len(self._table):
            size = len(self._table)
            while 2 * rows > size:
                size *= 2
            self._rehash(size)

    def _rehash(self, size: int) -> None:
        """A table of ``size`` slots holding the map's voxels (the compiled ``voxel_rehash`` where the fusion runs
        compiled: at a doubling the torch probing costs ~0.1 s for 300,000 voxels)."""
        self._table = torch.empty((size,), dtype=torch.int64, device=self.device)
        if ops.compiled(self._sums):
            torch.ops.torchtrack.voxel_rehash(self._table, self._keys, self._n)
            return
        self._table.fill_(EMPTY)
        n, self._n = self._n, 0
        self._index_torch(self._keys[:n].clone())  # each key new to the empty table: rows 0 .. n - 1, as they were
        self._n = n

    def voxels(self, b: int, ordered: bool = True, every: int = 1) -> tuple[Tensor, Tensor]:
        """Sequence b's voxels: keys (M_b,) and buffer rows (M_b,), in key order (``ordered``; else in the order they
        were created); ``every`` > 1: only those whose :func:`spatial_hash` is a multiple of it."""
        keys = self._keys[: self._n]
        pick = (keys >> (3 * AXIS_BITS)) == b
        if every > 1:
            pick &= spatial_hash(keys) % every == 0
        rows = pick.nonzero().squeeze(1)
        keys = keys[rows]
        if not ordered:
            return keys, rows
        keys, order = torch.sort(keys)
        return keys, rows[order]

    def points(self, b: int = 0, ordered: bool = True, every: int = 1) -> MapPoints:
        """Sequence b's map: one point per voxel, the mean position and colour of its points; sorted by voxel key
        (``ordered``; else in an order that saves the sort). ``every`` > 1: about one voxel in ``every``, the same ones
        whatever the other sequences in the map and the order they were added in (:func:`spatial_hash`)."""
        sums = self._sums[self.voxels(b, ordered, every)[1]]
        n = sums[:, 6:]
        return MapPoints(sums[:, :3] / n, (sums[:, 3:6] / n).float(), n[:, 0].long())

    @property
    def sums(self) -> Tensor:
        """The voxels' sums (M, 7) float64 by buffer row: x, y, z, r, g, b, count (a view: read, do not write)."""
        return self._sums[: self._n]

    def xyz(self, rows: Tensor) -> Tensor:
        """The mean positions (M, 3) of the voxels at buffer ``rows`` (M,) (:meth:`voxels`): ``points().xyz`` of
        those voxels, without the colours."""
        sums = self._sums[rows]
        return sums[:, :3] / sums[:, 6:]

    def size(self, b: int) -> int:
        """Occupied voxels of sequence b."""
        return self._sizes[b]

    def prune(self, b: int, keep: int, protect: Tensor | None = None) -> int:
        """Keep sequence b's ``keep`` best-supported voxels and forget the others: those that averaged the fewest
        points go first (a voxel seen once, a transient surface or a depth outlier, before one seen from many
        frames), whatever their age; among equal counts the larger :func:`spatial_hash` (then the larger key) goes
        first: no pattern in space, the same choice however the map grew. The voxels of ``protect`` (keys, e.g. those
        the last frame saw: present now, however little support they have yet) go last. The means of the kept voxels
        are unchanged; the buffers are compacted (their rows renumbered, in their order). Returns the number of voxels
        forgotten."""
        if keep < 0:
            raise ValueError(f"VoxelPointMap.prune: keep must be >= 0, got {keep}")
        if self._sizes[b] <= keep:
            return 0
        keys = self._keys[: self._n]
        rows = ((keys >> (3 * AXIS_BITS)) == b).nonzero().squeeze(1)
        mine = keys[rows]
        order = torch.argsort(mine)
        for rank in (spatial_hash(mine), -self._sums[rows, 6]):  # stable: the last sort decides first
            order = order[torch.argsort(rank[order], stable=True)]
        if protect is not None and len(protect):
            order = order[torch.argsort((~torch.isin(mine[order], protect)).to(torch.uint8), stable=True)]
        kept = torch.ones(self._n, dtype=torch.bool, device=self.device)
        kept[rows[order[keep:]]] = False
        dropped = self._sizes[b] - keep
        self._compact(kept)
        self._sizes[b] = keep
        return dropped

    def clear(self, b: int) -> None:
        """Forget sequence b's map and compact the buffers (a finished sequence's memory is released)."""
        if not self._sizes[b]:
            return
        self._compact((self._keys[: self._n] >> (3 * AXIS_BITS)) != b)
        self._sizes[b] = 0

    def _compact(self, kept: Tensor) -> None:
        """Keep the voxels of rows ``kept`` (_n,) bool, in their order (rows renumbered), and index them anew."""
        self._sums, self._keys = self._sums[: self._n][kept], self._keys[: self._n][kept]
        self._n = len(self._keys)
        self._rehash(len(self._table))
