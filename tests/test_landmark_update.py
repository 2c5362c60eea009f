"""Landmarks as filter measurements (torchtrack/estimators/landmark_update.py): the frame's update redone with them;
oracles on exact synthetic features and landmarks."""

from __future__ import annotations

import torch

from torchtrack.estimators.backends import EKFBackend, Observation, ekf_frame
from torchtrack.estimators.landmark_update import FrameFusion, joint_update, landmark_variances, mean_variances
from torchtrack.filter import FusionEKF, NoiseScale, Variances
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
    be = EKFBackend(FusionEKF(**ekf), gate=None, refit=None, noise_scale=False)  # the filter of ekf_frame's defaults
    be.reset(T0, torch.ones(T0.shape[0], dtype=torch.bool))
    return be


def _var(C, B=2):
    return Variances(torch.full((B, C), 0.25, dtype=F64), torch.full((B, C), 2e-6, dtype=F64))


def _obs(points_obj, X_cam, pixels, valid, K, T_cd, dt=1 / 30):
    B = valid.shape[0]
    return Observation(torch.full((B,), dt, dtype=F64), points_obj, X_cam, pixels, valid, K, T_cd)


def _frame(T0, T_world_obj, world, X_cam, pixels, K, T_cd, frame_valid, **ekf):
    """A back end after one frame whose features are the first 10 points (``frame_valid`` (B, 10)), and the
    :class:`FrameFusion` it keeps; the landmarks are the other 20 points (their model points from the world)."""
    be = _backend(T0, **ekf)
    points_obj = transform_points(T_inv(T_world_obj), world)
    obs = _obs(points_obj[:, :10], X_cam[:, :10], pixels[:, :10], frame_valid, K, T_cd)
    before = be.snapshot()
    be.step(obs, _var(10), active=torch.ones(2, dtype=torch.bool))
    landmarks = _obs(points_obj[:, 10:], X_cam[:, 10:], pixels[:, 10:], torch.ones(2, 20, dtype=torch.bool), K, T_cd)
    return be, FrameFusion(before, obs, _var(10), torch.ones(2, dtype=torch.bool)), landmarks


def test_joint_update_is_one_update_of_features_and_landmarks():
    """The frame redone with the landmarks equals one :func:`ekf_frame` of all 30 points from the frame's start (the
    same computation: exactly), and with exact points, a prior 1 cm / 0.6 deg off with a 1 m / 1 rad deviation and an
    iterated EKF, it is the truth."""
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    T0 = se3_exp(torch.tensor([0.01, -0.01, 0.005, 0.01, 0.0, -0.005], dtype=F64)).expand(2, 4, 4) @ T_true
    ekf = dict(init_sigma_angle=1.0, init_sigma_trans=1.0, init_sigma_ang_vel=1e-6, init_sigma_lin_vel=1e-6,
               iterations=5)  # fmt: skip
    be, fusion, landmarks = _frame(T0, T_world_obj, world, X_cam, pixels, K, T_cd, torch.ones(2, 10, dtype=torch.bool),
                                   **ekf)  # fmt: skip
    out = joint_update(be, fusion, landmarks, _var(20))
    assert bool(out.updated.all()) and bool(out.used.all())
    points_obj = transform_points(T_inv(T_world_obj), world)
    alone = ekf_frame(FusionEKF(**ekf), fusion.before.state, _obs(points_obj, X_cam, pixels, torch.ones(2, 30,
                      dtype=torch.bool), K, T_cd), _var(30), gate=None, refit=None)  # fmt: skip
    assert torch.equal(out.T_cam_obj, alone.T_cam_obj) and torch.equal(be.state.cov, alone.cov)
    err = se3_log(out.T_cam_obj @ T_inv(T_true))
    assert err.abs().max() < 1e-6, err


