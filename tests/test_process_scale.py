"""The online process-noise scale (filter/process_scale.py, EKFBackend(process_scale=True)).

Oracle: a rigid body driven by exactly the filter's motion model (constant velocity plus piecewise-constant white
acceleration, eqs. 3-4 on the SE(3) error state) whose true acceleration std is k x the model's: the scale
estimates c = k^2 per block, and the filter that estimates it tracks as well as the filter given the true Q. With
the measurement scale on as well, both are found. Then: batched equals looped, inactive, featureless and dt = 0
frames keep the scale, a re-selection keeps it, off is today's filter, on is exactly the filter with Q = c Q0,
the Euler state, bounds, configuration, frames.csv."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from test_noise_scale import sequence  # sequence b of oracle windows alone (B = 1)

from torchtrack.config import CONF_DIR, EKFBackendConfig
from torchtrack.estimators.backends import EKFBackend, ekf_frame
from torchtrack.filter import FusionEKF, Variances
from torchtrack.filter.process_scale import ANG, LIN, ProcessScale
from torchtrack.geometry import make_T, project, so3_exp, transform_points
from torchtrack.learn.oracle import OracleWindows, oracle_windows
from torchtrack.learn.rollout import pose_errors

F64 = torch.float64
TOL = {F64: 1e-9}  # batched vs looped: other shapes sum in other orders
B, T, N = 8, 80, 40  # sequences, frames, features
BURN_IN = 20  # frames before the scale and the pose errors are measured
SIGMA = (0.3, 0.3)  # the model's acceleration std (rad/s^2, m/s^2) in these tests
# measurement noise low enough that the process noise is observable at k = 0.25 (tracking index ~1; see RESULTS)
PIX_VAR, XYZ_VAR_AT_1M = 0.01, 2.5e-7


def accelerated(k: float, B: int = B, T: int = T, seed: int = 1, dt: float = 1 / 30) -> OracleWindows:
    """:func:`oracle_windows`' bodies and camera, moved by the filter's own motion model with k x its acceleration
    std (SIGMA) and observed with PIX_VAR, XYZ_VAR_AT_1M noise (the same random draws for every k)."""
    o = oracle_windows(B, T, N, seed=seed, flag_fraction=0.0)
    w = o.windows
    g = torch.Generator().manual_seed(seed + 100)

    def randn(*shape):
        return torch.randn(*shape, generator=g, dtype=F64)

    X, R, t = w.points_obj[0], w.start_T_cam_obj[:, :3, :3], w.start_T_cam_obj[:, :3, 3]
    omega, vel = 0.3 * randn(B, 3), 0.15 * randn(B, 3)
    poses, points_d, pixels, var_xyz = [], [], [], []
    for _ in range(T):
        a_ang, a_lin = k * SIGMA[0] * randn(B, 3), k * SIGMA[1] * randn(B, 3)  # constant within the step
        R, t = so3_exp(omega * dt + a_ang * dt**2 / 2) @ R, t + vel * dt + a_lin * dt**2 / 2
        omega, vel = omega + a_ang * dt, vel + a_lin * dt
        pose = make_T(R, t)
        P = transform_points(pose, X)
        v3 = XYZ_VAR_AT_1M * P[..., 2] ** 4
        poses.append(pose)
        points_d.append(P + v3.sqrt()[..., None] * randn(B, N, 3))
        pixels.append(project(w.K, P) + PIX_VAR**0.5 * randn(B, N, 2))
        var_xyz.append(v3)
    w = replace(w, T_cam_obj_gt=torch.stack(poses), points_d=torch.stack(points_d), pixels=torch.stack(pixels))
    var_xyz = torch.stack(var_xyz)
    return o._replace(windows=w, var_pix=torch.full_like(var_xyz, PIX_VAR), var_xyz=var_xyz)


def track(oracle, q_scale=1.0, *, var_scale=(1.0, 1.0), process_scale=False, state="se3", active=None, valid=None,
          **kw):  # fmt: skip
    """Run an EKFBackend (gate and refit at 0.999) with Q = q_scale x the model's and the true variances divided by
    ``var_scale`` (pix, xyz). Returns the per-frame poses (T, B, 4, 4) and process scales (T, B, 2) (None when
    off) and noise scales (T, B, 2) (None when off)."""
    w = oracle.windows
    ekf = FusionEKF(sigma_ang_acc=SIGMA[0] * q_scale**0.5, sigma_lin_acc=SIGMA[1] * q_scale**0.5, state=state)
    backend = EKFBackend(ekf, gate=0.999, refit=0.999, process_scale=process_scale, **{"noise_scale": False, **kw})
    backend.reset(w.start_T_cam_obj, torch.ones(w.dt.shape[1], dtype=torch.bool))
    poses, proc, noise = [], [], []
    for t in range(w.frames):
        obs = w.observation(t)
        if valid is not None:
            obs.valid = obs.valid & valid[:, None]
        out = backend.step(obs, Variances(oracle.var_pix[t] / var_scale[0], oracle.var_xyz[t] / var_scale[1]), active)
        poses.append(out.T_cam_obj)
        proc.append(out.process_scale)
        noise.append(out.noise_scale)
    return torch.stack(poses), _stacked(proc), _stacked(noise)


def _stacked(xs):
    """The frames' (B, 2) scales stacked to (T, B, 2), or None when the scale is off."""
    return None if xs[0] is None else torch.stack(xs)


