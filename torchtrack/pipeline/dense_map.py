"""A dense map that remembers, and the camera aligned to it (frame-to-model, point-to-plane).

The map is a :class:`~torchtrack.mapping.voxel_grid.VoxelPointMap` per sequence: the depth of the keyframes, placed by
their poses, averaged per voxel (one point per occupied voxel: memory bounded by the volume seen, not by the frames).
At a re-selection the camera the new model is anchored at is first aligned to the map: the map points predicted
visible from the tracker's camera are projected into the current depth image and each is paired with the surface
point seen at its pixel; Gauss-Newton on the point-to-plane distances ``n . (T p - v)`` (the current frame's normal n
at v), robustly weighted, with the tracker's pose as a prior, gives the camera that puts the map on the current
surface. Anything the camera saw before, however long ago, pulls the pose back instead of chaining the drift.

Frames: ``world`` is the tracker's world (its first depth camera); the alignment works in the colour camera, whose
grid the registered depth is in.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.geometry import T_inv, backproject_depth, rotation_angle, se3_exp, transform_points
from torchtrack.mapping.voxel_grid import VoxelPointMap


class Alignment(NamedTuple):
    """T_world_color (B, 4, 4) float64 the aligned colour cameras (the input where not ``applied``); applied (B,)
    bool; pairs (B,) long map points paired with the surface at the end; information (B, 6, 6) float64 the
    alignment's Gauss-Newton information (left perturbation of the world-to-camera pose, xi = (v, omega))."""

    T_world_color: Tensor
    applied: Tensor
    pairs: Tensor
    information: Tensor


