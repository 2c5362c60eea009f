"""The strided grid of a depth image and its surface: what the dense map (:mod:`torchtrack.map.dense_map`) fuses
and aligns to, and the torch form of what its compiled alignment (csrc/dense.cpp) computes per pixel."""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.geometry import backproject_depth


def grid(depth: Tensor, K: Tensor, stride: int, region: Tensor | None = None, clean: bool = True) -> tuple[Tensor, ...]:
    """Every ``stride``-th pixel of a depth image (B, 1, H, W) seen through K (B, 3, 3): the depth grid (B, h, w), 0
    outside ``region`` (B, 1, H, W) bool (None: everywhere) and, if ``clean``, where there is no depth (0, negative or
    NaN; else, without a region, a view of the image), and its intrinsics (B, 3, 3) float64."""
    d = depth[:, 0, ::stride, ::stride]
    if clean:  # a NaN would reach the torch fit's sums (0 x NaN is NaN)
        d = torch.where(d > 0, d, torch.zeros_like(d))
    if region is not None:
        d = torch.where(region[:, 0, ::stride, ::stride], d, torch.zeros_like(d))
    return d, _strided(K, stride)


def _strided(K: Tensor, stride: int) -> Tensor:
    """The intrinsics (B, 3, 3) float64 of every ``stride``-th pixel: pixel (i, j) of the grid is (i, j) x stride."""
    Ks = K.double().clone()
    Ks[:, :2] /= stride
    return Ks


MAX_STEP = 0.05  # surface(): no normal across a depth step larger than this fraction of the depth


def surface(depth: Tensor, K: Tensor, stride: int, max_step: float = MAX_STEP) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The surface of a depth image (B, 1, H, W) at every ``stride``-th pixel: vertices (B, h, w, 3) in the camera of
    K (B, 3, 3), unit normals (B, h, w, 3) (the cross product of the central differences), valid (B, h, w) (depth
    there and at the four neighbours, none farther than ``max_step`` x z in depth: no normal across a depth step),
    and the intrinsics of the strided grid (B, 3, 3); float64."""
    d, Ks = grid(depth, K, stride)
    V = backproject_depth(Ks, d[:, None].double())  # 0 depth: the origin
    z = V[..., 2]
    n = torch.linalg.cross(V[:, 1:-1, 2:] - V[:, 1:-1, :-2], V[:, 2:, 1:-1] - V[:, :-2, 1:-1])
    zc = z[:, 1:-1, 1:-1]

    def near(a: Tensor) -> Tensor:
        return (a > 0) & ((a - zc).abs() <= max_step * zc)

    N = torch.zeros_like(V)
    N[:, 1:-1, 1:-1] = n / torch.linalg.vector_norm(n, dim=-1, keepdim=True).clamp_min(1e-12)
    valid = torch.zeros_like(z, dtype=torch.bool)
    valid[:, 1:-1, 1:-1] = (zc > 0) & near(z[:, 1:-1, 2:]) & near(z[:, 1:-1, :-2]) & near(z[:, 2:, 1:-1])
    valid[:, 1:-1, 1:-1] &= near(z[:, :-2, 1:-1])
    return V, N, valid, Ks