def settled(scales):
    """(2,) the geometric mean of the scales (T, B, 2) over the sequences and the frames after the burn-in: each
    sequence's estimate from ~10 frames (the default forgetting) scatters by ~30 % (RESULTS)."""
    return scales[BURN_IN:].log().mean((0, 1)).exp()


def rmse(poses, oracle) -> tuple[float, float]:
    """Translation (m) and rotation (rad) RMSE over the frames after the burn-in, averaged over the sequences."""
    e_t, e_r = pose_errors(poses[BURN_IN:], oracle.windows.T_cam_obj_gt[BURN_IN:])
    return float(e_t.square().mean(0).sqrt().mean()), float(e_r.square().mean(0).sqrt().mean())


@pytest.mark.parametrize("k", [0.25, 4.0])
def test_the_scale_finds_a_wrong_acceleration_and_tracks_like_the_true_q(k):
    oracle = accelerated(k)
    given_truth = track(oracle, k**2)[0]
    given_model = track(oracle)[0]
    adaptive, scales, _ = track(oracle, process_scale=True)
    torch.testing.assert_close(settled(scales), torch.full((2,), k**2, dtype=F64), rtol=0.2, atol=0)
    truth, model, adapt = rmse(given_truth, oracle), rmse(given_model, oracle), rmse(adaptive, oracle)
    for e_truth, e_adapt in zip(truth, adapt, strict=True):  # translation, rotation
        assert e_adapt <= 1.1 * e_truth
    assert model[0] > 1.1 * truth[0]  # the scale matters here: the model's Q tracks worse


def test_the_right_acceleration_keeps_the_scale_at_one():
    oracle = accelerated(1.0)
    adaptive, scales, _ = track(oracle, process_scale=True)
    torch.testing.assert_close(settled(scales), torch.ones(2, dtype=F64), rtol=0.1, atol=0)
    truth, adapt = rmse(track(oracle)[0], oracle), rmse(adaptive, oracle)
    assert adapt[0] <= 1.1 * truth[0] and adapt[1] <= 1.1 * truth[1]


