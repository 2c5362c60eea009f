"""The pure fusion-EKF back end (estimation.ekf_frame): gradients with respect to the per-feature variances,
the innovation likelihood against a dense oracle, and equality with the stateful filter it replaced."""

import dataclasses
import math

import pytest
import torch
from test_fusion import DT, body, measurements, true_pose

from torchtrack.estimators.backends import EKFBackend, Observation, ekf_frame, innovation_nll
from torchtrack.filter import FusionEKF, PaperWeighting, Variances, WeightingInputs
from torchtrack.filter.fusion import FilterState
from torchtrack.filter.models import measure

F64 = torch.float64


def noisy_observations(frames=3, outlier=True, seed=0):
    """Observations of the moving body at frames 1..frames, with noise, and a gross outlier in feature 0."""
    X, K, T_cd = body(N=12, seed=seed)
    g = torch.Generator().manual_seed(seed)
    B, N = X.shape[:2]
    out = []
    for k in range(1, frames + 1):
        points_d, pixels = measurements(true_pose(k * DT), X, K, T_cd)
        points_d = points_d + 2e-3 * torch.randn(points_d.shape, generator=g, dtype=F64)
        pixels = pixels + 0.5 * torch.randn(pixels.shape, generator=g, dtype=F64)
        if outlier:
            points_d[:, 0] += 0.3
        valid = torch.ones(B, N, dtype=torch.bool)
        valid[1, -3:] = False  # padding in the second sequence
        out.append(Observation(torch.full((B,), DT, dtype=F64), X, points_d, pixels, valid, K, T_cd))
    return out


def rollout(ekf, observations, var_xyz, var_pix, gate=0.999, refit=0.999, with_nll=False):
    """Pose of every frame (F, B, 4, 4) from the ground-truth start; variances (F, B, N)."""
    state = ekf.initial_state(true_pose(0.0))
    poses, nll = [], 0.0
    for obs, vx, vp in zip(observations, var_xyz, var_pix, strict=True):
        out = ekf_frame(ekf, state, obs, Variances(vp, vx), gate=gate, refit=refit, with_nll=with_nll)
        state = FilterState(out.mean, out.cov)
        poses.append(out.T_cam_obj)
        nll = nll + out.nll.sum()
    return torch.stack(poses), nll


def variances(F, B, N, seed=1):
    g = torch.Generator().manual_seed(seed)
    var_xyz = 4e-6 * (1 + torch.rand(F, B, N, generator=g, dtype=F64))
    var_pix = 1.0 + torch.rand(F, B, N, generator=g, dtype=F64)
    return var_xyz, var_pix


@pytest.mark.parametrize("jacobian", ["forward", "analytic"])
def test_gradcheck_one_frame(jacobian):
    """d pose / d variance of one update (gate and refit active, the outlier dropped by them) against finite
    differences, float64."""
    obs = noisy_observations(frames=1)
    var_xyz, var_pix = variances(1, *obs[0].valid.shape)
    ekf = FusionEKF(jacobian=jacobian)

    def pose(log_vx, log_vp):
        return rollout(ekf, obs, log_vx.exp()[None], log_vp.exp()[None])[0][0, :, :3, :]

    assert torch.autograd.gradcheck(pose, (var_xyz[0].log().requires_grad_(), var_pix[0].log().requires_grad_()))


def test_gradcheck_rollout_of_several_frames():
    """Through three frames: the later linearisation points depend on the earlier variances."""
    obs = noisy_observations(frames=3)
    var_xyz, var_pix = variances(3, *obs[0].valid.shape)
    ekf = FusionEKF(jacobian="forward")

    def last_pose(log_vx, log_vp):
        return rollout(ekf, obs, log_vx.exp(), log_vp.exp())[0][-1, :, :3, :]

    assert torch.autograd.gradcheck(last_pose, (var_xyz.log().requires_grad_(), var_pix.log().requires_grad_()))


def test_gradcheck_innovation_nll():
    obs = noisy_observations(frames=2)
    var_xyz, var_pix = variances(2, *obs[0].valid.shape)
    ekf = FusionEKF(jacobian="analytic")

    def nll(log_vx, log_vp):
        return rollout(ekf, obs, log_vx.exp(), log_vp.exp(), with_nll=True)[1]

    assert torch.autograd.gradcheck(nll, (var_xyz.log().requires_grad_(), var_pix.log().requires_grad_()))


def test_innovation_nll_equals_the_dense_gaussian():
    """Oracle: the log-density of the used innovations under the (5N x 5N) S = H P H^T + R, formed densely."""
    obs = noisy_observations(frames=1)[0]
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    ekf = FusionEKF(jacobian="analytic")
    out = ekf_frame(ekf, ekf.initial_state(true_pose(0.0)), obs, Variances(var_pix[0], var_xyz[0]), gate=0.999,
                    with_nll=True)  # fmt: skip
    h, H = ekf.linearize_at(out.prior.mean, obs.points_obj, obs.K, obs.T_color_depth)
    var5 = torch.cat([var_xyz[0][..., None].expand(-1, -1, 3), var_pix[0][..., None].expand(-1, -1, 2)], -1)
    used = torch.cat([out.used_xyz[..., None].expand(-1, -1, 3), out.used_pix[..., None].expand(-1, -1, 2)], -1)
    for b in range(h.shape[0]):
        m = used[b].reshape(-1)
        Hb = H[b].reshape(-1, 12)[m]
        S = Hb @ out.prior.cov[b] @ Hb.T + torch.diag(var5[b].reshape(-1)[m])
        r = out.innovation[b].reshape(-1)[m]
        dense = torch.distributions.MultivariateNormal(torch.zeros_like(r), covariance_matrix=S).log_prob(r)
        torch.testing.assert_close(out.nll[b], -dense, rtol=1e-7, atol=0)  # the dense S mixes 1e-6 and 1: ~1e-8
    assert bool((~out.used_xyz[:, 0]).all())  # the 30 cm outlier was gated
    torch.testing.assert_close(innovation_nll(out.prior.cov, H, out.innovation * 0, var5, used * False),
                               torch.zeros(2, dtype=F64))  # fmt: skip


