"""The pure fusion-EKF back end (estimation.ekf_frame): gradients with respect to the per-feature variances,
the innovation likelihood against a dense oracle, the gate and the refit against chi-square tests written out here
(scipy's quantiles, per feature), and equality with the stateful filter it replaced."""

import dataclasses
import math

import pytest
import torch
from scipy.stats import chi2
from test_fusion import DT, body, measurements, true_pose

from torchtrack.filter import FusionEKF, PaperWeighting, Variances, WeightingInputs
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.frame import Observation, ekf_frame, innovation_nll
from torchtrack.filter.models import measure_pose

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
        state = out.posterior
        poses.append(out.T_cam_obj)
        nll = nll + out.nll.sum()
    return torch.stack(poses), nll


def variances(F, B, N, seed=1):
    g = torch.Generator().manual_seed(seed)
    var_xyz = 4e-6 * (1 + torch.rand(F, B, N, generator=g, dtype=F64))
    var_pix = 1.0 + torch.rand(F, B, N, generator=g, dtype=F64)
    return var_xyz, var_pix


@pytest.mark.slow
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


@pytest.mark.slow
@pytest.mark.parametrize("state", ["se3", "euler"])
def test_gradcheck_rollout_of_several_frames(state):
    """Through three frames: the later linearisation points depend on the earlier variances (and, in the SE(3)
    state, the nominal poses on the earlier injections)."""
    obs = noisy_observations(frames=3)
    var_xyz, var_pix = variances(3, *obs[0].valid.shape)
    ekf = FusionEKF(jacobian="forward", state=state)

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
    h, H = ekf.linearize_at(out.prior, obs.points_obj, obs.K, obs.T_color_depth)
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
        state = out.posterior
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
            state = out.posterior
        torch.testing.assert_close(out.T_cam_obj[0], both[-1, b], rtol=0, atol=1e-12)


def chi2_gate(z, h, s, valid, p):
    """The gate's decisions by its definition (ekf_frame's docstring), one feature at a time: the 3D point is kept
    when ``sum_xyz (z - h)^2 / s`` is below the chi-square quantile ``p`` with 3 dof, the pixel when its 2-dof sum
    is below that quantile with 2 dof OR its 3D point is kept (a pixel is dropped only together with its 3D point).
    Quantiles from scipy. z, h, s (B, N, 5); valid (B, N) -> (keep_xyz, keep_pix) (B, N) bool."""
    q3, q2 = float(chi2.ppf(p, 3)), float(chi2.ppf(p, 2))
    keep_xyz, keep_pix = torch.zeros_like(valid), torch.zeros_like(valid)
    for b in range(valid.shape[0]):
        for n in range(valid.shape[1]):
            if valid[b, n]:
                d2 = ((z[b, n] - h[b, n]) ** 2 / s[b, n]).tolist()
                keep_xyz[b, n] = sum(d2[:3]) < q3
                keep_pix[b, n] = sum(d2[3:]) < q2 or bool(keep_xyz[b, n])
    return keep_xyz, keep_pix


def reference_backend_step(ekf: FusionEKF, state, obs, var, gate, refit):
    """The back end's frame written out from the filter's steps (FusionEKF.predicted / linearize_at / updated /
    injected, gate and refit by :func:`chi2_gate`): the oracle that EKFBackend reproduces. Returns the posterior
    state, the pose and how many measurements the gate and the refit dropped."""
    prior = ekf.predicted(state, obs.dt)
    h, H = ekf.linearize_at(prior, obs.points_obj, obs.K, obs.T_color_depth)
    z = torch.cat([obs.points_d, obs.pixels], -1).to(F64)
    var5 = torch.cat([var.var_xyz[..., None].expand(-1, -1, 3), var.var_pix[..., None].expand(-1, -1, 2)], -1).double()
    xyz = pix = obs.valid
    if gate is not None:
        s = var5 + torch.diagonal(H @ prior.cov[:, None] @ H.transpose(-1, -2), dim1=-2, dim2=-1)  # diag(H P- H^T) + R
        xyz, pix = chi2_gate(z, h, s, obs.valid, gate)
    gated = int((obs.valid & ~xyz).sum())

    def update(xyz, pix):
        return ekf.injected(prior, ekf.updated(prior, obs.points_obj, obs.points_d, obs.pixels, xyz, pix, var.var_xyz,
                                               var.var_pix, obs.K, obs.T_color_depth, linearization=(h, H)))  # fmt: skip

    post = update(xyz, pix)
    refitted = 0
    if refit is not None:
        h_post = measure_pose(post.T_cam_obj, obs.points_obj.double(), obs.K.double(), obs.T_color_depth.double())
        ok_xyz, ok_pix = chi2_gate(z, h_post, var5, xyz | pix, refit)
        xyz_new, pix_new = xyz & ok_xyz, pix & ok_pix
        if bool(((xyz_new != xyz) | (pix_new != pix)).any()):
            refitted = int((xyz & ~xyz_new).sum())
            post = update(xyz_new, pix_new)
    return post, post.T_cam_obj, gated, refitted


