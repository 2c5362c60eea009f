"""The online noise scale (filter/noise_scale.py, FusionEKF(noise_scale=True)).

Oracle: observations whose true noise is k x the model's, for the pixel block or the 3D block alone: the scale
estimates k, and the filter that estimates it tracks as well as the filter given the true noise. Then: batched
equals looped, inactive and featureless sequences keep their scale, a re-selection keeps it, bounds, off is
today's filter, on computes exactly the filter with R = k R0 (gradients included), configuration."""

from __future__ import annotations

from dataclasses import fields, replace

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from torchtrack.config import CONF_DIR
from torchtrack.filter import FusionEKF, Variances
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.ekf import chi2_quantile
from torchtrack.filter.frame import ekf_frame
from torchtrack.filter.noise_scale import PIX, XYZ, NoiseScale, winsorised_chi2_mean, winsorised_scale
from torchtrack.learn.oracle import oracle_windows
from torchtrack.learn.rollout import PER_WINDOW, pose_errors

F64 = torch.float64
TOL = {F64: 1e-9}  # batched vs looped: other shapes sum in other orders
B, T, N = 8, 60, 40  # sequences, frames, features
BURN_IN = 15  # frames before the pose errors and the k = 1 band are measured
PIX_VAR, XYZ_VAR_AT_1M = 0.25, 4e-6  # the model's nominal noise (oracle_windows' defaults)


def windows(k_pix: float = 1.0, k_xyz: float = 1.0, seed: int = 1, **kw):
    """A smooth rigid motion observed with k x the nominal noise (the same random draws for every k)."""
    return oracle_windows(
        kw.pop("B", B), kw.pop("T", T), kw.pop("N", N), seed=seed, pix_var=PIX_VAR * k_pix,
        xyz_var_at_1m=XYZ_VAR_AT_1M * k_xyz, flag_fraction=0.0, **kw,
    )  # fmt: skip


def track(oracle, var_scale=(1.0, 1.0), *, noise_scale=False, active=None, valid=None, outliers=0.999, **kw):
    """Run an EKFBackend (the default pipeline's gate and refit at quantile ``outliers``) over the windows with the
    true variances divided by ``var_scale`` (pix, xyz). Returns the per-frame poses (T, B, 4, 4) and scales
    (T, B, 2) (None when off)."""
    w = oracle.windows
    backend = EKFBackend(FusionEKF(gate=outliers, refit=outliers, noise_scale=noise_scale, **kw))
    backend.reset(w.start_T_cam_obj, torch.ones(w.dt.shape[1], dtype=torch.bool))
    poses, scales = [], []
    for t in range(w.frames):
        obs = w.observation(t)
        if valid is not None:
            obs.valid = obs.valid & valid[:, None]
        var = Variances(oracle.var_pix[t] / var_scale[0], oracle.var_xyz[t] / var_scale[1])
        out = backend.step(obs, var, active=active)
        poses.append(out.T_cam_obj)
        scales.append(out.noise_scale)
    return torch.stack(poses), (torch.stack(scales) if noise_scale else None)


def rmse(poses, oracle) -> tuple[float, float]:
    """Translation (m) and rotation (rad) RMSE over the frames after the burn-in, averaged over the sequences."""
    e_t, e_r = pose_errors(poses[BURN_IN:], oracle.windows.T_cam_obj_gt[BURN_IN:])
    return float(e_t.square().mean(0).sqrt().mean()), float(e_r.square().mean(0).sqrt().mean())


@pytest.mark.parametrize(
    ("block", "k"),
    [(PIX, 4.0), pytest.param(PIX, 0.25, marks=pytest.mark.slow), pytest.param(XYZ, 0.25, marks=pytest.mark.slow),
     pytest.param(XYZ, 4.0, marks=pytest.mark.slow)],
)  # fmt: skip
def test_the_scale_finds_a_wrong_block_and_tracks_like_the_true_noise(block, k):
    true_scale = (k, 1.0) if block == PIX else (1.0, k)
    oracle = windows(*true_scale)
    given_truth, _ = track(oracle)  # the filter given the true noise
    given_model, _ = track(oracle, true_scale)  # the nominal noise, k times off
    adaptive, scales = track(oracle, true_scale, noise_scale=True)
    torch.testing.assert_close(scales[-1, :, block], torch.full((B,), k, dtype=F64), rtol=0.2, atol=0)
    torch.testing.assert_close(scales[-1, :, 1 - block], torch.ones(B, dtype=F64), rtol=0.1, atol=0)
    truth, model, adapt = rmse(given_truth, oracle), rmse(given_model, oracle), rmse(adaptive, oracle)
    for e_truth, e_adapt in zip(truth, adapt, strict=True):  # translation, rotation
        assert e_adapt <= 1.1 * e_truth
    assert model[0] > 1.05 * truth[0]  # the scale matters here: the nominal noise tracks worse


