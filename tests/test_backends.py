"""EKFBackend's outlier handling: the innovation gate and the refit (oracle: the update without the outlier)."""

import pytest
import torch
from test_fusion import DT, body, measurements, true_pose

from torchtrack.estimators.backends import EKFBackend, Observation, chi2_quantile
from torchtrack.filter import FusionEKF, Variances

F64 = torch.float64


def observation(outlier_px=0.0, outlier_m=0.0, drop_outlier=False):
    """Noise-free measurements of a moving body one frame after the start; feature 0 of every sequence is
    moved by ``outlier_px`` pixels and ``outlier_m`` metres (or left out with ``drop_outlier``)."""
    X, K, T_cd = body()
    B, N = X.shape[:2]
    points_d, pixels = measurements(true_pose(DT), X, K, T_cd)
    points_d[:, 0] += outlier_m
    pixels[:, 0] += outlier_px
    valid = torch.ones(B, N, dtype=torch.bool)
    valid[:, 0] = not drop_outlier
    var = torch.ones(B, N, dtype=F64)
    obs = Observation(torch.full((B,), DT, dtype=F64), X, points_d, pixels, valid, K, T_cd)
    return obs, Variances(0.25 * var, 1e-6 * var)


def estimate(backend, obs_var):
    obs, var = obs_var
    backend.reset(true_pose(0.0), torch.ones(obs.dt.shape[0], dtype=torch.bool))
    return backend.step(obs, var).T_cam_obj


def test_refit_equals_the_update_without_the_outlier():
    # 4 px and 2 cm: inside the gate of the prediction (the velocity is still unknown), so only the refit sees it
    obs = observation(outlier_px=4.0, outlier_m=0.02)
    plain = estimate(EKFBackend(FusionEKF(), gate=0.999, refit=None), obs)
    refit = estimate(EKFBackend(FusionEKF(), gate=0.999, refit=0.999), obs)
    oracle = estimate(EKFBackend(FusionEKF(), gate=0.999, refit=None), observation(drop_outlier=True))
    torch.testing.assert_close(refit, oracle, atol=1e-12, rtol=0)
    assert float((plain - oracle).abs().max()) > 1e-5  # the outlier did bias the plain update


def test_refit_changes_nothing_without_outliers():
    obs = observation()
    plain = estimate(EKFBackend(FusionEKF(), gate=None, refit=None), obs)
    torch.testing.assert_close(estimate(EKFBackend(FusionEKF(), gate=None, refit=0.999), obs), plain, atol=0, rtol=0)


def test_gate_drops_gross_outliers():
    obs = observation(outlier_px=200.0, outlier_m=1.0)
    gated = estimate(EKFBackend(FusionEKF(), gate=0.999, refit=None), obs)
    oracle = estimate(EKFBackend(FusionEKF(), gate=None, refit=None), observation(drop_outlier=True))
    torch.testing.assert_close(gated, oracle, atol=1e-12, rtol=0)


def test_chi2_quantile_against_known_values():
    assert chi2_quantile(0.999, 2) == pytest.approx(13.8155, abs=1e-4)  # exact for k = 2
    assert chi2_quantile(0.999, 3) == pytest.approx(16.2662, abs=1e-4)  # tables (Abramowitz & Stegun 26.8)
    assert chi2_quantile(0.95, 1) == pytest.approx(1.959964**2, abs=1e-5)  # the square of the normal quantile
    assert chi2_quantile(0.5, 10) == pytest.approx(9.3418, abs=1e-4)


@pytest.mark.parametrize("name, p", [("gate", 1.0), ("refit", 0.0)])
def test_bad_probabilities_raise(name, p):
    with pytest.raises(ValueError, match=name):
        EKFBackend(FusionEKF(), **{name: p})


def test_refit_drops_a_failing_3d_point_alone():
    """A feature whose 3D point alone is off loses only that: the oracle is the filter with that point masked."""
    obs, var = observation(outlier_m=0.02)
    refit = estimate(EKFBackend(FusionEKF(), gate=None, refit=0.999), (obs, var))
    keep = obs.valid.clone()
    keep[:, 0] = False
    oracle = FusionEKF()
    prior = oracle.predicted(oracle.initial_state(true_pose(0.0)), obs.dt)
    update = oracle.updated(prior, obs.points_obj, obs.points_d, obs.pixels, keep, obs.valid, var.var_xyz, var.var_pix,
                            obs.K, obs.T_color_depth)  # fmt: skip
    expected = oracle.injected(prior, update).T_cam_obj
    torch.testing.assert_close(refit, expected, atol=1e-12, rtol=0)
    dropped_both = estimate(EKFBackend(FusionEKF(), gate=None, refit=None), observation(drop_outlier=True))
    assert float((refit - dropped_both).abs().max()) > 1e-9  # the good pixel of feature 0 was kept


def test_a_pixel_alone_is_not_dropped():
    """Policy (EKFBackend._keep): the pixel variances of eq. (11) are relative, so a pixel is dropped only with
    its 3D point; a pixel-only outlier leaves the update as it is, and no second update is run."""
    obs = observation(outlier_px=4.0)
    plain = estimate(EKFBackend(FusionEKF(), gate=None, refit=None), obs)
    backend = EKFBackend(FusionEKF(), gate=None, refit=0.999)
    calls = []
    update = backend.ekf.updated
    backend.ekf.updated = lambda *a, **k: calls.append(1) or update(*a, **k)
    torch.testing.assert_close(estimate(backend, obs), plain, atol=0, rtol=0)
    assert len(calls) == 1