def test_gate_keeps_what_the_chi_square_test_keeps():
    """ekf_frame's gate (refit off) against :func:`chi2_gate` on the innovation at the prediction: h from eqs. (6)-(7)
    written out (test_fusion.measurements) at the prior pose, S's diagonal from H P- H^T formed per feature. Known
    answers by construction: a 30 cm 3D outlier loses its 3D point but keeps its pixel; a 40 px pixel outlier with
    a good 3D point keeps both; a feature wrong in both loses both; every other feature is kept."""
    obs = noisy_observations(frames=1, outlier=False)[0]
    obs.points_d[:, 0] += 0.3
    obs.pixels[:, 1] += 40.0
    obs.points_d[:, 2] += 0.3
    obs.pixels[:, 2] += 40.0
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    var = Variances(var_pix[0], var_xyz[0])
    ekf = FusionEKF(jacobian="analytic")
    out = ekf_frame(ekf, ekf.initial_state(true_pose(0.0)), obs, var, gate=0.999, refit=None)
    T_prior = out.prior.T_cam_obj
    points_d, pixels = measurements(T_prior, obs.points_obj, obs.K, obs.T_color_depth)
    h = torch.cat([points_d, pixels], -1)
    _, H = ekf.linearize_at(out.prior, obs.points_obj, obs.K, obs.T_color_depth)
    var5 = torch.cat([var_xyz[0][..., None].expand(-1, -1, 3), var_pix[0][..., None].expand(-1, -1, 2)], -1)
    s = torch.stack([
        torch.stack([torch.diagonal(H[b, n] @ out.prior.cov[b] @ H[b, n].T) for n in range(H.shape[1])])
        for b in range(H.shape[0])
    ]) + var5  # fmt: skip
    z = torch.cat([obs.points_d, obs.pixels], -1)
    keep_xyz, keep_pix = chi2_gate(z, h, s, obs.valid, 0.999)
    assert torch.equal(out.used_xyz, keep_xyz) and torch.equal(out.used_pix, keep_pix)
    expected_xyz, expected_pix = obs.valid.clone(), obs.valid.clone()
    expected_xyz[:, [0, 2]] = False
    expected_pix[:, 2] = False
    assert torch.equal(keep_xyz, expected_xyz) and torch.equal(keep_pix, expected_pix)


def test_gate_threshold_is_the_chi_square_quantile():
    """Known answers at the threshold: each feature's measurement is placed at the prediction h plus an offset whose
    normalised square sum (under S's diagonal) is a chosen fraction of scipy's quantile (3 dof for the 3D point, 2
    for the pixel), 1-10 % either side of it. The float64 sums are exact to ~1e-15: a quantile or a dof off by a
    percent flips a decision."""
    obs = noisy_observations(frames=1, outlier=False)[0]
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    var = Variances(var_pix[0], var_xyz[0])
    ekf = FusionEKF(jacobian="analytic")
    start = ekf.initial_state(true_pose(0.0))
    prior = ekf_frame(ekf, start, obs, var).prior  # the prediction does not depend on the measurements
    points_d, pixels = measurements(prior.T_cam_obj, obs.points_obj, obs.K, obs.T_color_depth)
    _, H = ekf.linearize_at(prior, obs.points_obj, obs.K, obs.T_color_depth)
    var5 = torch.cat([var_xyz[0][..., None].expand(-1, -1, 3), var_pix[0][..., None].expand(-1, -1, 2)], -1)
    s = var5 + torch.diagonal(H @ prior.cov[:, None] @ H.transpose(-1, -2), dim1=-2, dim2=-1)
    r3 = torch.tensor([0.9, 0.97, 0.99, 1.01, 1.03, 1.1, 0.5, 2.0, 0.95, 1.05, 1.2, 2.0], dtype=F64)  # of q(3 dof)
    r2 = torch.tensor([0.5, 2.0, 1.01, 1.01, 0.99, 1.02, 1.02, 0.98, 2.0, 1.05, 0.95, 0.2], dtype=F64)  # of q(2 dof)
    q3, q2 = float(chi2.ppf(0.999, 3)), float(chi2.ppf(0.999, 2))
    sign = torch.tensor([1.0, -1.0, 1.0, -1.0, 1.0], dtype=F64)
    offset = sign * torch.cat([(r3 * q3 / 3)[:, None].expand(-1, 3), (r2 * q2 / 2)[:, None].expand(-1, 2)], -1)
    offset = (offset.abs() * s).sqrt() * offset.sign()  # each component's share of the normalised square sum
    obs = dataclasses.replace(obs, points_d=points_d + offset[..., :3], pixels=pixels + offset[..., 3:])
    out = ekf_frame(ekf, start, obs, var, gate=0.999, refit=None)
    keep_xyz, keep_pix = r3 < 1, (r2 < 1) | (r3 < 1)  # a pixel is dropped only together with its 3D point
    assert torch.equal(out.used_xyz, obs.valid & keep_xyz) and torch.equal(out.used_pix, obs.valid & keep_pix)