def test_the_right_noise_keeps_the_scale_at_one():
    oracle = windows()
    adaptive, scales = track(oracle, noise_scale=True)
    torch.testing.assert_close(scales[BURN_IN:], torch.ones_like(scales[BURN_IN:]), rtol=0.1, atol=0)
    truth, adapt = rmse(track(oracle)[0], oracle), rmse(adaptive, oracle)
    assert adapt[0] <= 1.1 * truth[0] and adapt[1] <= 1.1 * truth[1]


def test_gross_outliers_barely_move_the_scale():
    """5 % of the features per frame 10 cm and 15 px off (the gate drops them, the scale still sees them): the
    scales of both blocks, each wrong by 4x, are found within 25 % all the same (the winsorised mean's bias is about
    +2.1 e and +1.6 e for a fraction e of outliers: +11 %, +8 %), and the pose is as good as the true noise's.
    Without the winsorising, the outliers would set the scale."""
    oracle = windows(4.0, 0.25)
    w = oracle.windows
    g = torch.Generator().manual_seed(7)
    bad = torch.rand(T, B, N, generator=g) < 0.05
    w.points_d = w.points_d + 0.1 * bad[..., None] * torch.nn.functional.normalize(
        torch.randn(T, B, N, 3, generator=g, dtype=F64), dim=-1
    )
    w.pixels = w.pixels + 15.0 * bad[..., None] * torch.nn.functional.normalize(
        torch.randn(T, B, N, 2, generator=g, dtype=F64), dim=-1
    )
    given_truth, _ = track(oracle)
    adaptive, scales = track(oracle, (4.0, 0.25), noise_scale=True)
    torch.testing.assert_close(scales[-1], torch.tensor([4.0, 0.25], dtype=F64).expand(B, 2), rtol=0.25, atol=0)
    truth, adapt = rmse(given_truth, oracle), rmse(adaptive, oracle)
    assert adapt[0] <= 1.1 * truth[0] and adapt[1] <= 1.1 * truth[1]
    _, plain_mean = track(oracle, (4.0, 0.25), noise_scale=True, noise_clip=None)
    assert bool((plain_mean[-1] > 5.0 * torch.tensor([4.0, 0.25], dtype=F64)).all())


def bisected_scale(q, w, c: float, expected: float) -> float:
    """The positive root of ``s E - sum w min(q, c s) / sum w`` by bisection (convex in s, negative just above 0)."""
    h = lambda s: s * expected - float((w * torch.minimum(q, torch.tensor(c * s, dtype=F64))).sum() / w.sum())  # noqa: E731
    lo, hi = 1e-300, 1.0
    while h(hi) <= 0:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if h(mid) <= 0 else (lo, mid)
    return 0.5 * (lo + hi)


@pytest.mark.parametrize("dof", [2, 3])
def test_the_winsorised_scale_is_the_root_of_its_equation(dof):
    """The closed form against bisection on heavy-tailed, unevenly weighted rows (some without a measurement), and the
    case it can be read off: equal q unclipped give q / E. Rows of no weight give 1e-12."""
    c = chi2_quantile(0.9, dof)
    E = winsorised_chi2_mean(dof, c)
    g = torch.Generator().manual_seed(dof)
    q = torch.randn(6, 150, dof, generator=g, dtype=F64).square().sum(-1)  # chi-square(dof)
    heavy = torch.where(torch.rand(6, 150, generator=g) < 0.2, 40.0, 1.0).to(F64)
    q = q * heavy * torch.tensor([0.1, 1, 3, 10, 1, 1], dtype=F64)[:, None]
    w = torch.rand(6, 150, generator=g, dtype=F64) * (torch.rand(6, 150, generator=g) < 0.8)
    w[4] = 0.0  # no measurement
    q[5], w[5] = 2.5, 1.0
    s = winsorised_scale(q, w, c, E)
    for b in (0, 1, 2, 3):
        assert abs(float(s[b]) - bisected_scale(q[b], w[b], c, E)) <= 1e-12 * float(s[b])
    assert float(s[4]) == 1e-12
    assert abs(float(s[5]) - 2.5 / E) <= 1e-15 * 2.5 / E


