"""Landmarks as filter measurements (torchtrack/estimators/landmark_update.py): oracles on exact synthetic landmarks."""

from __future__ import annotations

import math

import torch

from torchtrack.estimators.backends import EKFBackend
from torchtrack.estimators.landmark_update import landmark_update, landmark_variances, mean_variances
from torchtrack.filter import FusionEKF, Variances
from torchtrack.geometry import T_inv, make_T, project, se3_exp, se3_log, so3_exp, transform_points

F64 = torch.float64


def _setup(B=2, C=30, seed=0):
    """Model frames, the true object pose and C landmarks seen exactly (3D in the depth camera, colour pixels)."""
    g = torch.Generator().manual_seed(seed)
    T_world_obj = se3_exp(torch.cat([0.2 * torch.randn(B, 3, generator=g, dtype=F64),
                                     0.1 * torch.randn(B, 3, generator=g, dtype=F64)], -1))  # fmt: skip
    T_true = make_T(
        so3_exp(0.05 * torch.randn(B, 3, generator=g, dtype=F64)), torch.tensor([0.0, 0.0, 2.0], dtype=F64).expand(B, 3)
    )
    X_cam = torch.cat(
        [torch.rand(B, C, 2, generator=g, dtype=F64) - 0.5, 1.5 + torch.rand(B, C, 1, generator=g, dtype=F64)], -1
    )
    world = transform_points(T_world_obj @ T_inv(T_true), X_cam)  # the landmarks, where the true pose sees X_cam
    K = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], dtype=F64).expand(B, 3, 3)
    T_cd = make_T(torch.eye(3, dtype=F64), torch.tensor([0.025, 0, 0], dtype=F64)).expand(B, 4, 4)
    pixels = project(K, transform_points(T_cd, X_cam))
    return T_world_obj, T_true, world, X_cam, pixels, K, T_cd


def _backend(T0, **ekf):
    be = EKFBackend(FusionEKF(**ekf), gate=None, refit=None)
    be.reset(T0, torch.ones(T0.shape[0], dtype=torch.bool))
    return be


def _var(C, B=2):
    return Variances(torch.full((B, C), 0.25, dtype=F64), torch.full((B, C), 2e-6, dtype=F64))


def test_exact_landmarks_pull_an_uncertain_pose_onto_the_truth():
    """Prior 1 cm / 0.6 deg off with a 1 m / 1 rad standard deviation, iterated EKF: the landmarks alone decide."""
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    T0 = se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.005], dtype=F64)).expand(2, 4, 4) @ T_true
    be = _backend(T0, init_sigma_angle=1.0, init_sigma_trans=1.0, iterations=5)
    valid = torch.ones(2, 30, dtype=torch.bool)
    out = landmark_update(be, T0, T_world_obj, world, X_cam, pixels, valid, _var(30), K, T_cd)
    assert bool(out.updated.all()) and bool(out.used.all())
    err = se3_log(out.T_cam_obj @ T_inv(T_true))
    assert err.abs().max() < 1e-6, err  # the prior's pull: 1e-6 m^2 / 1 m^2 of the 1 cm offset ~ 1e-8


def test_uncertain_positions_move_nothing_and_masks_keep_the_state():
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    T0 = se3_exp(torch.tensor([0.01, 0, 0, 0, 0, 0], dtype=F64)).expand(2, 4, 4) @ T_true
    be = _backend(T0)
    valid = torch.ones(2, 30, dtype=torch.bool)
    valid[1] = False  # sequence 1 found none: its filter state is not touched
    before = be.state.mean.clone(), be.state.cov.clone()
    frame = Variances(torch.full((2, 5), 0.25, dtype=F64), torch.full((2, 5), 1e-6, dtype=F64))
    var = landmark_variances(
        X_cam, torch.full((2, 30), 1e6, dtype=F64), mean_variances(frame, torch.ones(2, 5, dtype=torch.bool)), K
    )
    out = landmark_update(be, T0, T_world_obj, world, X_cam, pixels, valid, var, K, T_cd)
    assert (se3_log(out.T_cam_obj @ T_inv(T0)).abs().max()) < 1e-8  # positions known to +-1 km: no information
    assert torch.equal(be.state.mean[1], before[0][1]) and torch.equal(be.state.cov[1], before[1][1])
    assert torch.equal(out.T_cam_obj[1], T0[1]) and out.updated.tolist() == [True, False]


def test_landmark_variances_add_the_position_variance():
    X = torch.tensor([[[0.0, 0.0, 2.0], [0.1, 0.0, 4.0]]], dtype=F64)
    var = Variances(torch.tensor([[1.0, 3.0, 100.0]], dtype=F64), torch.tensor([[1e-6, 3e-6, 1.0]], dtype=F64))
    frame_valid = torch.tensor([[True, True, False]])  # the mean over the valid features: 2 px^2, 2e-6 m^2
    K = torch.tensor([[[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]], dtype=F64)
    mean = mean_variances(var, frame_valid)
    torch.testing.assert_close(mean, torch.tensor([[2.0, 2e-6]], dtype=F64))
    out = landmark_variances(X, torch.tensor([[4e-6, 1e-6]], dtype=F64), mean, K)
    torch.testing.assert_close(out.var_xyz, torch.tensor([[6e-6, 3e-6]], dtype=F64))
    torch.testing.assert_close(out.var_pix, torch.tensor([[2 + 250**2 * 4e-6, 2 + 125**2 * 1e-6]], dtype=F64))
    assert math.isclose(float(out.var_pix[0, 0]), 2.25)