def test_refit_drops_what_fails_the_chi_square_test_at_the_updated_pose():
    """The refit (gate off): the update with every valid measurement, then each 3D point's and pixel's residual at
    the UPDATED pose (eqs. (6)-(7) written out) tested against R alone with :func:`chi2_gate` restricted to the used
    measurements; ekf_frame's final masks are those, and its pose is the update without the dropped ones. Known
    answer: a 2 cm 3D outlier (~7 sigma of R; the first update used it) loses its 3D point and nothing else does."""
    obs = noisy_observations(frames=1, outlier=False)[0]
    obs.points_d[:, 0] += 0.02
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    var = Variances(var_pix[0], var_xyz[0])
    ekf = FusionEKF(jacobian="analytic")
    start = ekf.initial_state(true_pose(0.0))
    first = ekf_frame(ekf, start, obs, var, gate=None, refit=None)  # neither gate nor refit: every valid measurement
    assert torch.equal(first.used_xyz, obs.valid) and torch.equal(first.used_pix, obs.valid)
    points_d, pixels = measurements(first.T_cam_obj, obs.points_obj, obs.K, obs.T_color_depth)
    var5 = torch.cat([var_xyz[0][..., None].expand(-1, -1, 3), var_pix[0][..., None].expand(-1, -1, 2)], -1)
    z, h_post = torch.cat([obs.points_d, obs.pixels], -1), torch.cat([points_d, pixels], -1)
    ok_xyz, ok_pix = chi2_gate(z, h_post, var5, obs.valid, 0.999)
    out = ekf_frame(ekf, start, obs, var, gate=None, refit=0.999)
    assert torch.equal(out.used_xyz, obs.valid & ok_xyz) and torch.equal(out.used_pix, obs.valid & ok_pix)
    expected_xyz = obs.valid.clone()
    expected_xyz[:, 0] = False
    assert torch.equal(out.used_xyz, expected_xyz) and torch.equal(out.used_pix, obs.valid)
    masked = ekf.updated(out.prior, obs.points_obj, obs.points_d, obs.pixels, out.used_xyz, out.used_pix, var.var_xyz,
                         var.var_pix, obs.K, obs.T_color_depth)  # fmt: skip
    for a, b in zip(out.posterior, ekf.injected(out.prior, masked), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)  # the same calls: bit for bit


def test_backend_equals_the_stateful_filter_over_a_rollout():
    """EKFBackend against :func:`reference_backend_step` over four frames in which the gate drops the outlier. The
    two take the same arithmetic in other orders (einsum vs matmul): within 1e-12 on poses of order 1 (float64)."""
    obs = noisy_observations(frames=4)
    var_xyz, var_pix = variances(4, *obs[0].valid.shape)
    backend, ref = EKFBackend(FusionEKF(gate=0.999, refit=0.999, noise_scale=False)), FusionEKF()
    everyone = torch.ones(2, dtype=torch.bool)
    backend.reset(true_pose(0.0), everyone)
    state = ref.initial_state(true_pose(0.0))
    gated = 0
    for k, o in enumerate(obs):
        var = Variances(var_pix[k], var_xyz[k])
        state, T_ref, n_gated, _ = reference_backend_step(ref, state, o, var, 0.999, 0.999)
        torch.testing.assert_close(backend.step(o, var).T_cam_obj, T_ref, rtol=0, atol=1e-12)
        gated += n_gated
    assert gated >= 4  # the outlier, in both sequences, at least from the second frame on: the gate was exercised
    assert math.isfinite(float(backend.state.cov.sum()))


