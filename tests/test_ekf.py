"""Generic batched EKF: closed-form Kalman filter oracle, information == gain form, masks, IEKF, gradients."""

import pytest
import torch

from torchtrack.filter import ekf
from torchtrack.filter.models import measure_analytic, measure_single
from torchtrack.geometry import intrinsics_matrix, make_T, so3_exp

TOL = {torch.float32: 1e-4, torch.float64: 1e-9}
F64 = torch.float64


def linear_h(x, H_i):
    """Linear per-feature model h(x) = H_i x, through the same autograd code path as nonlinear ones."""
    return H_i @ x


def random_spd(B, S, scale=1.0, g=None, dtype=F64):
    A = torch.randn(B, S, S, generator=g, dtype=dtype)
    return scale * (A @ A.transpose(-1, -2) / S + 0.1 * torch.eye(S, dtype=dtype))


def linear_problem(B=3, N=4, M=2, S=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    H = torch.randn(B, N, M, S, generator=g, dtype=F64)
    mean = torch.randn(B, S, generator=g, dtype=F64)
    cov = random_spd(B, S, g=g)
    z = torch.randn(B, N, M, generator=g, dtype=F64)
    var = torch.rand(B, N, M, generator=g, dtype=F64) + 0.1
    return mean, cov, H, z, var


def kalman_closed_form(mean, cov, H, z, var):
    """Textbook KF update for ONE sequence with full matrices: H (NM, S), R = diag(var)."""
    R = torch.diag(var)
    K = cov @ H.T @ torch.linalg.inv(H @ cov @ H.T + R)
    return mean + K @ (z - H @ mean), (torch.eye(len(mean), dtype=F64) - K @ H) @ cov


def fusion_problem(B=2, N=20, seed=0, dtype=F64):
    """Nonlinear paper model (eqs. 6-7) with realistic numbers: object ~1.5 m ahead, 1 mm / 1 px noise."""
    g = torch.Generator().manual_seed(seed)
    mean = torch.cat(
        [0.2 * torch.randn(B, 3, generator=g), 0.05 * torch.randn(B, 3, generator=g), torch.randn(B, 6, generator=g)],
        -1,
    )
    mean[:, 5] += 1.5
    cov = torch.diag_embed(torch.tensor([1e-3] * 6 + [1e-1] * 6).expand(B, 12)) + 1e-5 * random_spd(B, 12, g=g)
    X = 0.2 * torch.randn(B, N, 3, generator=g)
    K = intrinsics_matrix(525.0, 530.0, 319.5, 239.5).expand(B, 3, 3)
    T = make_T(so3_exp(0.05 * torch.randn(B, 3, generator=g)), 0.03 * torch.randn(B, 3, generator=g))
    h, _ = ekf.linearize(measure_single, mean.to(dtype), (X.to(dtype),), (K.to(dtype), T.to(dtype)))
    z = h + torch.cat([1e-3 * torch.randn(B, N, 3, generator=g), torch.randn(B, N, 2, generator=g)], -1).to(dtype)
    var = torch.cat([torch.full((B, N, 3), 1e-6), torch.full((B, N, 2), 1.0)], -1) * (
        0.5 + torch.rand(B, N, 1, generator=g)
    )
    mean, cov, z, var, X, K, T = (t.to(dtype) for t in (mean, cov, z, var, X, K, T))
    return mean, cov, z, var, (X,), (K, T)


def test_shapes_and_smoke():
    mean, cov, H, z, var = linear_problem()
    valid = torch.ones(3, 4, dtype=torch.bool)
    out = ekf.update(mean, cov, z, var, valid, linear_h, (H,))
    assert out.mean.shape == (3, 5) and out.cov.shape == (3, 5, 5) and out.innovation.shape == (3, 4, 2)
    assert out.num_valid.tolist() == [8, 8, 8]
    pred = ekf.predict(mean, cov, torch.eye(5, dtype=F64), torch.eye(5, dtype=F64))
    assert pred.mean.shape == (3, 5) and pred.cov.shape == (3, 5, 5)


def test_bad_input_raises():
    mean, cov, H, z, var = linear_problem()
    valid = torch.ones(3, 4, dtype=torch.bool)
    with pytest.raises(ValueError, match="mean must be"):
        ekf.update(mean[0], cov, z, var, valid, linear_h, (H,))
    with pytest.raises(ValueError, match="valid must be"):
        ekf.update(mean, cov, z, var, valid[:, :2], linear_h, (H,))
    with pytest.raises(ValueError, match="z and var"):
        ekf.update(mean, cov, z, var[..., :1], valid, linear_h, (H,))
    with pytest.raises(ValueError, match="iterations"):
        ekf.update(mean, cov, z, var, valid, linear_h, (H,), iterations=0)
    with pytest.raises(ValueError, match="feature inputs"):
        ekf.update(mean, cov, z, var, valid, linear_h, (H[:, :2],))
    with pytest.raises(ValueError, match="F must be"):
        ekf.predict(mean, cov, torch.eye(4, dtype=F64), cov)


@pytest.mark.parametrize("form", ["information", "gain"])
def test_linear_system_equals_closed_form_kalman(form):
    """Three predict/update cycles of a linear system == textbook KF with full (NM x NM) matrices."""
    B, N, M, S = 3, 4, 2, 5
    mean, cov, H, z, var = linear_problem(B, N, M, S)
    g = torch.Generator().manual_seed(1)
    F = torch.eye(S, dtype=F64) + 0.1 * torch.randn(B, S, S, generator=g, dtype=F64)
    Q = random_spd(B, S, 0.01, g=g)
    valid = torch.ones(B, N, dtype=torch.bool)
    ref_m, ref_P = mean.clone(), cov.clone()
    for step in range(3):
        zs = z + step
        mean, cov = ekf.predict(mean, cov, F, Q)
        mean, cov, *_ = ekf.update(mean, cov, zs, var, valid, linear_h, (H,), form=form)
        for b in range(B):
            m, P = F[b] @ ref_m[b], F[b] @ ref_P[b] @ F[b].T + Q[b]
            ref_m[b], ref_P[b] = kalman_closed_form(m, P, H[b].reshape(N * M, S), zs[b].reshape(-1), var[b].reshape(-1))
    torch.testing.assert_close(mean, ref_m, atol=TOL[F64], rtol=TOL[F64])
    torch.testing.assert_close(cov, ref_P, atol=TOL[F64], rtol=TOL[F64])


def test_predict_callable_equals_matrix():
    mean, cov, *_ = linear_problem()
    F = torch.eye(5, dtype=F64) + torch.diag(torch.ones(4, dtype=F64), 1) * 0.1
    Q = 0.01 * torch.eye(5, dtype=F64)
    a = ekf.predict(mean, cov, F, Q)
    b = ekf.predict(mean, cov, lambda x: F @ x, Q)
    torch.testing.assert_close(a.mean, b.mean)
    torch.testing.assert_close(a.cov, b.cov)


@pytest.mark.parametrize("iterations", [1, 3])
def test_information_equals_gain_form(iterations):
    """Information form == the paper's eq. (15), to 1e-8 in float64, on the nonlinear model with masks."""
    mean, cov, z, var, fi, si = fusion_problem()
    valid = torch.rand(2, 20, generator=torch.Generator().manual_seed(3)) > 0.3
    a = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=iterations)
    b = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, form="gain", iterations=iterations)
    torch.testing.assert_close(a.mean, b.mean, atol=1e-8, rtol=1e-8)
    torch.testing.assert_close(a.cov, b.cov, atol=1e-8 * cov.abs().max().item(), rtol=1e-8)