def test_no_nan_gradients_at_the_floor_zero_tim_and_no_valid_feature():
    """Paper weighting from d_TIM exactly 0 (floored), one sequence with no valid feature at all: the pose and the
    NLL have finite gradients with respect to every input cue and variance."""
    obs = noisy_observations(frames=2)
    B, N = obs[0].valid.shape
    obs = [dataclasses.replace(o, valid=o.valid.clone()) for o in obs]
    for o in obs:
        o.valid[1] = False  # sequence 1: nothing valid
    d_tim = torch.zeros(B, N, dtype=F64, requires_grad=True)  # exactly 0: at the floor
    weighting = PaperWeighting(1.0, 4e-6, depth_var_exponent=4.0)
    ekf = FusionEKF(jacobian="forward")
    state = ekf.initial_state(true_pose(0.0))
    loss = 0.0
    for o in obs:
        var = weighting(WeightingInputs(d_tim, o.points_d[..., 2], o.points_d, o.valid, o.K[:, 0, 0]))
        out = ekf_frame(ekf, state, o, var, gate=0.999, refit=0.999, with_nll=True)
        state = out.prior._replace(mean=out.mean, cov=out.cov)
        loss = loss + out.T_cam_obj[:, :3, 3].sum() + out.nll.sum()
    loss.backward()
    assert torch.isfinite(d_tim.grad).all()
    assert not bool(out.updated[1])  # the empty sequence kept its prediction


def test_batched_equals_looped():
    obs = noisy_observations(frames=2)
    var_xyz, var_pix = variances(2, *obs[0].valid.shape)
    ekf = FusionEKF()
    both = rollout(ekf, obs, var_xyz, var_pix, with_nll=True)[0]
    for b in range(2):
        one = [Observation(*(t[b : b + 1] for t in (o.dt, o.points_obj, o.points_d, o.pixels, o.valid, o.K,
                                                     o.T_color_depth))) for o in obs]  # fmt: skip
        state = ekf.initial_state(true_pose(0.0)[b : b + 1])
        for k, o in enumerate(one):
            out = ekf_frame(ekf, state, o, Variances(var_pix[k, b : b + 1], var_xyz[k, b : b + 1]), gate=0.999,
                            refit=0.999)  # fmt: skip
            state = out.prior._replace(mean=out.mean, cov=out.cov)
        torch.testing.assert_close(out.T_cam_obj[0], both[-1, b], rtol=0, atol=1e-12)


def reference_backend_step(ekf: FusionEKF, obs, var, gate, refit):
    """The stateful back end as it was before the pure function (FusionEKF.reset/predict/update, gate and refit
    written out): the oracle that EKFBackend reproduces."""
    from torchtrack.estimators.backends import _chi2_tests, _keep

    ekf.predict(obs.dt)
    prior = (ekf.mean, ekf.cov)
    h, H = ekf.linearize(obs.points_obj, obs.K, obs.T_color_depth)
    z = torch.cat([obs.points_d, obs.pixels], -1).to(F64)
    var5 = torch.cat([var.var_xyz[..., None].expand(-1, -1, 3), var.var_pix[..., None].expand(-1, -1, 2)], -1).double()
    xyz = pix = obs.valid
    if gate is not None:
        s = var5 + torch.einsum("bnms,bst,bnmt->bnm", H, ekf.cov, H)
        xyz, pix = _keep(xyz, pix, *_chi2_tests(z, h, s, gate))

    def update(xyz, pix):
        ekf.update(obs.points_obj, obs.points_d, obs.pixels, xyz | pix, var.var_xyz, var.var_pix, obs.K,
                   obs.T_color_depth, valid_xyz=xyz, valid_pix=pix, linearization=(h, H))  # fmt: skip

    update(xyz, pix)
    if refit is not None:
        h_post = measure(ekf.mean, obs.points_obj.double(), obs.K.double(), obs.T_color_depth.double())
        xyz_new, pix_new = _keep(xyz, pix, *_chi2_tests(z, h_post, var5, refit))
        if bool(((xyz_new != xyz) | (pix_new != pix)).any()):
            ekf.mean, ekf.cov = prior
            update(xyz_new, pix_new)
    return ekf.T_cam_obj


def test_backend_equals_the_stateful_filter_over_a_rollout():
    obs = noisy_observations(frames=4)
    var_xyz, var_pix = variances(4, *obs[0].valid.shape)
    backend, ref = EKFBackend(FusionEKF(), gate=0.999, refit=0.999), FusionEKF()
    everyone = torch.ones(2, dtype=torch.bool)
    backend.reset(true_pose(0.0), everyone)
    ref.reset(true_pose(0.0))
    for k, o in enumerate(obs):
        var = Variances(var_pix[k], var_xyz[k])
        torch.testing.assert_close(
            backend.step(o, var).T_cam_obj, reference_backend_step(ref, o, var, 0.999, 0.999), rtol=0, atol=0
        )
    assert math.isfinite(float(backend.state.cov.sum()))