def test_with_the_noise_scale_both_are_found():
    """Q 16x and the pixel noise 4x the model's at once (identifiability, module docstring): with both scales on,
    each finds what it finds alone when the other block is given its truth (within 5 %), the process scale finds
    c = 16, and the pose is as good as the filter's given the true Q and the noise scale alone. (The noise scale reads
    1.2-1.3x the true pixel noise in this fast-motion oracle whether Q is estimated or true: its own bias, RESULTS.)"""
    w = accelerated(4.0).windows
    g = torch.Generator().manual_seed(5)
    extra = (3 * PIX_VAR) ** 0.5 * torch.randn(w.pixels.shape, generator=g, dtype=F64)  # total 4 PIX_VAR
    oracle = accelerated(4.0)._replace(windows=replace(w, pixels=w.pixels + extra))
    oracle = oracle._replace(var_pix=oracle.var_pix * 4.0)  # the true variances
    told = (4.0, 1.0)  # the filter is told PIX_VAR: 4x too little
    _, proc_alone, _ = track(oracle, var_scale=(1.0, 1.0), process_scale=True)
    given_q, _, noise_alone = track(oracle, 16.0, var_scale=told, noise_scale=True)
    both, proc, noise = track(oracle, var_scale=told, process_scale=True, noise_scale=True)
    torch.testing.assert_close(settled(proc), settled(proc_alone), rtol=0.05, atol=0)
    torch.testing.assert_close(settled(noise), settled(noise_alone), rtol=0.05, atol=0)
    torch.testing.assert_close(settled(proc), torch.full((2,), 16.0, dtype=F64), rtol=0.2, atol=0)
    truth, adapt = rmse(given_q, oracle), rmse(both, oracle)
    assert adapt[0] <= 1.1 * truth[0] and adapt[1] <= 1.1 * truth[1]


def test_the_winsorising_is_unbiased():
    """With the cap at the median (half the frames capped), the right Q still reads c = 1 (0.99, 1.12 here; 1.00,
    1.08 at the default cap): the capped statistic is divided by E[min(chi2(3), cap)] (without it, ~0.02: the cap bites every frame and the log step compounds)."""
    _, scales, _ = track(accelerated(1.0), process_scale=True, process_clip=0.5)
    torch.testing.assert_close(settled(scales), torch.ones(2, dtype=F64), rtol=0.15, atol=0)


def test_the_euler_state_finds_it_too():
    oracle = accelerated(4.0, T=40)
    _, scales, _ = track(oracle, process_scale=True, state="euler")
    torch.testing.assert_close(scales[BURN_IN:].log().mean((0, 1)).exp(), torch.full((2,), 16.0, dtype=F64),
                               rtol=0.3, atol=0)  # fmt: skip


def test_batched_equals_looped():
    oracle = accelerated(4.0, B=3, T=12)
    poses, scales, _ = track(oracle, process_scale=True)
    for b in range(3):
        p, s, _ = track(sequence(oracle, b), process_scale=True)
        torch.testing.assert_close(s[:, 0], scales[:, b], atol=TOL[F64], rtol=TOL[F64])
        torch.testing.assert_close(p[:, 0], poses[:, b], atol=TOL[F64], rtol=TOL[F64])


def test_inactive_featureless_and_dt0_frames_keep_the_scale():
    oracle = accelerated(4.0, B=3, T=10)
    keep = torch.tensor([True, False, True])
    _, inactive, _ = track(oracle, process_scale=True, active=keep)
    _, blind, _ = track(oracle, process_scale=True, valid=keep)
    for scales in (inactive, blind):
        assert bool((scales[:, 1] == 1.0).all())  # never updated: the initial scale
        assert bool((scales[-1, keep] > 3.0).all())  # the others moved towards theirs
    w = oracle.windows
    backend = EKFBackend(FusionEKF(*SIGMA), gate=0.999, refit=0.999, process_scale=True, noise_scale=False)
    backend.reset(w.start_T_cam_obj, torch.ones(3, dtype=torch.bool))
    for t in range(5):
        backend.step(w.observation(t), Variances(oracle.var_pix[t], oracle.var_xyz[t]))
    before = backend.process_state
    obs = w.observation(5)
    obs.dt = torch.zeros_like(obs.dt)  # a second update of the same frame (landmarks): no process noise, no estimate
    backend.step(obs, Variances(oracle.var_pix[5], oracle.var_xyz[5]))
    assert torch.equal(backend.process_state.scale, before.scale) and torch.equal(backend.process_state.dof, before.dof)


