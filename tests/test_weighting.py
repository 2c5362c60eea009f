"""Measurement weighting, eqs. (11)-(14): hand computation, preserved means, masks, floors, fixed ablation."""

import pytest
import torch

from torchtrack.filter.weighting import FixedWeighting, PaperWeighting, WeightingInputs, paper_variances

F64 = torch.float64


def inputs(B=2, N=8, seed=0, valid=None):
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(B, N, 3, generator=g, dtype=F64) * 0.2 + torch.tensor([0.0, 0.0, 1.5], dtype=F64)
    d = torch.rand(B, N, generator=g, dtype=F64) * 2
    v = torch.ones(B, N, dtype=torch.bool) if valid is None else valid
    return WeightingInputs(d, pts[..., 2].clone(), pts, v, torch.full((B,), 525.0, dtype=F64))


def test_hand_computed_example():
    """Three features, written out with Python floats exactly as eqs. (11)-(14) read."""
    d = [0.5, 1.0, 2.5]
    pts = [[0.1, 0.0, 1.0], [-0.2, 0.1, 2.0], [0.0, -0.3, 1.5]]
    z = [p[2] for p in pts]
    f, s_pix, s_xyz, n = 500.0, 2.0, 1e-4, 3
    var_pix = [n * di / sum(d) * s_pix for di in d]  # eq. (11)
    w1 = [zi / f * di for zi, di in zip(z, d, strict=True)]  # eq. (12)
    w1n = [w / sum(w1) for w in w1]
    c = [sum(p[k] for p in pts) / n for k in range(3)]
    w2 = [1 / sum((p[k] - c[k]) ** 2 for k in range(3)) ** 0.5 for p in pts]  # eq. (13)
    w2n = [w / sum(w2) for w in w2]
    s = [a + b for a, b in zip(w1n, w2n, strict=True)]
    var_xyz = [n * si / sum(s) * s_xyz for si in s]  # eq. (14)
    inp = WeightingInputs(
        torch.tensor([d], dtype=F64), torch.tensor([z], dtype=F64), torch.tensor([pts], dtype=F64),
        torch.ones(1, 3, dtype=torch.bool), torch.tensor([f], dtype=F64),
    )  # fmt: skip
    out = PaperWeighting(s_pix, s_xyz, depth_var_exponent=0.0)(inp)  # the paper's eqs. (11)-(14)
    torch.testing.assert_close(out.var_pix, torch.tensor([var_pix], dtype=F64))
    torch.testing.assert_close(out.var_xyz, torch.tensor([var_xyz], dtype=F64))


def test_means_preserved_over_valid_features_and_invalid_get_nominal():
    valid = torch.rand(3, 10, generator=torch.Generator().manual_seed(1)) > 0.3
    inp = inputs(3, 10, valid=valid)
    out = PaperWeighting(1.5, 4e-4, depth_var_exponent=0.0)(inp)  # the paper's: eq. (14) keeps the mean
    assert out.var_pix.shape == (3, 10) and out.var_xyz.shape == (3, 10)
    for b in range(3):
        torch.testing.assert_close(out.var_pix[b][valid[b]].mean(), torch.tensor(1.5, dtype=F64))
        torch.testing.assert_close(out.var_xyz[b][valid[b]].mean(), torch.tensor(4e-4, dtype=F64))
    assert (out.var_pix[~valid] == 1.5).all() and (out.var_xyz[~valid] == 4e-4).all()


def test_garbage_in_masked_features_changes_nothing():
    inp = inputs(2, 6)
    ref = PaperWeighting()(inp)
    nan = torch.full((2, 3), float("nan"), dtype=F64)
    padded = WeightingInputs(
        torch.cat([inp.d_tim, nan], 1), torch.cat([inp.depth, nan], 1),
        torch.cat([inp.points_d, nan[..., None].expand(2, 3, 3)], 1),
        torch.cat([inp.valid, torch.zeros(2, 3, dtype=torch.bool)], 1), inp.focal,
    )  # fmt: skip
    out = PaperWeighting()(padded)
    torch.testing.assert_close(out.var_pix[:, :6], ref.var_pix)
    torch.testing.assert_close(out.var_xyz[:, :6], ref.var_xyz)
    assert torch.isfinite(out.var_pix).all() and torch.isfinite(out.var_xyz).all()


def test_zero_tim_floor_and_no_valid_feature():
    inp = inputs(2, 5)._replace(d_tim=torch.zeros(2, 5, dtype=F64))
    out = PaperWeighting(1.0, 1e-4, d_tim_floor=0.01)(inp)
    torch.testing.assert_close(out.var_pix, torch.ones(2, 5, dtype=F64))  # all floored equally -> nominal
    assert (out.var_xyz > 0).all()
    one_perfect = inputs(1, 4)._replace(d_tim=torch.tensor([[0.0, 1.0, 1.0, 1.0]], dtype=F64))
    v = PaperWeighting(1.0, 1e-4, d_tim_floor=0.01)(one_perfect).var_pix
    torch.testing.assert_close(v, 4 * torch.tensor([[0.01, 1.0, 1.0, 1.0]], dtype=F64) / 3.01)
    empty = inputs(1, 4, valid=torch.zeros(1, 4, dtype=torch.bool))
    out = PaperWeighting(2.0, 3e-4)(empty)
    assert (out.var_pix == 2.0).all() and (out.var_xyz == 3e-4).all()


def test_depth_dependent_option():
    inp = inputs(1, 6)
    base = PaperWeighting(1.0, 1e-4, depth_var_exponent=0.0)(inp)
    kin = PaperWeighting(1.0, 1e-4, depth_var_exponent=4.0, depth_ref=1.0)(inp)
    torch.testing.assert_close(kin.var_xyz, base.var_xyz * inp.depth**4)
    torch.testing.assert_close(kin.var_pix, base.var_pix)


def test_fixed_weighting_ablation():
    inp = inputs(2, 7)
    out = FixedWeighting(0.7, 2e-4)(inp)
    assert (out.var_pix == 0.7).all() and (out.var_xyz == 2e-4).all() and out.var_pix.shape == (2, 7)


@pytest.mark.equivalence
def test_batched_equals_looped_and_module_equals_function():
    valid = torch.rand(3, 9, generator=torch.Generator().manual_seed(2)) > 0.2
    inp = inputs(3, 9, valid=valid)
    out = PaperWeighting(1.2, 5e-4, d_tim_floor=0.05)(inp)
    fn = paper_variances(inp, 1.2, 5e-4, d_tim_floor=0.05)
    assert torch.equal(out.var_pix, fn.var_pix) and torch.equal(out.var_xyz, fn.var_xyz)
    for b in range(3):
        one = PaperWeighting(1.2, 5e-4, d_tim_floor=0.05)(WeightingInputs(*(t[b : b + 1] for t in inp[:5])))
        torch.testing.assert_close(one.var_pix[0], out.var_pix[b])
        torch.testing.assert_close(one.var_xyz[0], out.var_xyz[b])


def test_bad_input_raises():
    inp = inputs(2, 5)
    with pytest.raises(ValueError, match="weighting: expected"):
        PaperWeighting()(inp._replace(points_d=inp.points_d[..., :2]))
    with pytest.raises(ValueError, match="weighting: expected"):
        FixedWeighting()(inp._replace(focal=inp.focal[:1]))
    with pytest.raises(ValueError, match="must be > 0"):
        PaperWeighting(sigma2_pix=0.0)