def test_landmarks_weigh_against_the_features_by_their_variances():
    """Features exact under one pose, landmarks exact under another 2 cm away, both with the same variance: the
    update lands between them (more than 1 mm from either); with the landmarks' variance 1e6 x larger it is the features' pose (within 1e-6 m), and
    1e6 x smaller the landmarks' (the prior is vague, the EKF iterated)."""
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    shift = se3_exp(torch.tensor([0.02, 0, 0, 0, 0, 0], dtype=F64)).expand(2, 4, 4)
    T_lm = shift @ T_true  # the landmarks' world positions agree with this pose instead
    world = torch.cat([world[:, :10], transform_points(T_world_obj @ T_inv(T_lm), X_cam[:, 10:])], 1)
    ekf = dict(init_sigma_angle=1.0, init_sigma_trans=1.0, init_sigma_ang_vel=1e-6, init_sigma_lin_vel=1e-6,
               iterations=5)  # fmt: skip
    ones = torch.ones(2, 10, dtype=torch.bool)
    poses = []
    for factor in (1e6, 1.0, 1e-6):
        be, fusion, landmarks = _frame(T_true, T_world_obj, world, X_cam, pixels, K, T_cd, ones, **ekf)
        var = Variances(*(v * factor for v in _var(20)))
        poses.append(joint_update(be, fusion, landmarks, var).T_cam_obj)
    assert se3_log(poses[0] @ T_inv(T_true)).abs().max() < 1e-6
    assert se3_log(poses[2] @ T_inv(T_lm)).abs().max() < 1e-6
    for end in (T_true, T_lm):
        gap = poses[1][:, :3, 3] - end[:, :3, 3]
        assert bool((torch.linalg.vector_norm(gap, dim=-1) > 1e-3).all()), gap


def test_sequences_without_landmarks_keep_the_frames_update():
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    T0 = se3_exp(torch.tensor([0.01, 0, 0, 0, 0, 0], dtype=F64)).expand(2, 4, 4) @ T_true
    be, fusion, landmarks = _frame(T0, T_world_obj, world, X_cam, pixels, K, T_cd, torch.ones(2, 10, dtype=torch.bool))
    be.noise = NoiseScale()  # the running scale too: sequence 1's stays the frame's
    be.scale_state = be.noise.initial(2)._replace(scale=torch.tensor([[2.0, 3.0], [4.0, 5.0]], dtype=F64))
    after = be.snapshot()
    landmarks.valid[1] = False  # sequence 1 found none: its state stays the frame's update, bit for bit
    out = joint_update(be, fusion, landmarks, _var(20))
    assert out.updated.tolist() == [True, False] and not bool(out.used[1].any())
    assert torch.equal(be.state.mean[1], after.state.mean[1]) and torch.equal(be.state.cov[1], after.state.cov[1])
    assert torch.equal(out.T_cam_obj[1], after.state.T_cam_obj[1])
    assert torch.equal(be.scale_state.scale[1], after.noise.scale[1]) and torch.equal(be.scale_state.dof[1],
                                                                                      after.noise.dof[1])  # fmt: skip
    assert not torch.equal(out.T_cam_obj[0], after.state.T_cam_obj[0])


def test_uncertain_landmarks_move_nothing():
    """Landmarks known to +-1 km (variance 1e6 m^2, 1e12 px^2): the joint update is the frame's own within 1e-8."""
    T_world_obj, T_true, world, X_cam, pixels, K, T_cd = _setup()
    T0 = se3_exp(torch.tensor([0.01, 0, 0, 0, 0, 0], dtype=F64)).expand(2, 4, 4) @ T_true
    be, fusion, landmarks = _frame(T0, T_world_obj, world, X_cam, pixels, K, T_cd, torch.ones(2, 10, dtype=torch.bool))
    frame_pose = be.state.T_cam_obj
    var = Variances(torch.full((2, 20), 1e12, dtype=F64), torch.full((2, 20), 1e6, dtype=F64))
    out = joint_update(be, fusion, landmarks, var)
    assert se3_log(out.T_cam_obj @ T_inv(frame_pose)).abs().max() < 1e-8


def test_landmark_variances_are_the_frames_mean():
    """A landmark takes the mean variances of the frame's valid features, as the model's own points."""
    X = torch.tensor([[[0.0, 0.0, 2.0], [0.1, 0.0, 4.0]]], dtype=F64)
    var = Variances(torch.tensor([[1.0, 3.0, 100.0]], dtype=F64), torch.tensor([[1e-6, 3e-6, 1.0]], dtype=F64))
    frame_valid = torch.tensor([[True, True, False]])  # the mean over the valid features: 2 px^2, 2e-6 m^2
    mean = mean_variances(var, frame_valid)
    torch.testing.assert_close(mean, torch.tensor([[2.0, 2e-6]], dtype=F64))
    out = landmark_variances(X, mean)
    assert torch.equal(out.var_pix, torch.full((1, 2), 2.0, dtype=F64))
    assert torch.equal(out.var_xyz, torch.full((1, 2), 2e-6, dtype=F64))