def surface(depth: Tensor, K: Tensor, stride: int, max_step: float = 0.05) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The current frame's surface at every ``stride``-th pixel: vertices (B, h, w, 3), unit normals (B, h, w, 3) (by
    central differences of the neighbouring vertices), valid (B, h, w) (depth at the pixel and its four neighbours,
    none farther than ``max_step`` x z in depth: no normal across a depth step), and the strided intrinsics (B, 3, 3)."""
    d = depth[:, :, ::stride, ::stride]
    Ks = K.clone().to(d.dtype)
    Ks[:, :2, :2] /= stride
    Ks[:, :2, 2] = Ks[:, :2, 2] / stride  # pixel centres at integer coordinates in both grids
    V = backproject_depth(Ks, d)  # B,h,w,3
    z = d[:, 0]
    ok = z > 0
    dx = V[:, 1:-1, 2:] - V[:, 1:-1, :-2]
    dy = V[:, 2:, 1:-1] - V[:, :-2, 1:-1]
    n = torch.linalg.cross(dx, dy)
    n = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(1e-12)
    zc = z[:, 1:-1, 1:-1]
    near = lambda a: (a > 0) & ((a - zc).abs() <= max_step * zc)  # noqa: E731
    good = ok[:, 1:-1, 1:-1] & near(z[:, 1:-1, 2:]) & near(z[:, 1:-1, :-2]) & near(z[:, 2:, 1:-1]) & near(z[:, :-2, 1:-1])
    N = torch.zeros_like(V)
    N[:, 1:-1, 1:-1] = n
    valid = torch.zeros_like(ok)
    valid[:, 1:-1, 1:-1] = good
    return V, N, valid, Ks


class DenseMap:
    """B dense point maps of the keyframes' depth and the alignment of a camera to them.

    Args:
        voxel_size: map voxel edge, metres.
        stride: the depth is used at every ``stride``-th pixel (map and alignment).
        max_points: at most this many map points per alignment (the visible ones, evenly thinned).
        iterations: Gauss-Newton iterations.
        max_distance_m: a pair farther apart along the normal is not used (occluded, or not the same surface).
        huber_m: Huber threshold of the point-to-plane distance.
        sigma_m: the point-to-plane distance's standard deviation at 1 m, x max(1, z^2) (the information's scale).
        prior_m, prior_deg: the tracker's camera as a prior, standard deviations of its translation and rotation.
        min_pairs: fewer pairs at the end: no correction.
        max_correction_m, max_correction_deg: a larger correction is not applied (a wrong fit, not drift).
        max_depth: depth beyond this (metres) enters neither the map nor the alignment.
    """

    def __init__(
        self,
        *,
        voxel_size: float = 0.02,
        stride: int = 4,
        max_points: int = 6000,
        iterations: int = 8,
        max_distance_m: float = 0.05,
        huber_m: float = 0.01,
        sigma_m: float = 0.005,
        prior_m: float = 0.05,
        prior_deg: float = 3.0,
        min_pairs: int = 500,
        max_correction_m: float = 0.1,
        max_correction_deg: float = 5.0,
        max_depth: float = 4.0,
    ) -> None:
        if voxel_size <= 0 or stride < 1 or iterations < 1 or max_points < 1:
            raise ValueError(f"DenseMap: need voxel_size > 0, stride >= 1, iterations >= 1, max_points >= 1; got "
                             f"{voxel_size}, {stride}, {iterations}, {max_points}")  # fmt: skip
        self.voxel_size, self.stride, self.max_points, self.iterations = voxel_size, stride, max_points, iterations
        self.max_distance_m, self.huber_m, self.sigma_m = max_distance_m, huber_m, sigma_m
        self.prior_m, self.prior_deg, self.min_pairs = prior_m, prior_deg, min_pairs
        self.max_correction_m, self.max_correction_deg, self.max_depth = max_correction_m, max_correction_deg, max_depth
        self.map: VoxelPointMap | None = None

    def reset(self, B: int, device: torch.device | str = "cpu") -> None:
        """Empty maps for B sequences."""
        self.map = VoxelPointMap(voxel_size=self.voxel_size, batch_size=B, device=device)

    def add(self, depth: Tensor, K: Tensor, T_world_color: Tensor, mask: Tensor) -> None:
        """Fuse the registered depth (B, 1, H, W) of the sequences in ``mask`` (B,), seen through the colour
        intrinsics K (B, 3, 3) from ``T_world_color`` (B, 4, 4), into their maps."""
        if self.map is None or not bool(mask.any()):
            return
        d = depth[:, :, :: self.stride, :: self.stride].double()
        Ks = K.double().clone()
        Ks[:, :2] /= self.stride
        V = backproject_depth(Ks, d).flatten(1, 2)  # B,hw,3
        ok = (V[..., 2] > 0) & (V[..., 2] <= self.max_depth) & mask[:, None]
        world = transform_points(T_world_color.double(), V)
        b = torch.arange(len(mask), device=ok.device)[:, None].expand_as(ok)
        dev = self.map.device
        self.map.add(world[ok].to(dev), torch.zeros_like(world[ok]).to(dev), b[ok].to(dev))

    def align(self, depth: Tensor, K: Tensor, T_world_color: Tensor, mask: Tensor) -> Alignment:
        """The colour cameras ``T_world_color`` (B, 4, 4) of the sequences in ``mask`` (B,) aligned to their maps
        through the current registered depth (B, 1, H, W) and colour intrinsics K (B, 3, 3)."""
        B = len(mask)
        T_out = T_world_color.double().clone()
        applied = torch.zeros(B, dtype=torch.bool, device=mask.device)
        pairs = torch.zeros(B, dtype=torch.long, device=mask.device)
        info = torch.zeros(B, 6, 6, dtype=torch.float64, device=mask.device)
        if self.map is None or not bool(mask.any()):
            return Alignment(T_out, applied, pairs, info)
        V, N, valid, Ks = surface(depth.double(), K.double(), self.stride)
        for b in mask.nonzero().squeeze(1).tolist():
            world = self.map.points(b, ordered=False).xyz.to(V.device)
            if len(world) < self.min_pairs:
                continue
            T_cw, n_pairs, H = self._fit(world, V[b], N[b], valid[b], Ks[b], T_inv(T_out[b]))
            delta = T_cw @ T_out[b]  # the correction, camera side
            ok = (
                n_pairs >= self.min_pairs
                and float(delta[:3, 3].norm()) <= self.max_correction_m
                and float(rotation_angle(delta[None, :3, :3])[0]) <= self.max_correction_deg * torch.pi / 180
            )
            pairs[b], info[b] = n_pairs, H
            if ok:
                T_out[b], applied[b] = T_inv(T_cw), True
        return Alignment(T_out, applied, pairs, info)

    def _fit(self, world: Tensor, V: Tensor, N: Tensor, valid: Tensor, K: Tensor,
             T_cw0: Tensor) -> tuple[Tensor, int, Tensor]:  # fmt: skip
        """Gauss-Newton of the world-to-camera pose from ``T_cw0`` (4, 4): (pose, pairs used, information)."""
        h, w = valid.shape
        world = world[:: max(1, len(world) // (8 * self.max_points))]  # evenly thinned before the visibility test
        p = transform_points(T_cw0.float(), world.float())
        fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
        x, y, z = p.unbind(-1)
        u, v = fx * x + cx * z, fy * y + cy * z  # the pixel times z: no division for the test
        seen = (z > 0.1) & (z <= self.max_depth) & (u > -0.5 * z) & (v > -0.5 * z) & (u < (w - 0.5) * z)
        world = world[seen & (v < (h - 0.5) * z)]
        if len(world) > self.max_points:  # evenly thinned, deterministic
            world = world[torch.linspace(0, len(world) - 1, self.max_points, device=world.device).long()]
        prior = torch.tensor([1 / self.prior_m**2] * 3 + [1 / (self.prior_deg * torch.pi / 180) ** 2] * 3,
                             dtype=torch.float64, device=world.device).diag()  # fmt: skip
        T_cw, xi = T_cw0.clone(), torch.zeros(6, dtype=torch.float64, device=world.device)
        H = torch.zeros(6, 6, dtype=torch.float64, device=world.device)
        n_pairs = 0
        for _ in range(self.iterations):
            p = torch.addmm(T_cw[:3, 3], world, T_cw[:3, :3].T)
            z = p[:, 2].clamp_min(1e-6)
            u = (p[:, 0] / z * K[0, 0] + K[0, 2]).round().long()
            v = (p[:, 1] / z * K[1, 1] + K[1, 2]).round().long()
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h) & (p[:, 2] > 0.1)
            idx = (v.clamp(0, h - 1) * w + u.clamp(0, w - 1))
            q, n, ok = V.reshape(-1, 3)[idx], N.reshape(-1, 3)[idx], valid.reshape(-1)[idx] & inside
            r = ((p - q) * n).sum(-1)
            ok &= (r.abs() <= self.max_distance_m) & ((p - q).norm(dim=-1) <= 2 * self.max_distance_m)
            n_pairs = int(ok.sum())
            if n_pairs < 6:
                break
            sig = self.sigma_m * p[:, 2].square().clamp_min(1.0)
            wgt = torch.where(r.abs() <= self.huber_m, 1.0, self.huber_m / r.abs().clamp_min(1e-12)) * ok / sig**2
            J = torch.cat([n, torch.linalg.cross(p, n)], -1)  # d r / d xi = n^T [I, -[p]x], left perturbation
            H = (J * wgt[:, None]).T @ J
            g = (J * wgt[:, None]).T @ r
            step = -torch.linalg.solve(H + prior, g + prior @ xi)
            xi = xi + step
            T_cw = se3_exp(step[None])[0] @ T_cw
        return T_cw, n_pairs, H