def test_innovation_nll_of_a_near_singular_prior_is_that_of_the_updates_jittered_s():
    """A prior covariance that is not numerically positive definite (smallest eigenvalue -2e-15, mean variance 0.32):
    the plain Cholesky fails, the update and the likelihood share one fallback (cholesky_jittered), so the NLL is finite
    and equals the dense Gaussian's under S = H (L L^T) H^T + R with the update's L; and the update from P- equals
    the update from L L^T (it used that covariance). float64, dense S mixing 1e-6 and 1: rtol 1e-7 as above."""
    from torchtrack.filter.ekf import cholesky_jittered

    obs = noisy_observations(frames=1, outlier=False)[0]
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    ekf = FusionEKF(jacobian="analytic")
    prior = ekf.predicted(ekf.initial_state(true_pose(0.0)), obs.dt)
    v = torch.nn.functional.normalize(torch.arange(1.0, 13.0, dtype=F64), dim=0)
    vPv = v @ torch.linalg.solve(prior.cov, v[:, None].expand(2, 12, 1))[..., 0].T  # (B,) v^T P^-1 v
    bad = prior.cov - (1 + 1e-9) / vPv[:, None, None] * torch.outer(v, v)  # P - (1+e) v v^T / (v^T P^-1 v): indefinite
    assert bool((torch.linalg.cholesky_ex(bad).info > 0).all())  # the plain Cholesky of the old NLL fails
    L = cholesky_jittered(bad)
    P_used = L @ L.transpose(-1, -2)
    jitter = torch.diagonal(P_used - bad, dim1=-2, dim2=-1).mean(-1) / torch.diagonal(bad, dim1=-2, dim2=-1).mean(-1)
    assert bool(((jitter > 1e-13) & (jitter < 1e-1)).all())  # one of the fallback's 1e-12 ... 1e-2 (measured 1e-12)

    var5 = torch.cat([var_xyz[0][..., None].expand(-1, -1, 3), var_pix[0][..., None].expand(-1, -1, 2)], -1)
    h, H = ekf.linearize_at(prior, obs.points_obj, obs.K, obs.T_color_depth)
    z = torch.cat([obs.points_d, obs.pixels], -1)
    used = obs.valid[..., None].expand_as(z)
    r = torch.where(used, z - h, torch.zeros_like(z))
    nll = innovation_nll(bad, H, r, var5, used)
    assert bool(torch.isfinite(nll).all())
    for b in range(2):
        m = used[b].reshape(-1)
        Hb = H[b].reshape(-1, 12)[m]
        S = Hb @ P_used[b] @ Hb.T + torch.diag(var5[b].reshape(-1)[m])
        rb = r[b].reshape(-1)[m]
        dense = torch.distributions.MultivariateNormal(torch.zeros_like(rb), covariance_matrix=S).log_prob(rb)
        torch.testing.assert_close(nll[b], -dense, rtol=1e-7, atol=0)

    def update(cov):
        return ekf.updated(prior._replace(cov=cov), obs.points_obj, obs.points_d, obs.pixels, obs.valid, obs.valid,
                           var_xyz[0], var_pix[0], obs.K, obs.T_color_depth)  # fmt: skip

    a, b = update(bad), update(P_used)
    torch.testing.assert_close(a.mean, b.mean, rtol=1e-9, atol=1e-12)  # refactoring L L^T: ~1e-13 relative


def test_float64_in_float64_out():
    """float64 observations and variances give float64 everywhere: the frame's outputs, a rollout of learned
    windows (poses, NLL, the weighting's variances) and its pose errors."""
    from torchtrack.learn.model import LearnedWeighting
    from torchtrack.learn.oracle import oracle_windows
    from torchtrack.learn.rollout import concat_windows, pose_errors
    from torchtrack.learn.rollout import rollout as learn_rollout

    obs = noisy_observations(frames=1)[0]
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    ekf = FusionEKF(jacobian="analytic")
    out = ekf_frame(ekf, ekf.initial_state(true_pose(0.0)), obs, Variances(var_pix[0], var_xyz[0]), gate=0.999,
                    refit=0.999, with_nll=True)  # fmt: skip
    for name in ("mean", "cov", "innovation", "innovation_var", "nll"):
        assert getattr(out, name).dtype == F64, name
    a, b = oracle_windows(B=2, T=2, N=6, seed=0).windows, oracle_windows(B=1, T=2, N=4, seed=1).windows
    win = concat_windows([a, b])  # pads b's features
    assert win.points_d.dtype == F64 and win.valid.shape == (2, 3, 6)
    model = LearnedWeighting(mode="absolute").double()
    res = learn_rollout(ekf, model, win, gate=0.999, refit=0.999, with_nll=True)
    for name in ("T_cam_obj", "nll", "var_pix", "var_xyz"):
        assert getattr(res, name).dtype == F64, name
    assert all(e.dtype == F64 for e in pose_errors(res.T_cam_obj, win.T_cam_obj_gt))