def test_first_iteration_linearises_at_prediction():
    """Docstring claim: the EKF update uses h and H evaluated at the PREDICTED mean."""
    mean, cov, z, var, fi, si = fusion_problem(B=1)
    valid = torch.ones(1, 20, dtype=torch.bool)
    out = ekf.update(mean, cov, z, var, valid, measure_single, fi, si)
    h, H = ekf.linearize(measure_single, mean, fi, si)
    ref_m, ref_P = kalman_closed_form(
        mean[0],
        cov[0],
        H[0].reshape(100, 12),
        (z - h)[0].reshape(-1) + H[0].reshape(100, 12) @ mean[0],
        var[0].reshape(-1),
    )
    torch.testing.assert_close(out.mean[0], ref_m, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.cov[0], ref_P, atol=1e-12, rtol=1e-8)
    torch.testing.assert_close(out.innovation, z - h)


def test_iterated_update_reaches_map_stationary_point():
    """IEKF = Gauss-Newton on ||x - mu-||^2_{P^-1} + ||z - h(x)||^2_{Q^-1}: its gradient vanishes at the end."""
    mean, cov, z, var, fi, si = fusion_problem(B=2)
    valid = torch.ones(2, 20, dtype=torch.bool)
    out = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=8)
    h, H = ekf.linearize(measure_single, out.mean, fi, si)
    grad = torch.linalg.solve(cov, (out.mean - mean)[..., None])[..., 0] - torch.einsum(
        "bnms,bnm->bs", H, (z - h) / var
    )
    one = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=1)
    h1, H1 = ekf.linearize(measure_single, one.mean, fi, si)
    grad1 = torch.linalg.solve(cov, (one.mean - mean)[..., None])[..., 0] - torch.einsum(
        "bnms,bnm->bs", H1, (z - h1) / var
    )
    assert grad.abs().max() < 1e-6 * grad1.abs().max()


