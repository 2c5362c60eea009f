"""A dense map that remembers, and the model placed on it (frame-to-model, point-to-plane).

The map (:class:`DenseMap`) is one :class:`~torchtrack.map.voxel_grid.VoxelPointMap` per sequence: the depth of
the keyframes, placed by their poses, averaged per voxel (one point per occupied voxel, so memory grows with the
volume seen, not with the frames; an index in space). Every ``every`` frames and at every re-selection, the tracker's
current camera is aligned to it (:meth:`DenseMap.align`): the map points predicted visible from the camera are
projected into the current depth image and each is paired with the surface point seen at its pixel; Gauss-Newton on
the point-to-plane distances ``n . (T p - v)`` (n the current frame's normal at v), Huber-weighted, with the tracker's
camera as a prior, gives the posterior camera. The tracker then moves its model in the world (``T_world_obj``) so that
the camera is there: the features and the filter are untouched (they measure the camera against the model), and the
model's world pose, which a chain of re-selections would only accumulate, is estimated against everything the camera
saw before, however long ago. The Gauss-Newton fit, a keyframe's points and the pool's upkeep run as compiled
operators (csrc/dense.cpp, csrc/voxel.cpp) where they build, else as their torch references.

Frames: ``world`` is the tracker's world (its first depth camera); the map and the alignment work in the depth camera,
on its own pixel grid and intrinsics (a separate depth camera's frames are used as taken, not warped).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack import ops
from torchtrack.geometry import T_inv, backproject_depth, se3_exp, transform_points
from torchtrack.map.depth_grid import MAX_STEP, grid, surface
from torchtrack.map.voxel_grid import AXIS_BITS, Added, VoxelPointMap, spatial_hash


class Alignment(NamedTuple):
    """T_world_cam (B, 4, 4) float64 the aligned depth cameras (the input where not ``applied``); applied (B,)
    bool; pairs (B,) long the map points paired with the surface in the last iteration (0 where not aligned)."""

    T_world_cam: Tensor
    applied: Tensor
    pairs: Tensor


class Fit(NamedTuple):
    """One camera's Gauss-Newton fit to its map: the correction ``delta`` (4, 4) (the aligned world-to-camera pose is
    delta @ T_cw); its twist ``xi`` (6,) (the sum of the steps: the prior's residual); the data's information
    ``info`` J^T W J (6, 6) of the last iteration; the ``pairs`` of the last iteration; ``step``, the last step's
    largest component (metres and radians; inf where fewer than 6 pairs were left); ``steps`` taken; ``weak``: False
    where the information is clearly above ``weak`` times the prior's in every direction (the gate has nothing to
    project off), True where some direction may be below it (the gate's eigenproblem decides)."""

    delta: Tensor
    xi: Tensor
    info: Tensor
    pairs: int
    step: float
    steps: int
    weak: bool = True


class DenseMap:
    """B dense point maps of the keyframes' depth, and a camera aligned to them.

    A pose direction in which the current depth holds little information (``weak``: half a surface, a plane) keeps
    the tracker's camera: the correction is projected off it.

    Args:
        voxel_size: map voxel edge, metres (one point per occupied voxel: the mean of the points that fell in it).
        every: the tracker aligns its camera at every re-selection and every this many frames (:meth:`due`).
        stride: the depth is used at every ``stride``-th pixel (map and alignment).
        max_points: at most this many visible map points per alignment (evenly thinned).
        iterations: Gauss-Newton iterations.
        max_distance_m: a pair farther apart along the normal (or twice this in space) is not used: occluded, or
            another surface.
        huber_m: Huber threshold of the point-to-plane distance.
        sigma_m: the point-to-plane distance's standard deviation at 1 m, times max(1, z^2) (the depth noise).
        prior_m, prior_deg: standard deviations of the tracker's camera as the prior (translation, rotation).
        min_pairs: fewer pairs at the end: no correction.
        max_correction_m, max_correction_deg: a larger correction is not applied (a wrong fit, not drift).
        max_depth: depth beyond this (metres) enters neither the map nor the alignment.
        converged: a correction is applied only when the last Gauss-Newton step's largest component is below this
            (metres and radians): else the fit was in a wrong basin, or still on its way.
        tolerance: Gauss-Newton stops after a step below this (metres and radians; the steps shrink geometrically,
            ~0.4x each: what remains is a few hundredths of a millimetre).
        weak: a direction of the pose in which the depth's information is below this many times the prior's is left
            as the tracker had it (the correction projected off it).
        max_voxels: the most voxels a sequence's map holds, so that memory is bounded however far the camera goes:
            beyond it the map is pruned to three quarters of it (so that a full map is pruned every few keyframes,
            not at each; at least ``min_pairs``), the voxels that averaged the fewest points first, those the frame
            that filled it saw last (:meth:`~torchtrack.map.voxel_grid.VoxelPointMap.prune`).

    The fit, a keyframe's points and the pool's upkeep run as the compiled ``dense_fit``, ``depth_points``
    (csrc/dense.cpp) and ``pool_update`` (csrc/voxel.cpp) where they run (:func:`torchtrack.ops.compiled`), else as
    their references :meth:`_fit_torch`, :meth:`_points_torch` and :meth:`_updated`'s torch path.
    """

    def __init__(
        self,
        *,
        voxel_size: float = 0.01,
        every: int = 1,
        stride: int = 4,
        max_points: int = 5000,
        iterations: int = 12,
        max_distance_m: float = 0.05,
        huber_m: float = 0.01,
        sigma_m: float = 0.005,
        prior_m: float = 0.01,
        prior_deg: float = 1.0,
        min_pairs: int = 500,
        max_correction_m: float = 0.1,
        max_correction_deg: float = 5.0,
        max_depth: float = 4.0,
        converged: float = 3e-3,
        tolerance: float = 1e-4,
        weak: float = 3.0,
        max_voxels: int = 1_000_000,
    ) -> None:
        if voxel_size <= 0 or min(every, stride, iterations, max_points) < 1 or 3 * max_voxels // 4 < min_pairs:
            raise ValueError(f"DenseMap: need voxel_size > 0, every, stride, iterations, max_points >= 1 and 3/4 of "
                             f"max_voxels >= min_pairs; got {voxel_size}, {every}, {stride}, {iterations}, {max_points}, "
                             f"{max_voxels} (min_pairs {min_pairs})")  # fmt: skip
        self.voxel_size, self.every, self.stride, self.max_points = voxel_size, every, stride, max_points
        self.iterations, self.max_distance_m, self.huber_m, self.sigma_m = iterations, max_distance_m, huber_m, sigma_m
        self.prior_m, self.prior_deg, self.min_pairs = prior_m, prior_deg, min_pairs
        self.max_correction_m, self.max_correction_deg, self.max_depth = max_correction_m, max_correction_deg, max_depth
        self.converged, self.tolerance, self.weak, self.max_voxels = converged, tolerance, weak, max_voxels
        self.map: VoxelPointMap | None = None
        self.since: Tensor | None = None  # frames since each sequence's last alignment
        self._pools: list[_Pool | None] = []  # per sequence: the map's points an alignment draws from

    def reset(self, B: int, device: torch.device | str = "cpu") -> None:
        """Empty maps for B sequences."""
        self.map = VoxelPointMap(voxel_size=self.voxel_size, batch_size=B, device=device)
        self.since = torch.zeros(B, dtype=torch.long, device=device)
        self._pools = [None] * B

    def due(self, reselect: Tensor, active: Tensor) -> Tensor:
        """(B,) bool: the ``active`` (B,) sequences whose camera is aligned this frame: a new model is taken
        (``reselect`` (B,)) or ``every`` frames passed since the last alignment. Counts the frame."""
        if self.since is None:
            raise ValueError("DenseMap: call reset(B) before due")
        self.since = self.since + active.long()
        out = active & (reselect | (self.since >= self.every))
        self.since = torch.where(out, 0, self.since)
        return out

    def add(self, depth: Tensor, K: Tensor, T_world_cam: Tensor, mask: Tensor, region: Tensor | None = None) -> None:
        """Fuse the depth (B, 1, H, W) of the sequences in ``mask`` (B,), seen through the intrinsics K (B, 3, 3) of its
        camera from ``T_world_cam`` (B, 4, 4), into their maps (no depth (0, negative, NaN) or beyond ``max_depth``:
        nothing; only inside ``region`` (B, 1, H, W) bool where given)."""
        if self.map is None:
            raise ValueError("DenseMap: call reset(B) before add")
        if ops.compiled(depth):
            world, b = torch.ops.torchtrack.depth_points(
                depth.float().contiguous(), None if region is None else region.contiguous(), K.double().contiguous(),
                T_world_cam.double().contiguous(), mask.contiguous(), self.stride, self.max_depth,
            )  # fmt: skip
        else:
            world, b = self._points_torch(depth, K, T_world_cam, mask, region)
        world, b = world.to(self.map.device), b.to(self.map.device)
        added = self.map.add(world, torch.zeros_like(world), b)
        for i in mask.nonzero().squeeze(1).tolist():
            self._pools[i] = self._updated(i, added)
        for i in mask.nonzero().squeeze(1).tolist():  # after the pools: a prune renumbers the rows ``added`` names
            if self.map.size(i) > self.max_voxels:  # what this frame saw is kept (present now, if seen once so far)
                self.map.prune(i, 3 * self.max_voxels // 4, protect=torch.cat([added.keys, added.known_keys]))
                self._pools[i] = None  # picked anew (the others hold keys and points, not rows)

    def _points_torch(self, depth: Tensor, K: Tensor, T_world_cam: Tensor, mask: Tensor,
                      region: Tensor | None) -> tuple[Tensor, Tensor]:  # fmt: skip
        """The world points (P, 3) float64 :meth:`add` fuses and their sequences (P,), in (sequence, row, column) order,
        of the depth (B, 1, H, W) (read as float32), K (B, 3, 3), T_world_cam (B, 4, 4), mask (B,) and region as
        :meth:`add`'s: the compiled ``depth_points``'s reference (tests/test_dense_op.py)."""
        d, Ks = grid(depth.float(), K, self.stride, region)
        V = backproject_depth(Ks, d[:, None].double()).flatten(1, 2)
        ok = (V[..., 2] > 0) & (V[..., 2] <= self.max_depth) & mask[:, None]
        b = torch.arange(len(mask), device=ok.device)[:, None].expand_as(ok)[ok]
        return transform_points(T_world_cam.double(), V)[ok], b

    def align(self, depth: Tensor, K: Tensor, T_world_cam: Tensor, mask: Tensor,
              region: Tensor | None = None) -> Alignment:  # fmt: skip
        """The depth cameras ``T_world_cam`` (B, 4, 4) of the sequences in ``mask`` (B,) aligned to their maps through
        their current depth (B, 1, H, W) (only inside ``region`` (B, 1, H, W) bool where given) and its intrinsics K
        (B, 3, 3)."""
        if self.map is None:
            raise ValueError("DenseMap: call reset(B) before align")
        B = len(mask)
        T_in = T_world_cam.double().cpu()
        T_cw = T_inv(T_in)
        delta = torch.eye(4, dtype=torch.float64, device="cpu").repeat(B, 1, 1)  # the corrections, on the host
        applied, pairs = [False] * B, [0] * B
        if bool(mask.any()):
            d, Ks = grid(depth, K, self.stride, region, clean=False)  # the fit finds no surface where depth is not > 0
            for b in mask.nonzero().squeeze(1).tolist():
                world = self._pool(b)
                if world is None:
                    continue
                fit = self.fit(world, d[b], Ks[b], T_cw[b].to(world.device))
                pairs[b] = fit.pairs
                if fit.step == math.inf:  # too few pairs left: no correction
                    continue
                delta[b] = self._gated(fit)  # the correction, in the camera
                cos = (float(delta[b, :3, :3].trace()) - 1.0) / 2.0
                applied[b] = (
                    fit.pairs >= self.min_pairs
                    and fit.step < self.converged  # else a wrong basin, or a partial correction
                    and float(delta[b, :3, 3].norm()) <= self.max_correction_m
                    and math.acos(max(-1.0, min(1.0, cos))) <= math.radians(self.max_correction_deg)
                )
        dev = mask.device
        done = torch.tensor(applied, dtype=torch.bool, device="cpu")
        T_out = torch.where(done[:, None, None], T_inv(delta @ T_cw), T_in) if any(applied) else T_in
        return Alignment(T_out.to(dev), done.to(dev), torch.tensor(pairs, dtype=torch.long, device=dev))

    def _pool(self, b: int) -> Tensor | None:
        """Sequence b's map points an alignment draws from (M, 3) float64: about 8 ``max_points`` of its voxels, picked
        by a spatial hash and in voxel-key order (the same points in the same order however the map grew, so the
        alignment does not depend on the other sequences); kept up to date by :meth:`add` (:meth:`_updated`). None
        while the map has fewer than ``min_pairs`` voxels."""
        if self._pools[b] is None:
            if self.map.size(b) < self.min_pairs:
                return None
            keys, rows = self.map.voxels(b, ordered=True, every=self._every(b))
            self._pools[b] = _Pool(keys, self.map.xyz(rows), self._every(b))
        return self._pools[b].xyz

    def _every(self, b: int) -> int:
        """The pool's thinning for sequence b's map as it is: about 8 ``max_points`` of its voxels kept."""
        return max(1, self.map.size(b) // (8 * self.max_points))

    def _updated(self, b: int, added: Added) -> _Pool | None:
        """Sequence b's pool after an add (None: picked anew at the next alignment, where the thinning changed): the
        means of its voxels that took points recomputed, the new voxels the hash picks merged into the sorted keys; the
        same points in the same order as picked anew (tests/test_dense_map.py), at the cost of what the add touched,
        not of the pool's ~50,000 means scattered over the map. Compiled (``pool_update``) where it runs."""
        pool = self._pools[b]
        if pool is None or self.map.size(b) < self.min_pairs or pool.every != self._every(b):
            return None
        if ops.compiled(pool.xyz):
            keys, xyz = torch.ops.torchtrack.pool_update(pool.keys, pool.xyz, self.map.sums, added.known_keys,
                                                         added.known_rows, added.keys, added.rows, b, pool.every)  # fmt: skip
            return _Pool(keys, xyz, pool.every)

        def picked(keys: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
            keep = (keys >> (3 * AXIS_BITS)) == b
            if pool.every > 1:
                keep &= spatial_hash(keys) % pool.every == 0
            return keys[keep], rows[keep]

        keys, rows = picked(added.keys, added.rows)
        keys, xyz = _merge((pool.keys, pool.xyz), (keys, self.map.xyz(rows)))
        known, rows = picked(added.known_keys, added.known_rows)  # in the pool since it was picked or merged
        xyz[torch.searchsorted(keys, known)] = self.map.xyz(rows)
        return _Pool(keys, xyz, pool.every)

    def fit(self, world: Tensor, depth: Tensor, K: Tensor, T_cw: Tensor) -> Fit:
        """Gauss-Newton on the world-to-camera pose from ``T_cw`` (4, 4), the map points ``world`` (M, 3) (the
        :meth:`_pool`) against the surface of the depth grid (h, w) (any strides; no depth where 0, negative or NaN)
        seen through K (3, 3) (:func:`surface`), by the compiled ``torch.ops.torchtrack.dense_fit`` (csrc/dense.cpp)
        where it runs, else by :meth:`_fit_torch`. Stops early once a step is below ``tolerance``."""
        if not ops.compiled(depth):
            return self._fit_torch(world, depth, K, T_cw)
        delta, xi, info, stats = torch.ops.torchtrack.dense_fit(
            world.double().contiguous(), depth.float(), K.double().contiguous(),
            T_cw.double().contiguous(), self.max_points, self.iterations, self.max_depth,
            self.max_distance_m, self.huber_m, self.sigma_m, self.prior_m, math.radians(self.prior_deg),
            self.tolerance, MAX_STEP, self.weak,
        )  # fmt: skip
        pairs, step, steps, weak = stats.tolist()
        return Fit(delta, xi, info, int(pairs), step, int(steps), bool(weak))

    def _fit_torch(self, world: Tensor, depth: Tensor, K: Tensor, T_cw: Tensor) -> Fit:
        """:meth:`fit` in torch: the operator's reference (tests/test_dense_op.py), and the path where it does not
        build."""
        V, N, valid, K = (x[0] for x in surface(depth[None, None], K[None], 1))
        h, w = valid.shape
        x, y, z = transform_points(T_cw, world).unbind(-1)  # float64: the operator's culling flips no point
        fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        u, v = fx * x + cx * z, fy * y + cy * z  # the pixel times z: no division
        seen = (z > 0.1) & (z <= self.max_depth) & (u > -0.5 * z) & (v > -0.5 * z) & (u < (w - 0.5) * z)
        world = world[seen & (v < (h - 0.5) * z)]  # still in voxel order
        n, m = len(world), self.max_points
        if n > m:  # evenly thinned, in integers (the operator picks the same points)
            world = world[torch.arange(m, device=world.device) * (n - 1) // max(m - 1, 1)]
        # Structure of arrays (3, M): the per-point work is a few dozen row operations, not strided columns.
        P0 = torch.addmm(T_cw[:3, 3:], T_cw[:3, :3], world.T)  # the points in the starting camera
        # One gather per iteration: each pixel's vertex, normal and validity in a row; the last row is "no surface".
        table = torch.cat([V.reshape(-1, 3), N.reshape(-1, 3), valid.reshape(-1, 1).double()], 1)
        table = torch.cat([table, table.new_zeros(1, 7)])
        rad = math.radians(self.prior_deg)
        prior = torch.tensor([self.prior_m**-2] * 3 + [rad**-2] * 3, dtype=torch.float64, device=world.device).diag()
        xi = torch.zeros(6, dtype=torch.float64, device=world.device)  # the correction so far (the prior's residual)
        step = torch.full_like(xi, math.inf)
        delta = torch.eye(4, dtype=torch.float64, device=world.device)  # the correction, applied to P0
        n_pairs = 0
        for k in range(self.iterations):
            P = torch.addmm(delta[:3, 3:], delta[:3, :3], P0)
            x, y, z = P
            iz = 1.0 / z.clamp_min(1e-6)
            u = (x * iz * fx + cx).round_().long()
            v = (y * iz * fy + cy).round_().long()
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0.1)
            S = table[torch.where(inside, v * w + u, h * w)].T  # (7, M)
            q, n = S[:3], S[3:6]
            d = P - q
            r = (d * n).sum(0)
            ra = r.abs()
            ok = (S[6] > 0) & (ra <= self.max_distance_m) & ((d * d).sum(0) <= (2 * self.max_distance_m) ** 2)
            n_pairs = int(ok.sum())
            if n_pairs < 6:
                return Fit(delta, xi, torch.zeros_like(prior), n_pairs, math.inf, k)
            huber = torch.where(ra <= self.huber_m, 1.0, self.huber_m / ra.clamp_min(1e-12))
            wgt = huber * ok / (self.sigma_m * z.square().clamp_min(1.0)) ** 2
            x, y, z = P
            a, b, c = n
            J = torch.stack([a, b, c, y * c - z * b, z * a - x * c, x * b - y * a])  # d r / d xi = n^T [I, -[p]x]
            Jw = J * wgt
            step = -torch.linalg.solve(torch.addmm(prior, Jw, J.T), Jw @ r + prior @ xi)
            xi = xi + step
            delta = se3_exp(step[None])[0] @ delta  # left perturbation
            if float(step.abs().max()) < self.tolerance:
                break
        return Fit(delta, xi, Jw @ J.T, n_pairs, float(step.abs().max()), k + 1)

    def _gated(self, fit: Fit) -> Tensor:
        """The fit's correction (4, 4) float64, projected off every pose direction in which the data's information is
        below ``weak`` times the prior's."""
        # A direction in which the depth holds less than ``weak`` times the prior's information (half a surface, a
        # plane) is not corrected: the point-to-plane sigma treats the pairs as independent, so along it the data's
        # information is overstated and the correction would follow the depth's correlated errors.
        # The 6x6 eigenproblem in numpy: on a matrix this small torch's per-call overhead (eigh, boolean indexing,
        # small tensors) is most of the cost, and this runs every frame.
        if not fit.weak:  # the operator's Cholesky test: the eigenproblem (~0.3 ms, caches cold) would find none
            return fit.delta.cpu()
        rad = math.radians(self.prior_deg)
        sd = np.array([self.prior_m] * 3 + [rad] * 3)
        ratio, vec = np.linalg.eigh(fit.info.cpu().numpy() * sd[:, None] * sd[None, :])  # whitened: information ratios
        weak = vec[:, ratio < self.weak]
        if not weak.shape[1]:
            return fit.delta.cpu()
        y = fit.xi.cpu().numpy() / sd
        return se3_exp(torch.from_numpy(sd * (y - weak @ (weak.T @ y)))[None])[0]


class _Pool(NamedTuple):
    """A sequence's pool (:meth:`DenseMap._pool`): voxel keys (M,) ascending, their points (M, 3), and the thinning
    ``every`` they were picked with."""

    keys: Tensor
    xyz: Tensor
    every: int


def _merge(old: tuple[Tensor, ...], new: tuple[Tensor, ...]) -> tuple[Tensor, ...]:
    """Two disjoint sets of rows, each sorted by its first tensor (keys), as one sorted set: (keys, ...) tensors of
    equal length each (the torch reference of ``pool_update``'s merge)."""
    order = torch.argsort(torch.cat([old[0], new[0]]))
    return tuple(torch.cat([a, b])[order] for a, b in zip(old, new, strict=True))
