"""Learned weighting (torchtrack.learn.model) and its checkpoints: the untrained model is FixedWeighting,
normalisation and bounds, masks (garbage in invalid slots), batched = looped, permutation equivariance, gradcheck,
save/load round trip, mismatches, the Hydra factory and config composition."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

import torchtrack.learn.checkpoint as ckpt
from torchtrack.config import CONF_DIR
from torchtrack.filter.cues import CUE_INDEX, CUE_NAMES, CUE_VERSION, D_TIM_CAP
from torchtrack.filter.weighting import FixedWeighting, WeightingInputs
from torchtrack.learn.checkpoint import load_checkpoint, save_checkpoint
from torchtrack.learn.model import LearnedWeighting, soft_clamp

F64 = torch.float64
CONF = CONF_DIR
MODES = ("normalised", "absolute")


def make_inputs(B=2, N=12, seed=0, dtype=torch.float32, valid=None) -> WeightingInputs:
    """Plausible raw cues (CUE_NAMES order) and matching depth/points; a few d_TIM at D_TIM_CAP."""
    g = torch.Generator().manual_seed(seed)

    def u(lo, hi):
        return lo + (hi - lo) * torch.rand(B, N, generator=g, dtype=F64)

    pts = torch.randn(B, N, 3, generator=g, dtype=F64) * 0.3 + torch.tensor([0.0, 0.0, 2.0], dtype=F64)
    pts[..., 2] = pts[..., 2].clamp_min(0.4)
    d_sim = u(0, 2).masked_fill(torch.rand(B, N, generator=g) < 0.2, D_TIM_CAP)
    c = dict(
        d_tim_int=u(0, 2), d_tim_sim=d_sim, sim_won=(u(0, 1) > 0.5).to(F64), lk_residual=u(0, 0.05),
        depth=pts[..., 2], centroid_dist=(pts - pts.mean(1, keepdim=True)).norm(dim=-1), cornerness_int=u(0, 1),
        cornerness_sim=u(0, 1), sim_value=u(0, 1), track_age=u(0, 40).floor(), prev_reproj=u(0, 2),
        u_norm=u(0, 1), v_norm=u(0, 1), depth_step=u(0, 0.3), depth_holes=u(0, 1), lk_min_eig=u(0, 1e-3),
    )  # fmt: skip
    c["fb_error"] = torch.minimum(c["d_tim_int"], d_sim)
    cues = torch.stack([c[n] for n in CUE_NAMES], -1).to(dtype)
    v = torch.ones(B, N, dtype=torch.bool) if valid is None else valid
    d_tim = torch.minimum(c["d_tim_int"], d_sim).to(dtype)
    return WeightingInputs(
        d_tim, pts[..., 2].to(dtype), pts.to(dtype), v, torch.full((B,), 525.0, dtype=dtype), cues=cues
    )


def randomised(model: LearnedWeighting, seed=1, scale=1.0) -> LearnedWeighting:
    """PyTorch's default initialisation for every layer, the zero-initialised last one too (times ``scale``):
    a stand-in for a trained model."""
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        for layer in model.modules():
            if isinstance(layer, torch.nn.Linear):
                layer.reset_parameters()
    with torch.no_grad():
        for p in model.head[-1].parameters():
            p.mul_(scale)
    return model


def test_size_and_untrained_equals_fixed():
    model = LearnedWeighting()
    assert model.needs_cues and sum(p.numel() for p in model.parameters()) <= 10_000
    for mode in MODES:
        for dtype in (torch.float32, F64):
            m = LearnedWeighting(mode=mode, sigma2_pix=0.7, sigma2_xyz=3e-6, depth_var_exponent=0.0).to(dtype)
            inp = make_inputs(dtype=dtype, valid=torch.rand(2, 12, generator=torch.Generator().manual_seed(3)) > 0.3)
            out, ref = m(inp), FixedWeighting(0.7, 3e-6)(inp)
            assert out.var_pix.dtype == dtype and torch.equal(out.var_pix, ref.var_pix)
            assert torch.equal(out.var_xyz, ref.var_xyz)
            # the depth prior multiplies after the network, as PaperWeighting's (z / depth_ref)^e
            kin = LearnedWeighting(mode=mode, sigma2_pix=0.7, sigma2_xyz=3e-6, depth_ref=2.0).to(dtype)(inp)
            torch.testing.assert_close(kin.var_xyz, torch.where(inp.valid, 3e-6 * (inp.depth / 2.0) ** 4, 3e-6))


@pytest.mark.parametrize("mode", MODES)
def test_constant_scores_reproduce_fixed(mode):
    """Random hidden layers with a zero last weight: constant scores, i.e. constant variances (normalised: any bias)."""
    m = randomised(LearnedWeighting(mode=mode, sigma2_pix=2.0, sigma2_xyz=1e-4, depth_var_exponent=0.0)).double()
    inp = make_inputs(dtype=F64)
    with torch.no_grad():
        m.head[-1].weight.zero_()
        m.head[-1].bias.copy_(torch.tensor([0.8, -1.3]) if mode == "normalised" else torch.zeros(2))
    out, ref = m(inp), FixedWeighting(2.0, 1e-4)(inp)
    torch.testing.assert_close(out.var_pix, ref.var_pix)
    torch.testing.assert_close(out.var_xyz, ref.var_xyz)


def test_normalised_keeps_the_mean_and_absolute_stays_in_bounds():
    valid = torch.rand(3, 20, generator=torch.Generator().manual_seed(4)) > 0.25
    inp = make_inputs(3, 20, dtype=F64, valid=valid)
    m = randomised(LearnedWeighting(sigma2_pix=1.5, sigma2_xyz=4e-6), scale=5.0).double()
    out = m(inp)
    for b in range(3):  # eqs. (11)/(14): the mean over valid features is kept; the depth prior comes after
        v = valid[b]
        torch.testing.assert_close(out.var_pix[b][v].mean(), torch.tensor(1.5, dtype=F64))
        torch.testing.assert_close((out.var_xyz[b][v] / inp.depth[b][v] ** 4).mean(), torch.tensor(4e-6, dtype=F64))
    assert out.var_pix[valid].std() > 0.01  # the network does redistribute
    big = randomised(LearnedWeighting(mode="absolute", depth_var_exponent=0.0, log_ratio_min=-3, log_ratio_max=2))
    with torch.no_grad():
        big.head[-1].bias.copy_(torch.tensor([1e3, -1e3]))  # scores far beyond both bounds
    r = big(make_inputs(3, 20, valid=valid))
    torch.testing.assert_close(r.var_pix, torch.full_like(r.var_pix, 2.0).where(valid, 0.0).exp())
    torch.testing.assert_close(r.var_xyz, 4e-6 * torch.full_like(r.var_xyz, -3.0).where(valid, 0.0).exp())


def test_soft_clamp():
    s = torch.linspace(-15, 15, 1001, dtype=F64, requires_grad=True)
    y = soft_clamp(s, -3.0, 2.0)
    (g,) = torch.autograd.grad(y.sum(), s)
    assert y.min() > -3 and y.max() < 2 and (g > 0).all() and g.max() == 1.0
    far = torch.tensor([-1e6, 1e6], requires_grad=True)  # saturated: at the bounds, zero but finite gradient
    (g,) = torch.autograd.grad(soft_clamp(far, -3.0, 2.0).sum(), far)
    assert torch.equal(soft_clamp(far, -3.0, 2.0), torch.tensor([-3.0, 2.0])) and torch.isfinite(g).all()
    assert soft_clamp(torch.zeros(1), -3.0, 2.0).item() == 0.0
    torch.testing.assert_close(soft_clamp(torch.tensor([1e-4, -1e-4], dtype=F64), -3.0, 2.0), torch.tensor([1e-4, -1e-4], dtype=F64))  # fmt: skip


@pytest.mark.parametrize("mode", MODES)
def test_garbage_in_invalid_slots_changes_nothing(mode):
    m = randomised(LearnedWeighting(mode=mode))
    inp = make_inputs(2, 8)
    ref = m(inp)
    nan = torch.full((2, 4), float("nan"))
    padded = WeightingInputs(
        torch.cat([inp.d_tim, nan], 1), torch.cat([inp.depth, nan], 1),
        torch.cat([inp.points_d, nan[..., None].expand(2, 4, 3)], 1),
        torch.cat([inp.valid, torch.zeros(2, 4, dtype=torch.bool)], 1), inp.focal,
        cues=torch.cat([inp.cues, torch.full((2, 4, len(CUE_NAMES)), float("nan"))], 1),
    )  # fmt: skip
    out = m(padded)
    torch.testing.assert_close(out.var_pix[:, :8], ref.var_pix)
    torch.testing.assert_close(out.var_xyz[:, :8], ref.var_xyz)
    assert (out.var_pix[:, 8:] == m.sigma2_pix).all() and (out.var_xyz[:, 8:] == m.sigma2_xyz).all()
    loss = out.var_pix.log().sum() + out.var_xyz.log().sum()
    grads = torch.autograd.grad(loss, list(m.parameters()))
    assert all(torch.isfinite(g).all() for g in grads)


@pytest.mark.equivalence
@pytest.mark.parametrize("mode", MODES)
def test_batched_equals_looped_and_permutation_equivariant(mode):
    valid = torch.rand(3, 15, generator=torch.Generator().manual_seed(5)) > 0.3
    inp = make_inputs(3, 15, valid=valid)
    m = randomised(LearnedWeighting(mode=mode))
    out = m(inp)
    for b in range(3):
        one = m(WeightingInputs(*(t[b : b + 1] for t in inp[:5]), cues=inp.cues[b : b + 1]))
        torch.testing.assert_close(one.var_pix[0], out.var_pix[b])
        torch.testing.assert_close(one.var_xyz[0], out.var_xyz[b])
    perm = torch.randperm(15, generator=torch.Generator().manual_seed(6))
    shuffled = m(WeightingInputs(*(t[:, perm] for t in inp[:4]), inp.focal, cues=inp.cues[:, perm]))
    torch.testing.assert_close(shuffled.var_pix, out.var_pix[:, perm])
    torch.testing.assert_close(shuffled.var_xyz, out.var_xyz[:, perm])


def test_float32_matches_float64():
    m = randomised(LearnedWeighting())
    inp32, inp64 = make_inputs(dtype=torch.float32), make_inputs(dtype=F64)
    out32, out64 = m(inp32), m.double()(inp64)
    assert out32.var_pix.dtype == torch.float32 and out64.var_pix.dtype == F64
    torch.testing.assert_close(out32.var_pix, out64.var_pix.float(), rtol=1e-4, atol=0)
    torch.testing.assert_close(out32.var_xyz, out64.var_xyz.float(), rtol=1e-4, atol=0)


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck_parameters_and_cues(mode):
    m = randomised(LearnedWeighting(mode=mode, hidden=3, log_ratio_min=-2.0, log_ratio_max=1.5), scale=3.0).double()
    inp = make_inputs(2, 5, dtype=F64, valid=torch.tensor([[True, True, False, True, True], [True] * 5]))
    names = [n for n, _ in m.named_parameters()]

    def f(cues, *params):
        out = torch.func.functional_call(m, dict(zip(names, params, strict=True)), (inp._replace(cues=cues),))
        return out.var_pix, out.var_xyz * 1e4

    params = [p.detach().clone().requires_grad_() for p in m.parameters()]
    assert torch.autograd.gradcheck(f, (inp.cues.clone().requires_grad_(), *params))


def test_no_nan_gradients_at_edges():
    """All features of a sequence invalid, cues at 0 (below every log floor), at D_TIM_CAP, at a floor exactly."""
    for mode in MODES:
        m = randomised(LearnedWeighting(mode=mode)).double()
        inp = make_inputs(3, 6, dtype=F64, valid=torch.tensor([[False] * 6, [True] * 6, [True] * 6]))
        cues = inp.cues.clone()
        cues[1] = 0.0
        cues[2, :, CUE_INDEX["d_tim_int"]] = D_TIM_CAP
        cues[2, :, CUE_INDEX["d_tim_sim"]] = D_TIM_CAP
        cues[2, :, CUE_INDEX["depth"]] = 0.1
        cues.requires_grad_()
        out = m(inp._replace(cues=cues))
        assert torch.isfinite(out.var_pix).all() and torch.isfinite(out.var_xyz).all()
        assert (out.var_pix[0] == m.sigma2_pix).all()
        grads = torch.autograd.grad(out.var_pix.sum() + 1e4 * out.var_xyz.sum(), [cues, *m.parameters()])
        assert all(torch.isfinite(g).all() for g in grads)


def test_bad_input_raises():
    m = LearnedWeighting()
    inp = make_inputs()
    with pytest.raises(ValueError, match="expected cues"):
        m(inp._replace(cues=None))
    with pytest.raises(ValueError, match="expected cues"):
        m(inp._replace(cues=inp.cues[..., :5]))
    with pytest.raises(ValueError, match="mode"):
        LearnedWeighting(mode="relative")
    with pytest.raises(ValueError, match="log_ratio_min < 0 < log_ratio_max"):
        LearnedWeighting(log_ratio_min=1.0)


# ----------------------------------------------------------------------------------------------- checkpoints


@pytest.mark.parametrize("mode", MODES)
def test_checkpoint_round_trip(tmp_path, mode):
    m = randomised(LearnedWeighting(mode=mode, sigma2_pix=0.5, hidden=16, depth_var_exponent=2.0))
    path = save_checkpoint(tmp_path / "sub" / "w.pt", m, extra={"config": {"lr": 1e-3}, "metrics": {"ate": 0.01}})
    assert [p.name for p in path.parent.iterdir()] == ["w.pt"]  # no temporary left behind
    loaded, meta = load_checkpoint(path)
    assert not loaded.training and loaded.config == m.config
    assert meta["format"] == "torchtrack-weighting" and meta["cue_names"] == list(CUE_NAMES)
    assert meta["config"] == {"lr": 1e-3} and meta["metrics"] == {"ate": 0.01} and "state_dict" not in meta
    inp = make_inputs()
    a, b = m(inp), loaded(inp)
    assert torch.equal(a.var_pix, b.var_pix) and torch.equal(a.var_xyz, b.var_xyz)


def test_checkpoint_mismatches_raise(tmp_path):
    path = save_checkpoint(tmp_path / "w.pt", LearnedWeighting())
    blob = torch.load(path, weights_only=True)

    def write(**changes):
        torch.save({**blob, **changes}, bad := tmp_path / "bad.pt")
        return bad

    with pytest.raises(
        ValueError, match=r"bad\.pt: made with cue version 2 .*column 0: 'depth' there, 'd_tim_int' here\)"
    ):
        load_checkpoint(write(cue_names=["depth", "d_tim_int", *CUE_NAMES[2:]]))
    with pytest.raises(ValueError, match=r"bad\.pt: made with cue version 1 \(13 cues\).*column 13: 'none' there"):
        load_checkpoint(write(cue_names=list(CUE_NAMES[:13]), cue_version=1))  # a cue-version-1 model: one line
    with pytest.raises(ValueError, match=rf"bad\.pt.*cue version {CUE_VERSION + 1}.*cue version {CUE_VERSION}"):
        load_checkpoint(write(cue_version=CUE_VERSION + 1))
    with pytest.raises(ValueError, match=r"bad\.pt: checkpoint version 99; this torchtrack reads version 1"):
        load_checkpoint(write(version=99))
    with pytest.raises(ValueError, match=r"bad\.pt: not a 'torchtrack-weighting' checkpoint \(format 'other'\)"):
        load_checkpoint(write(format="other"))
    with pytest.raises(FileNotFoundError, match="nowhere.pt"):
        load_checkpoint(tmp_path / "nowhere.pt")
    with pytest.raises(ValueError, match="reserved keys"):
        save_checkpoint(tmp_path / "x.pt", LearnedWeighting(), extra={"model": {}})
    with pytest.raises(ValueError, match="weights_only"):
        save_checkpoint(tmp_path / "x.pt", LearnedWeighting(), extra={"thing": Path("a")})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.pt", "w.pt"]


def test_factory(tmp_path, monkeypatch):
    m = randomised(LearnedWeighting(mode="absolute", sigma2_xyz=1e-5))
    path = save_checkpoint(tmp_path / "w.pt", m)
    f = ckpt.learned_weighting(str(path), mode="absolute", sigma2_xyz=1e-5)
    assert not any(p.requires_grad for p in f.parameters())
    assert torch.equal(f(make_inputs()).var_xyz, m(make_inputs()).var_xyz)
    with pytest.raises(ValueError, match=r"w\.pt was trained with other settings \(sigma2_xyz: config 0.0001 vs checkpoint 1e-05\)"):  # fmt: skip
        ckpt.learned_weighting(str(path), sigma2_xyz=1e-4)
    with pytest.raises(ValueError, match="unknown arguments"):
        ckpt.learned_weighting(str(path), width=3)
    monkeypatch.setattr(ckpt, "DEFAULT_CHECKPOINT", tmp_path / "missing.pt")
    with pytest.raises(FileNotFoundError, match="no trained model shipped.*weighting.checkpoint=PATH"):
        ckpt.learned_weighting()
    monkeypatch.setattr(ckpt, "DEFAULT_CHECKPOINT", path)
    assert ckpt.learned_weighting().config == m.config


def test_config_composition(tmp_path):
    from torchtrack.factory import build_tracker

    m = randomised(LearnedWeighting())
    path = save_checkpoint(tmp_path / "w.pt", m)
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=["weighting=learned", f"weighting.checkpoint={path}"])
        bad = compose("config", overrides=["weighting=learned", f"weighting.checkpoint={path}", "weighting.mode=absolute"])  # fmt: skip
    w = instantiate(cfg.weighting)
    assert isinstance(w, LearnedWeighting) and w.config == m.config
    assert isinstance(build_tracker(cfg).weighting, LearnedWeighting)
    with pytest.raises(Exception, match="trained with other settings"):
        instantiate(bad.weighting)