@pytest.mark.parametrize("form", ["information", "gain"])
def test_masked_garbage_features_change_nothing(form):
    mean, cov, z, var, fi, si = fusion_problem(N=10)
    valid = torch.ones(2, 10, dtype=torch.bool)
    ref = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, form=form, iterations=2)
    pad = lambda t, v: torch.cat([t, torch.full((2, 5, *t.shape[2:]), v, dtype=t.dtype)], 1)  # noqa: E731
    for bad in (float("nan"), float("inf"), 0.0, -3.0):
        out = ekf.update(
            mean, cov, pad(z, bad), pad(var, bad), pad(valid, False), measure_single, (pad(fi[0], bad),), si,
            form=form, iterations=2,
        )  # fmt: skip
        torch.testing.assert_close(out.mean, ref.mean, atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(out.cov, ref.cov, atol=1e-15, rtol=1e-12)
        assert torch.equal(out.innovation[:, 10:], torch.zeros_like(out.innovation[:, 10:]))


def test_component_mask_equals_dropping_rows():
    """valid (B, N, M): masking the 3D part of a feature == a model without those rows (linear oracle)."""
    B, N, M, S = 2, 4, 3, 5
    mean, cov, H, z, var = linear_problem(B, N, M, S)
    valid = torch.ones(B, N, M, dtype=torch.bool)
    valid[:, 1, :2] = False
    out = ekf.update(mean, cov, z.masked_fill(~valid, float("nan")), var, valid, linear_h, (H,))
    for b in range(B):
        keep = valid[b].reshape(-1)
        ref_m, ref_P = kalman_closed_form(
            mean[b], cov[b], H[b].reshape(N * M, S)[keep], z[b].reshape(-1)[keep], var[b].reshape(-1)[keep]
        )
        torch.testing.assert_close(out.mean[b], ref_m)
        torch.testing.assert_close(out.cov[b], ref_P)


def test_no_valid_feature_keeps_prediction_exactly():
    mean, cov, z, var, fi, si = fusion_problem()
    valid = torch.ones(2, 20, dtype=torch.bool)
    valid[1] = False
    out = ekf.update(mean, cov, z, var, valid, measure_single, fi, si)
    assert torch.equal(out.mean[1], mean[1]) and out.num_valid[1] == 0
    torch.testing.assert_close(out.cov[1], cov[1], atol=1e-15, rtol=1e-12)
    assert not torch.equal(out.mean[0], mean[0])


@pytest.mark.equivalence
def test_batched_equals_looped():
    mean, cov, z, var, fi, si = fusion_problem(B=3)
    valid = torch.rand(3, 20, generator=torch.Generator().manual_seed(5)) > 0.2
    out = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=2)
    for b in range(3):
        one = ekf.update(mean[b : b + 1], cov[b : b + 1], z[b : b + 1], var[b : b + 1], valid[b : b + 1], measure_single, (fi[0][b : b + 1],), tuple(s[b : b + 1] for s in si), iterations=2)  # fmt: skip
        torch.testing.assert_close(one.mean[0], out.mean[b], atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(one.cov[0], out.cov[b], atol=1e-15, rtol=1e-10)


def test_jacfwd_equals_jacrev():
    mean, _, _, _, fi, si = fusion_problem()
    h1, H1 = ekf.linearize(measure_single, mean, fi, si, mode="forward")
    h2, H2 = ekf.linearize(measure_single, mean, fi, si, mode="reverse")
    torch.testing.assert_close(h1, h2)
    torch.testing.assert_close(H1, H2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_covariance_symmetric_positive_definite(dtype):
    """Tight 3D variances (1e-8 m^2) after a loose prior: still symmetric PD, in float32 too."""
    mean, cov, z, var, fi, si = fusion_problem(N=50, dtype=dtype)
    var = var * torch.tensor([1e-2] * 3 + [1.0] * 2, dtype=dtype)
    valid = torch.ones(2, 50, dtype=torch.bool)
    for _ in range(3):
        mean, cov, *_ = ekf.update(mean, cov, z, var, valid, measure_single, fi, si)
        assert torch.equal(cov, cov.transpose(-1, -2))
        assert torch.linalg.eigvalsh(cov.double()).min() > 0


def test_gradient_through_update_wrt_variances():
    """float64 gradcheck of the posterior mean w.r.t. per-feature variances (a learned weighting needs it)."""
    mean, cov, z, var, fi, si = fusion_problem(B=1, N=4)
    valid = torch.tensor([[True, True, False, True]])
    var = var.clone().requires_grad_(True)

    def analytic(x, fi, si):  # closed-form Jacobian keeps the 40 gradcheck evaluations fast
        return measure_analytic(x, fi[0], *si)

    def f(v):
        return ekf.update(mean, cov, z, v, valid, feature_inputs=fi, sequence_inputs=si, linearizer=analytic).mean

    assert torch.autograd.gradcheck(f, (var,), eps=1e-9, atol=1e-5, rtol=1e-4, fast_mode=True)
    z_bad = z.clone()
    z_bad[0, 2] = float("nan")
    ekf.update(
        mean, cov, z_bad, var, valid, feature_inputs=fi, sequence_inputs=si, linearizer=analytic
    ).mean.sum().backward()
    assert torch.isfinite(var.grad).all() and (var.grad[0, 2] == 0).all()


def test_masked_feature_with_singular_model_does_not_leak():
    """h blows up (inf/NaN value and Jacobian) at the placeholder input of masked features: result unchanged."""

    def h_log(x, a):  # (S,), (M,) -> (M,); log(0) = -inf at zeroed inputs
        return torch.log(a) * x[: a.shape[0]] + x[: a.shape[0]] ** 2

    mean, cov, _, z, var = linear_problem(B=2, N=4, M=2, S=5)
    a = torch.rand(2, 4, 2, generator=torch.Generator().manual_seed(7), dtype=F64) + 0.5
    valid = torch.tensor([[True, True, False, True], [False, True, True, True]])
    for form in ("information", "gain"):
        out = ekf.update(mean, cov, z, var, valid, h_log, (a.masked_fill(~valid[..., None], -1.0),), form=form)
        ref = ekf.update(mean, cov, z, var, valid, h_log, (a,), form=form)
        assert torch.isfinite(out.mean).all() and torch.isfinite(out.cov).all()
        torch.testing.assert_close(out.mean, ref.mean)
        torch.testing.assert_close(out.cov, ref.cov)


@pytest.mark.parametrize("iterations", [1, 3])
def test_given_linearization_equals_a_fresh_one(iterations):
    """An update handed (h, H) at the prior mean, computed once for all features (as the gate and the refit
    share it), equals one that linearises itself, with some features masked."""
    mean, cov, z, var, fi, si = fusion_problem()
    valid = torch.ones(z.shape[:2], dtype=torch.bool)
    valid[:, :5] = False
    given = ekf.linearize(measure_single, mean, fi, si)
    fresh = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=iterations)
    reused = ekf.update(mean, cov, z, var, valid, measure_single, fi, si, iterations=iterations, linearization=given)
    torch.testing.assert_close(reused.mean, fresh.mean, atol=1e-12, rtol=0)
    torch.testing.assert_close(reused.cov, fresh.cov, atol=1e-12, rtol=0)