def test_a_root_at_a_breakpoint_is_found():
    """Rows whose root lies within rounding of one q / c (one value moved onto c times the root, a few ulps either
    side): the segment is chosen by the sign of the equation at the breakpoints, so such a root is not lost (choosing
    by each segment's own root missed it in ~1 of 1,000 such rows). Also: q = 0 with weight counts as unclipped, a
    row without a positive root gives 1e-12, a NaN gives NaN, and float32 agrees with float64."""
    c = chi2_quantile(0.9, 3)
    E = winsorised_chi2_mean(3, c)
    g = torch.Generator().manual_seed(11)
    for trial in range(60):
        q = torch.cat([torch.rand(40, generator=g, dtype=F64) * 2, 5 + torch.rand(10, generator=g, dtype=F64)])
        w = torch.ones(50, dtype=F64)
        t = bisected_scale(q, w, c, E)
        for k in (-3, -1, 0, 1, 3):
            moved = q.clone()
            moved[40 + trial % 10] = c * t * (1 + k * 2e-16)
            s = float(winsorised_scale(moved[None], w[None], c, E)[0])
            assert abs(s - bisected_scale(moved, w, c, E)) <= 1e-12 * s, (trial, k, s)
    q = torch.tensor([[0.0, 0.0, 1.0, 2.0, 3.0], [0.0] * 5, [1.0, float("nan"), 2.0, 3.0, 4.0]], dtype=F64)
    s = winsorised_scale(q, torch.ones(3, 5, dtype=F64), c, E)
    assert abs(float(s[0]) - bisected_scale(q[0], torch.ones(5, dtype=F64), c, E)) <= 1e-12 * float(s[0])
    assert float(s[1]) == 1e-12 and bool(torch.isnan(s[2]))
    q32 = torch.rand(4, 100, generator=g) * 3
    s32 = winsorised_scale(q32, torch.ones(4, 100), c, E)
    torch.testing.assert_close(s32.double(), winsorised_scale(q32.double(), torch.ones(4, 100, dtype=F64), c, E),
                               rtol=1e-5, atol=0)  # fmt: skip


def test_batched_equals_looped():
    oracle = windows(4.0, 0.25, B=3, T=12)
    poses, scales = track(oracle, (4.0, 0.25), noise_scale=True)
    for b in range(3):
        p, s = track(sequence(oracle, b), (4.0, 0.25), noise_scale=True)
        torch.testing.assert_close(s[:, 0], scales[:, b], atol=TOL[F64], rtol=TOL[F64])
        torch.testing.assert_close(p[:, 0], poses[:, b], atol=TOL[F64], rtol=TOL[F64])


def sequence(oracle, b: int):
    """Sequence b of the oracle's windows alone (B = 1)."""
    w = oracle.windows
    rows = {f.name: getattr(w, f.name)[b : b + 1] if f.name in PER_WINDOW else getattr(w, f.name)[:, b : b + 1]
            for f in fields(w)}  # fmt: skip
    return oracle._replace(windows=replace(w, **rows), var_pix=oracle.var_pix[:, b : b + 1],
                           var_xyz=oracle.var_xyz[:, b : b + 1])  # fmt: skip


def test_inactive_and_featureless_sequences_keep_their_scale():
    oracle = windows(4.0, 4.0, B=3, T=10)
    keep = torch.tensor([True, False, True])
    _, inactive = track(oracle, (4.0, 4.0), noise_scale=True, active=keep)
    _, blind = track(oracle, (4.0, 4.0), noise_scale=True, valid=keep)
    for scales in (inactive, blind):
        assert bool((scales[:, 1] == 1.0).all())  # never updated: the initial scale
        assert bool((scales[-1, keep] > 3.0).all())  # the others found theirs


def test_a_reselection_keeps_the_scale_and_a_new_batch_starts_at_one():
    oracle = windows(4.0, 1.0, B=2, T=10)
    w = oracle.windows
    backend = EKFBackend(FusionEKF(gate=0.999, refit=0.999, noise_scale=True))
    backend.reset(w.start_T_cam_obj, torch.ones(2, dtype=torch.bool))
    for t in range(10):
        out = backend.step(w.observation(t), Variances(oracle.var_pix[t] / 4.0, oracle.var_xyz[t]))
    before = backend.scale_state
    backend.reset(w.T_cam_obj_gt[-1], torch.tensor([True, False]))  # sequence 0 re-selects its model
    assert backend.scale_state is before and bool((out.noise_scale[:, PIX] > 3.0).all())
    backend.reset(w.T_cam_obj_gt[-1, :1], torch.ones(1, dtype=torch.bool))  # a new batch
    assert bool((backend.scale_state.scale == 1.0).all())


@pytest.mark.parametrize(("k", "bound"), [(1e4, 100.0), (1e-4, 0.01)])
def test_the_scale_is_bounded(k, bound):
    _, scales = track(windows(k, k, B=2, T=5), (k, k), noise_scale=True)
    assert bool((scales[-1] == bound).all()) and bool(((scales >= 0.01) & (scales <= 100.0)).all())