def test_a_reselection_keeps_the_scale_and_a_new_batch_starts_at_one():
    oracle = accelerated(4.0, B=2, T=10)
    w = oracle.windows
    backend = EKFBackend(FusionEKF(*SIGMA), gate=0.999, refit=0.999, process_scale=True, noise_scale=False)
    backend.reset(w.start_T_cam_obj, torch.ones(2, dtype=torch.bool))
    for t in range(10):
        out = backend.step(w.observation(t), Variances(oracle.var_pix[t], oracle.var_xyz[t]))
    before = backend.process_state
    backend.reset(w.T_cam_obj_gt[-1], torch.tensor([True, False]))  # sequence 0 re-selects its model
    assert backend.process_state is before and bool((out.process_scale > 3.0).all())
    backend.start()
    assert backend.process_state is None
    backend.reset(w.T_cam_obj_gt[-1, :1], torch.ones(1, dtype=torch.bool))  # a new run
    assert bool((backend.process_state.scale == 1.0).all())


def test_snapshot_and_restore_carry_the_process_scale():
    """A frame redone from a snapshot (landmarks.measure's joint update) starts from the process scale of before it:
    redone with the same measurements it is the same frame, bit for bit; restored for one sequence only, the other
    keeps its after-frame scale."""
    oracle = accelerated(4.0, B=2, T=6)
    w = oracle.windows
    backend = EKFBackend(FusionEKF(*SIGMA), gate=0.999, refit=0.999, process_scale=True, noise_scale=False)
    backend.reset(w.start_T_cam_obj, torch.ones(2, dtype=torch.bool))
    for t in range(5):
        backend.step(w.observation(t), Variances(oracle.var_pix[t], oracle.var_xyz[t]))
    before = backend.snapshot()
    first = backend.step(w.observation(5), Variances(oracle.var_pix[5], oracle.var_xyz[5]))
    backend.restore(before)
    assert backend.process_state is before.process
    again = backend.step(w.observation(5), Variances(oracle.var_pix[5], oracle.var_xyz[5]))
    assert torch.equal(again.process.scale, first.process.scale) and torch.equal(again.process.dof, first.process.dof)
    backend.restore(before, torch.tensor([True, False]))
    assert torch.equal(backend.process_state.scale[0], before.process.scale[0])
    assert torch.equal(backend.process_state.scale[1], first.process.scale[1]) and bool(
        (first.process.scale != before.process.scale).all()
    )


@pytest.mark.parametrize(("q_scale", "bound"), [(1e3, 0.01), (1e-3, 100.0)])  # Q 1000x too large, too small
def test_the_scale_is_bounded(q_scale, bound):
    _, scales, _ = track(accelerated(1.0, B=2, T=30), q_scale, process_scale=True)
    assert bool((scales[-1] == bound).all()) and bool(((scales >= 0.01) & (scales <= 100.0)).all())


