"""Observations with a known-optimal weighting: the oracle that learned weighting must recover.

:func:`oracle_windows` draws B windows of a rigid body moving smoothly in front of the camera, observed through
eqs. (6)-(7) with Gaussian noise whose variance is a known function of one cue per feature:

* 3D noise grows with depth: ``var_xyz = xyz_var_at_1m * z^4`` (a Kinect-like sigma ~ z^2);
* a flagged fraction of the features (the cue ``lk_residual`` = ``flag_cue`` there, 0 elsewhere) has
  ``flag_var_ratio`` times the pixel variance of the others.

The true variances come with the windows, so the filter given them (:func:`true_variances`) is the optimum a
learned weighting can reach; the class ratios (flagged / unflagged pixel variance, far / near 3D variance) are
what a trained model must recover.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.filter.cues import CUE_INDEX, CUE_NAMES
from torchtrack.filter.weighting import Variances, WeightingInputs
from torchtrack.geometry import intrinsics_matrix, make_T, project, so3_exp, transform_points
from torchtrack.learn.rollout import Windows

F64 = torch.float64


class OracleWindows(NamedTuple):
    """windows: the :class:`Windows`; var_pix, var_xyz: (T, B, N) the true noise variances; flagged: (B, N) bool."""

    windows: Windows
    var_pix: Tensor
    var_xyz: Tensor
    flagged: Tensor


def oracle_windows(
    B: int = 32,
    T: int = 4,
    N: int = 40,
    *,
    seed: int = 0,
    pix_var: float = 0.25,
    flag_var_ratio: float = 400.0,
    flag_fraction: float = 0.1,
    flag_cue: float = 0.2,
    xyz_var_at_1m: float = 4e-6,
    dt: float = 1 / 30,
) -> OracleWindows:
    """B windows of T frames of N features (see the module docstring). Depths span about 0.8-3 m."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    def randn(*shape):
        return torch.randn(*shape, generator=g, dtype=F64)

    # model points: a slab from 0.8 to 3 m deep, seen by a 525 px camera; object frame at their centroid
    z = 0.8 + 2.2 * rand(B, N)
    xy = (rand(B, N, 2) - 0.5) * 0.8 * z[..., None]
    pts0 = torch.cat([xy, z[..., None]], -1)
    centroid = pts0.mean(1, keepdim=True)
    X = pts0 - centroid
    T0 = make_T(torch.eye(3, dtype=F64, device="cpu").expand(B, 3, 3), centroid[:, 0])
    # smooth motion: constant twist per window (small), in the camera frame about the centroid
    omega = 0.3 * randn(B, 3)  # rad/s
    vel = 0.15 * randn(B, 3)  # m/s
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=F64).expand(B, 3, 3).clone()
    T_cd = torch.eye(4, dtype=F64, device="cpu").expand(B, 4, 4).clone()
    flagged = rand(B, N) < flag_fraction

    def pose(t: float) -> Tensor:
        return make_T(so3_exp(omega * t), centroid[:, 0] + vel * t)

    poses = torch.stack([pose(k * dt) for k in range(1, T + 1)])  # T,B,4,4
    points_d, pixels, var_xyz, var_pix = [], [], [], []
    for k in range(T):
        P = transform_points(poses[k], X)
        v3 = xyz_var_at_1m * P[..., 2] ** 4
        v2 = torch.where(flagged, pix_var * flag_var_ratio, torch.full_like(v3, pix_var))
        pix = project(K, P)
        points_d.append(P + v3.sqrt()[..., None] * randn(B, N, 3))
        pixels.append(pix + v2.sqrt()[..., None] * randn(B, N, 2))
        var_xyz.append(v3)
        var_pix.append(v2)
    points_d, pixels = torch.stack(points_d), torch.stack(pixels)
    cues = torch.zeros(T, B, N, len(CUE_NAMES), device="cpu")
    cues[..., CUE_INDEX["lk_residual"]] = torch.where(flagged, flag_cue, 0.0).float()
    cues[..., CUE_INDEX["depth"]] = points_d[..., 2].float()
    win = Windows(
        start_T_cam_obj=T0,
        dt=torch.full((T, B), dt, dtype=F64, device="cpu"),
        points_obj=X.expand(T, B, N, 3).clone(),
        points_d=points_d,
        pixels=pixels,
        valid=torch.ones(T, B, N, dtype=torch.bool, device="cpu"),
        has_depth=torch.ones(T, B, N, dtype=torch.bool, device="cpu"),
        cues=cues,
        K=K,
        T_color_depth=T_cd,
        focal=K[:, 0, 0].clone(),
        reselected=torch.zeros(T, B, dtype=torch.bool, device="cpu"),
        model_T_cam_obj=torch.eye(4, dtype=F64, device="cpu").expand(T, B, 4, 4).clone(),
        T_cam_obj_gt=poses,
        gt_valid=torch.ones(T, B, dtype=torch.bool, device="cpu"),
        start_noise=torch.ones(B, 2, dtype=F64, device="cpu"),
        start_noise_dof=torch.zeros(B, 2, dtype=F64, device="cpu"),
    )
    return OracleWindows(win, torch.stack(var_pix), torch.stack(var_xyz), flagged)


class TrueVariances:
    """A 'weighting' that returns the true variances of frame t of an :class:`OracleWindows` (call order = frames)."""

    def __init__(self, oracle: OracleWindows) -> None:
        self.oracle, self.t = oracle, 0

    def __call__(self, inputs: WeightingInputs) -> Variances:
        t = self.t % self.oracle.var_pix.shape[0]
        self.t += 1
        return Variances(self.oracle.var_pix[t], self.oracle.var_xyz[t])


def class_ratios(var_pix: Tensor, var_xyz: Tensor, flagged: Tensor, depth: Tensor) -> dict[str, float]:
    """Geometric-mean variance ratios: flagged / unflagged pixel, and the 3D variance's power law in depth (the
    slope of log var_xyz against log z, 4 for var ~ z^4). var_*: (B, N); flagged, depth: (B, N)."""
    lp = var_pix.log()
    ratio = math.exp(float(lp[flagged].mean() - lp[~flagged].mean()))
    lz, lv = depth.log().reshape(-1), var_xyz.log().reshape(-1)
    lz, lv = lz - lz.mean(), lv - lv.mean()
    slope = float((lz * lv).sum() / (lz * lz).sum())
    return {"pix_flag_ratio": ratio, "xyz_depth_exponent": slope}