def test_off_is_the_filter_of_today():
    oracle = windows(4.0, 1.0, B=2, T=5)
    w, ekf = oracle.windows, FusionEKF()
    state, off = ekf.initial_state(w.start_T_cam_obj), EKFBackend(FusionEKF(noise_scale=False))
    off.reset(w.start_T_cam_obj, torch.ones(2, dtype=torch.bool))
    for t in range(5):
        var = Variances(oracle.var_pix[t], oracle.var_xyz[t])
        out = off.step(w.observation(t), var)
        ref = ekf_frame(ekf, state, w.observation(t), var, gate=0.999, refit=0.999)
        state = ref.posterior
        assert out.noise is None and out.noise_scale is None and off.scale_state is None
        assert torch.equal(out.mean, ref.mean) and torch.equal(out.cov, ref.cov)


def test_on_is_the_filter_with_the_scaled_noise_and_its_gradient():
    """A frame with the scale on is exactly the frame with R = k R0 (k a constant): same posterior, same gradient
    with respect to the weighting's variances."""
    oracle = windows(4.0, 0.25, B=2, T=2)
    w, ekf, ns = oracle.windows, FusionEKF(), NoiseScale()
    state = ekf.initial_state(w.start_T_cam_obj)
    scale = ns.initial(2)._replace(scale=torch.tensor([[3.0, 0.5], [0.3, 2.0]], dtype=F64))
    vp, vx = oracle.var_pix[1].clone().requires_grad_(), oracle.var_xyz[1].clone().requires_grad_()
    on = ekf_frame(ekf, state, w.observation(1), Variances(vp, vx), gate=0.999, refit=0.999, noise_scale=ns,
                   scale_state=scale)  # fmt: skip
    k = scale.scale
    ref = ekf_frame(ekf, state, w.observation(1), Variances(vp * k[:, :1], vx * k[:, 1:]), gate=0.999, refit=0.999)
    assert torch.equal(on.mean, ref.mean) and torch.equal(on.cov, ref.cov)
    assert not on.noise.scale.requires_grad and not on.noise.dof.requires_grad
    g_on = torch.autograd.grad(on.T_cam_obj[:, :3, 3].sum(), (vp, vx))
    g_ref = torch.autograd.grad(ref.T_cam_obj[:, :3, 3].sum(), (vp, vx))
    for a, b in zip(g_on, g_ref, strict=True):
        assert torch.equal(a, b) and bool(a.abs().sum() > 0)


@pytest.mark.parametrize(
    "kwargs", [dict(forgetting=0.0), dict(forgetting=1.5), dict(min_scale=2.0), dict(max_scale=0.5), dict(clip=1.0)]
)
def test_bad_parameters_raise(kwargs):
    with pytest.raises(ValueError, match="NoiseScale"):
        NoiseScale(**kwargs)


def test_configuration():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        default = compose("config")
        off = compose("config", overrides=["filter.noise_scale=false"])
        paper = compose("config", overrides=["+experiment=paper"])
    assert default.filter.noise_scale is True and isinstance(instantiate(default.estimator).ekf.noise, NoiseScale)
    assert instantiate(off.estimator).ekf.noise is None and paper.filter.noise_scale is False
    assert instantiate(paper.estimator).ekf.noise is None
    noise = FusionEKF(noise_forgetting=0.9, noise_clip=None).noise  # its tuning: the filter's arguments, not keys
    assert isinstance(noise, NoiseScale) and noise.forgetting == 0.9 and noise.clip is None


def test_frames_csv_reports_the_back_ends_scale(tmp_path):
    """The runner writes the back end's scales per frame (1.0 where the scale is off): the last row equals the filter's
    final scale state, read from the tracker itself."""
    import csv

    from torchtrack.data import TumSequence
    from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
    from torchtrack.factory import build_tracker
    from torchtrack.run import run_tracker

    seq = TumSequence(ensure_sequence(SyntheticConfig(width=160, height=120, frames=6, seed=1), tmp_path / "data"))
    for on in (False, True):
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            tracker = build_tracker(compose("config", overrides=[f"filter.noise_scale={str(on).lower()}"]))
        run_tracker(tracker, [seq], tmp_path / str(on), plots=False)
        with open(tmp_path / str(on) / seq.name / "frames.csv") as f:
            rows = list(csv.DictReader(f))
        got = [(float(r["noise_scale_pix"]), float(r["noise_scale_xyz"])) for r in rows]
        if not on:
            assert got == [(1.0, 1.0)] * len(rows)
            continue
        final = tracker.backend.scale_state.scale[0]
        assert got[-1] == pytest.approx((float(final[PIX]), float(final[XYZ])), rel=1e-6)
        assert got[0] == (1.0, 1.0) and got[-1] != (1.0, 1.0)  # the first frame has no update