@pytest.mark.parametrize("state", ["se3", "euler"])
def test_off_is_the_filter_of_today_and_on_is_the_filter_with_the_scaled_q(state):
    """Off: the same frames as ekf_frame without the scale. On: a frame equals the frame of a filter whose
    acceleration stds are sqrt(c) x the model's (c a constant), gradients included."""
    oracle = accelerated(4.0, B=2, T=3)
    w, ekf = oracle.windows, FusionEKF(*SIGMA, state=state)
    state0 = ekf.initial_state(w.start_T_cam_obj)
    off = EKFBackend(ekf, gate=0.999, refit=0.999, noise_scale=False)
    off.reset(w.start_T_cam_obj, torch.ones(2, dtype=torch.bool))
    s = state0
    for t in range(3):
        var = Variances(oracle.var_pix[t], oracle.var_xyz[t])
        out = off.step(w.observation(t), var)
        ref = ekf_frame(ekf, s, w.observation(t), var, gate=0.999, refit=0.999)
        s = ref.posterior
        assert out.process is None and out.process_scale is None and off.process_state is None
        assert torch.equal(out.mean, ref.mean) and torch.equal(out.cov, ref.cov)
    ps = ProcessScale()
    c = torch.tensor([[3.0, 0.5], [0.3, 2.0]], dtype=F64)
    vp, vx = oracle.var_pix[1].clone().requires_grad_(), oracle.var_xyz[1].clone().requires_grad_()
    on = ekf_frame(ekf, state0, w.observation(1), Variances(vp, vx), gate=0.999, refit=0.999, process_scale=ps,
                   process_state=ps.initial(2)._replace(scale=c))  # fmt: skip
    assert not on.process.scale.requires_grad
    g_on = torch.autograd.grad(on.T_cam_obj[:, :3, 3].sum(), (vp, vx))
    for b in range(2):
        one = FusionEKF(SIGMA[0] * float(c[b, ANG]) ** 0.5, SIGMA[1] * float(c[b, LIN]) ** 0.5, state=state)
        vpb, vxb = vp[b : b + 1].detach().requires_grad_(), vx[b : b + 1].detach().requires_grad_()
        ref = ekf_frame(one, sequence_state(state0, b), sequence(oracle, b).windows.observation(1),
                        Variances(vpb, vxb), gate=0.999, refit=0.999)  # fmt: skip
        torch.testing.assert_close(on.posterior.cov[b : b + 1], ref.posterior.cov, rtol=1e-9, atol=1e-15)
        torch.testing.assert_close(on.T_cam_obj[b : b + 1], ref.T_cam_obj, rtol=1e-9, atol=1e-12)
        g_ref = torch.autograd.grad(ref.T_cam_obj[:, :3, 3].sum(), (vpb, vxb))
        for a, r in zip(g_on, g_ref, strict=True):
            torch.testing.assert_close(a[b : b + 1], r, rtol=1e-6, atol=1e-12)
            assert bool(r.abs().sum() > 0)


def sequence_state(state, b: int):
    """Row b of a FilterState."""
    return type(state)(*(x[b : b + 1] for x in state))


@pytest.mark.parametrize(
    "kwargs", [dict(forgetting=0.0), dict(forgetting=1.5), dict(min_scale=2.0), dict(max_scale=0.5), dict(clip=1.0)]
)
def test_bad_parameters_raise(kwargs):
    with pytest.raises(ValueError, match="ProcessScale"):
        ProcessScale(**kwargs)


def test_configuration():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        default = compose("config")
        on = compose("config", overrides=["tracker.process_scale=true", "tracker.process_forgetting=0.8"])
        paper = compose("config", overrides=["+experiment=paper", "weighting=learned"])
    assert instantiate(default.tracker).process is None and paper.tracker.process_scale is False
    process = instantiate(on.tracker).process
    assert isinstance(process, ProcessScale) and process.forgetting == 0.8
    assert process.clip == EKFBackendConfig.process_clip and process.max_scale == EKFBackendConfig.process_scale_max


def test_frames_csv_reports_the_back_ends_process_scale(tmp_path):
    """The runner writes the back end's process scales per frame: the last row equals the filter's final state."""
    import csv

    from torchtrack.data import TumSequence
    from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
    from torchtrack.factory import build_tracker
    from torchtrack.run import run_tracker

    seq = TumSequence(ensure_sequence(SyntheticConfig(width=160, height=120, frames=6, seed=1), tmp_path / "data"))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        tracker = build_tracker(compose("config", overrides=["tracker.process_scale=true"]))
    run_tracker(tracker, [seq], tmp_path / "on", plots=False)
    with open(tmp_path / "on" / seq.name / "frames.csv") as f:
        rows = list(csv.DictReader(f))
    got = [(float(r["process_scale_ang"]), float(r["process_scale_lin"])) for r in rows]
    final = tracker.backend.process_state.scale[0]
    assert got[-1] == pytest.approx((float(final[ANG]), float(final[LIN])), rel=1e-6)
    assert got[0] == (1.0, 1.0) and got[-1] != (1.0, 1.0)  # the first frame has no update
