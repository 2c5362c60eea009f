"""Metrics: ATE/RPE against evo on the same TUM files; Umeyama, eqs. (16), (17), per-axis errors by hand."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from torchtrack.geometry import (
    T_inv,
    euler_to_matrix,
    intrinsics_matrix,
    make_T,
    matrix_to_quat_xyzw,
    pose_from_euler,
    project,
    quat_xyzw_to_matrix,
    se3_exp,
    so3_exp,
    transform_points,
)
from torchtrack.metrics import (
    ate,
    per_axis_errors,
    percentage_improvement,
    reprojection_error,
    reprojection_errors,
    rpe,
    rpe_pairs,
    shared_error,
    trajectory_metrics,
    umeyama_alignment,
)

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core import filters, sync  # noqa: E402
from evo.tools import file_interface  # noqa: E402

TOL = 1e-6  # ATE and RPE equal evo's to 1e-6
F64 = torch.float64


# ---------------------------------------------------------------- helpers: smooth trajectories, TUM files


def _smooth_trajectory(F: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Jittered ~30 Hz timestamps (F,) and smooth camera-to-world poses (F, 4, 4)."""
    g = torch.Generator().manual_seed(seed)
    ts = 1305031102.0 + np.cumsum(1 / 30 + 0.004 * torch.rand(F, generator=g, dtype=F64).numpy())
    s = torch.linspace(0, 1, F, dtype=F64)[:, None]
    amp, freq, phase = (torch.rand(3, 2, 3, generator=g, dtype=F64) for _ in range(3))
    wave = lambda k: (amp[k] * torch.sin(2 * math.pi * (1 + 2 * freq[k]) * s[..., None] + 6 * phase[k])).sum(1)  # noqa: E731
    pos = 0.8 * wave(0) + s * torch.tensor([1.0, 0.2, -0.5], dtype=F64)
    omega = 0.6 * wave(1)
    return ts, make_T(so3_exp(omega), pos).numpy()


def _perturb(T_gt: np.ndarray, seed: int) -> np.ndarray:
    """Estimate = global rigid offset @ gt @ (slow drift + per-frame noise): alignment matters, RPE is non-zero."""
    g = torch.Generator().manual_seed(seed)
    F = T_gt.shape[0]
    offset = se3_exp(torch.tensor([0.3, -0.2, 0.1, 0.2, -0.4, 0.3], dtype=F64))
    drift = torch.cumsum(0.002 * torch.randn(F, 6, generator=g, dtype=F64), 0)
    noise = 0.01 * torch.randn(F, 6, generator=g, dtype=F64)
    return (offset @ torch.as_tensor(T_gt) @ se3_exp(drift + noise)).numpy()


def _write_tum(path, ts: np.ndarray, T: np.ndarray) -> None:
    q = matrix_to_quat_xyzw(torch.as_tensor(T[:, :3, :3])).numpy()
    rows = np.concatenate([ts[:, None], T[:, :3, 3], q], 1)
    np.savetxt(path, rows, fmt=["%.6f"] + ["%.12f"] * 7, header="timestamp tx ty tz qx qy qz qw")


def _read_tum(path) -> tuple[np.ndarray, np.ndarray]:
    m = np.loadtxt(path)
    R = quat_xyzw_to_matrix(torch.as_tensor(m[:, 4:]))
    return m[:, 0], make_T(R, torch.as_tensor(m[:, 1:4])).numpy()


@pytest.fixture(scope="module")
def tum_pair(tmp_path_factory):
    """gt.txt and est.txt of 120 frames, read back by us (arrays) and by evo (associated PoseTrajectory3D)."""
    d = tmp_path_factory.mktemp("tum")
    ts, T_gt = _smooth_trajectory(120, seed=0)
    _write_tum(d / "gt.txt", ts, T_gt)
    _write_tum(d / "est.txt", ts, _perturb(T_gt, seed=1))
    ts, T_gt = _read_tum(d / "gt.txt")
    _, T_est = _read_tum(d / "est.txt")
    ref = file_interface.read_tum_trajectory_file(str(d / "gt.txt"))
    est = file_interface.read_tum_trajectory_file(str(d / "est.txt"))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    return ts, T_est, T_gt, ref, est


def _evo_ape(ref, est, align: bool) -> tuple[dict, np.ndarray, np.ndarray]:
    est = copy.deepcopy(est)
    R, t = np.eye(3), np.zeros(3)
    if align:
        R, t, _ = est.align(ref, correct_scale=False)  # evo_ape -a
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    return ape.get_all_statistics(), ape.error, make_T(torch.as_tensor(R), torch.as_tensor(t)).numpy()


def _evo_rpe(ref, est, relation, delta, unit, all_pairs=False):
    r = evo_metrics.RPE(relation, delta=delta, delta_unit=unit, all_pairs=all_pairs)
    r.process_data((ref, est))
    return r.get_all_statistics(), r.error


# ---------------------------------------------------------------- Umeyama


def test_umeyama_recovers_known_se3_and_sim3():
    g = torch.Generator().manual_seed(3)
    src = torch.randn(50, 3, generator=g, dtype=F64)
    R = so3_exp(torch.tensor([0.4, -1.1, 2.0], dtype=F64))
    t = torch.tensor([0.5, -2.0, 1.5], dtype=F64)
    res = umeyama_alignment(src, src @ R.T + t)
    torch.testing.assert_close(res.R, R, rtol=0, atol=1e-12)
    torch.testing.assert_close(res.t, t, rtol=0, atol=1e-12)
    assert float(res.s) == 1.0
    res = umeyama_alignment(src, 2.5 * src @ R.T + t, with_scale=True)
    torch.testing.assert_close(res.R, R, rtol=0, atol=1e-12)
    torch.testing.assert_close(res.s, torch.tensor(2.5, dtype=F64), rtol=0, atol=1e-12)
    torch.testing.assert_close(res.t, t, rtol=0, atol=1e-12)


@pytest.mark.equivalence
def test_umeyama_reflection_is_excluded_and_batched_equals_looped():
    g = torch.Generator().manual_seed(4)
    src = torch.randn(4, 30, 3, generator=g, dtype=F64)
    dst = src * torch.tensor([1.0, 1.0, -1.0], dtype=F64) + 0.01 * torch.randn(4, 30, 3, generator=g, dtype=F64)
    batched = umeyama_alignment(src, dst)
    torch.testing.assert_close(torch.det(batched.R), torch.ones(4, dtype=F64))
    for b in range(4):
        one = umeyama_alignment(src[b], dst[b])
        torch.testing.assert_close(batched.R[b], one.R)
        torch.testing.assert_close(batched.t[b], one.t)


def test_umeyama_bad_input():
    with pytest.raises(ValueError, match="umeyama_alignment"):
        umeyama_alignment(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match="umeyama_alignment"):
        umeyama_alignment(np.zeros((5, 2)), np.zeros((5, 2)))


# ---------------------------------------------------------------- ATE / RPE against evo


@pytest.mark.parametrize("align", [True, False])
def test_ate_equals_evo(tum_pair, align):
    _, T_est, T_gt, ref, est = tum_pair
    stats, errors, T_align = _evo_ape(ref, est, align)
    res = ate(T_est, T_gt, align=align)
    assert res.errors.shape == (120,) and res.T_align.shape == (4, 4)
    np.testing.assert_allclose(res.errors.numpy(), errors, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.T_align.numpy(), T_align, rtol=0, atol=TOL)
    ours = (res.rmse_m, res.mean, res.median, res.max)
    np.testing.assert_allclose(ours, [stats[k] for k in ("rmse", "mean", "median", "max")], rtol=0, atol=TOL)
    assert res.rmse_m > 0.01  # the perturbation is not trivially aligned away


@pytest.mark.parametrize(
    "delta, unit, all_pairs",
    [(1, "frames", False), (5, "frames", False), (5, "frames", True), (0.4, "meters", False), (0.4, "meters", True)],
)
def test_rpe_equals_evo(tum_pair, delta, unit, all_pairs):
    _, T_est, T_gt, ref, est = tum_pair
    evo_unit = {"frames": evo_metrics.Unit.frames, "meters": evo_metrics.Unit.meters}[unit]
    rel = evo_metrics.PoseRelation
    st, et = _evo_rpe(ref, est, rel.translation_part, delta, evo_unit, all_pairs)
    sr, er = _evo_rpe(ref, est, rel.rotation_angle_deg, delta, evo_unit, all_pairs)
    res = rpe(T_est, T_gt, delta=delta, unit=unit, all_pairs=all_pairs)
    assert res.trans_errors.shape == res.rot_errors_deg.shape == (len(et),) and res.pairs.shape == (len(et), 2)
    np.testing.assert_allclose(res.trans_errors.numpy(), et, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.rot_errors_deg.numpy(), er, rtol=0, atol=TOL)
    ours = [res.trans_rmse_m, res.trans_mean_m, res.rot_rmse_deg, res.rot_mean_deg]
    np.testing.assert_allclose(ours, [st["rmse"], st["mean"], sr["rmse"], sr["mean"]], rtol=0, atol=TOL)


@pytest.mark.parametrize("delta, all_pairs", [(0.1, False), (0.5, False), (0.5, True)])
def test_rpe_seconds_equals_evo_path_rule_on_time(tum_pair, monkeypatch, delta, all_pairs):
    """evo has no time unit: its path-length pair rule run on poses at (t, 0, 0) selects pairs by elapsed time."""
    ts, T_est, T_gt, ref, est = tum_pair
    time_poses = [make_T(torch.eye(3, dtype=F64), torch.tensor([t - ts[0], 0, 0], dtype=F64)).numpy() for t in ts]
    pairs = filters.filter_pairs_by_path(time_poses, delta, delta * 0.1, all_pairs)
    monkeypatch.setattr(evo_metrics, "id_pairs_from_delta", lambda *a, **k: pairs)
    rel = evo_metrics.PoseRelation
    st, et = _evo_rpe(ref, est, rel.translation_part, 1, evo_metrics.Unit.frames)
    sr, er = _evo_rpe(ref, est, rel.rotation_angle_deg, 1, evo_metrics.Unit.frames)
    res = rpe(T_est, T_gt, delta=delta, unit="seconds", timestamps=ts, all_pairs=all_pairs)
    assert res.pairs.tolist() == [list(p) for p in pairs]
    np.testing.assert_allclose(res.trans_errors.numpy(), et, rtol=0, atol=TOL)
    np.testing.assert_allclose(res.rot_errors_deg.numpy(), er, rtol=0, atol=TOL)
    np.testing.assert_allclose([res.trans_rmse_m, res.rot_rmse_deg], [st["rmse"], sr["rmse"]], rtol=0, atol=TOL)


def test_rpe_seconds_on_uniform_stamps_equals_frames():
    """At exactly 30 Hz, delta = 0.1 s is 3 frames although 3 * (1/30) rounds below 0.1."""
    _, T_gt = _smooth_trajectory(40, seed=5)
    T_est = _perturb(T_gt, seed=6)
    ts = 1305031102.0 + np.arange(40) / 30
    by_time = rpe(T_est, T_gt, delta=0.1, unit="seconds", timestamps=ts)
    by_frames = rpe(T_est, T_gt, delta=3, unit="frames")
    assert by_time.pairs.tolist() == by_frames.pairs.tolist() == [[i, i + 3] for i in range(0, 37, 3)]
    torch.testing.assert_close(by_time.trans_errors, by_frames.trans_errors)


def test_rpe_is_zero_for_a_rigidly_moved_copy_and_pairs_by_hand():
    _, T_gt = _smooth_trajectory(12, seed=7)
    T_est = se3_exp(torch.tensor([1.0, 2.0, 3.0, 0.5, -0.5, 1.0], dtype=F64)) @ torch.as_tensor(T_gt)
    res = rpe(T_est, T_gt, delta=2)
    assert res.trans_rmse_m < 1e-12 and res.rot_rmse_deg < 1e-6
    assert rpe_pairs(T_gt, 5).tolist() == [[0, 5], [5, 10]]
    assert rpe_pairs(T_gt, 10, all_pairs=True).tolist() == [[0, 10], [1, 11]]


def test_trajectory_metrics_equals_evo_with_missing_gt(tmp_path):
    """gt.txt lacks every 7th frame: evo associates, we mask with gt_valid (NaN rows must be ignored)."""
    ts, T_gt = _smooth_trajectory(90, seed=8)
    T_est = _perturb(T_gt, seed=9)
    keep = np.arange(90) % 7 != 3
    _write_tum(tmp_path / "gt.txt", ts[keep], T_gt[keep])
    _write_tum(tmp_path / "est.txt", ts, T_est)
    ref = file_interface.read_tum_trajectory_file(str(tmp_path / "gt.txt"))
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "est.txt"))
    ref, est = sync.associate_trajectories(ref, est, max_diff=0.01)
    ts, T_est = _read_tum(tmp_path / "est.txt")
    T_gt_full = np.full((90, 4, 4), np.nan)
    T_gt_full[keep] = _read_tum(tmp_path / "gt.txt")[1]
    out = trajectory_metrics(ts, T_est, T_gt_full, gt_valid=keep)
    rel = evo_metrics.PoseRelation
    ape, _, _ = _evo_ape(ref, est, align=True)
    rt, _ = _evo_rpe(ref, est, rel.translation_part, 1, evo_metrics.Unit.frames)
    rr, _ = _evo_rpe(ref, est, rel.rotation_angle_deg, 1, evo_metrics.Unit.frames)
    assert out["frames_with_gt"] == int(keep.sum())
    ours = [out[k] for k in ("ate_rmse_m", "rpe_trans_m", "rpe_rot_deg", "rpe_trans_mean_m", "rpe_rot_mean_deg")]
    np.testing.assert_allclose(ours, [ape["rmse"], rt["rmse"], rr["rmse"], rt["mean"], rr["mean"]], rtol=0, atol=TOL)


def test_trajectory_metrics_too_few_frames_gives_none():
    _, T = _smooth_trajectory(5, seed=10)
    out = trajectory_metrics(np.arange(5.0), T, T, gt_valid=[True, False, False, False, False])
    assert out["frames_with_gt"] == 1 and out["ate_rmse_m"] is None and out["rpe_trans_m"] is None


def test_ate_rpe_bad_input():
    _, T = _smooth_trajectory(10, seed=11)
    with pytest.raises(ValueError, match="same frames"):
        ate(T, T[:9])
    with pytest.raises(ValueError, match=r"\(F, 4, 4\)"):
        ate(T[:, :3], T[:, :3])
    bad = T.copy()
    bad[2, 0, 3] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        rpe(bad, T)
    with pytest.raises(ValueError, match="no pair"):
        rpe(T, T, delta=10)
    with pytest.raises(ValueError, match="unit"):
        rpe(T, T, unit="parsecs")
    with pytest.raises(ValueError, match="timestamps"):
        rpe(T, T, delta=0.1, unit="seconds")
    with pytest.raises(ValueError, match="integer"):
        rpe(T, T, delta=1.5)


# ---------------------------------------------------------------- per-axis errors


def test_per_axis_errors_known_perturbation():
    angles = torch.tensor([[0.1, 0.2, 0.3], [-0.5, 0.4, 3.1]], dtype=F64)
    d_angles = torch.tensor([[0.01, -0.02, 0.03], [0.0, 0.0, 0.1]], dtype=F64)  # 3.1 + 0.1 wraps past pi
    t = torch.tensor([[0.1, 0.2, 1.0], [0.0, 0.0, 2.0]], dtype=F64)
    d_t = torch.tensor([[0.001, -0.002, 0.003], [0.0, 0.05, 0.0]], dtype=F64)
    T_gt = pose_from_euler(torch.cat([angles, t], -1))
    T_est = pose_from_euler(torch.cat([angles + d_angles, t + d_t], -1))
    res = per_axis_errors(T_est, T_gt)
    torch.testing.assert_close(res.rot_deg, torch.rad2deg(d_angles.abs()), rtol=0, atol=1e-9)
    torch.testing.assert_close(res.trans_m, d_t.abs(), rtol=0, atol=1e-12)
    torch.testing.assert_close(res.rot_mean_deg, torch.rad2deg(d_angles.abs()).mean(0), rtol=0, atol=1e-9)
    torch.testing.assert_close(res.trans_mean_m, d_t.abs().mean(0), rtol=0, atol=1e-12)


# ---------------------------------------------------------------- eq. (16) reprojection error


def _scene(B=3, N=20, seed=12):
    g = torch.Generator().manual_seed(seed)
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=F64).expand(B, 3, 3)
    X = torch.rand(B, N, 3, generator=g, dtype=F64) - 0.5  # object points around its origin
    T = make_T(
        euler_to_matrix(0.3 * torch.randn(B, 3, generator=g, dtype=F64)),
        torch.tensor([0.0, 0.0, 2.0], dtype=F64).expand(B, 3),
    )
    return K, T, X, project(K, transform_points(T, X))


def test_reprojection_error_zero_for_exact_projection_and_known_offset():
    K, T, X, x = _scene()
    torch.testing.assert_close(reprojection_error(K, T, X, x), torch.zeros(3, dtype=F64), rtol=0, atol=1e-9)
    offset = torch.tensor([3.0, 4.0], dtype=F64)  # a 5-pixel shift of every observation
    torch.testing.assert_close(reprojection_error(K, T, X, x + offset), torch.full((3,), 5.0, dtype=F64))


@pytest.mark.equivalence
def test_reprojection_error_mask_and_batched_equals_looped():
    K, T, X, x = _scene()
    shift = torch.zeros_like(x)
    shift[:, :5, 0] = 2.0  # features 0..4 are 2 px off, 5..9 are 100 px off but invalid
    shift[:, 5:10, 1] = 100.0
    valid = torch.ones(3, 20, dtype=torch.bool)
    valid[:, 5:10] = False
    valid[2] = False
    e = reprojection_error(K, T, X, x + shift, valid)
    torch.testing.assert_close(e[:2], torch.full((2,), 2.0 * 5 / 15, dtype=F64))
    assert torch.isnan(e[2])
    per = reprojection_errors(K, T, X, x + shift, valid)
    assert per.shape == (3, 20) and bool((per[~valid] == 0).all())
    looped = torch.stack([reprojection_error(K[b], T[b], X[b], (x + shift)[b], valid[b]) for b in range(2)])
    torch.testing.assert_close(e[:2], looped)


def test_reprojection_error_bad_input():
    K, T, X, x = _scene()
    with pytest.raises(ValueError, match="same"):
        reprojection_error(K, T, X, x[:, :10])
    with pytest.raises(ValueError, match="valid"):
        reprojection_error(K, T, X, x, torch.ones(3, 19, dtype=torch.bool))
    with pytest.raises(ValueError, match="T_cam_obj"):
        reprojection_error(K, T[:, :3], X, x)


def test_reprojection_error_pose_inverse_consistency():
    """Observations made from T; evaluating the inverse-of-inverse pose is exact, a 1 cm shift is not."""
    K, T, X, x = _scene(B=1)
    assert float(reprojection_error(K, T_inv(T_inv(T)), X, x)) < 1e-9
    T_off = T.clone()
    T_off[..., 0, 3] += 0.01
    expected = (x - project(K, transform_points(T_off, X))).norm(dim=-1).mean(-1)
    torch.testing.assert_close(reprojection_error(K, T_off, X, x), expected)


# ---------------------------------------------------------------- eq. (17) percentage improvement


def test_percentage_improvement_by_hand():
    assert percentage_improvement(2.24, 3.38) == pytest.approx(100 * 1.14 / 3.38)  # Table III, Book vs ICP
    assert percentage_improvement(4.0, 2.0) == pytest.approx(-100.0)
    out = percentage_improvement(np.array([1.0, 3.0]), np.array([2.0, 4.0]))
    torch.testing.assert_close(out, torch.tensor([50.0, 25.0], dtype=F64))
    with pytest.raises(ValueError, match="baseline"):
        percentage_improvement(1.0, 0.0)


# ---------------------------------------------------------------- shared error of two estimates


def _with_position_noise(T: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    out = T.clone()
    out[:, :3, 3] += noise
    return out


def test_shared_error_of_identical_estimates_is_their_error():
    _, T_gt = _smooth_trajectory(200, seed=11)
    T_gt = torch.as_tensor(T_gt)
    T = torch.as_tensor(_perturb(T_gt.numpy(), seed=12))
    s = shared_error(T, T, T_gt)
    assert s.ate_m == pytest.approx(ate(T, T_gt).rmse_m, rel=1e-12)
    assert s.rpe_trans_m == pytest.approx(rpe(T, T_gt).trans_rmse_m, rel=1e-12)


def test_shared_error_recovers_the_common_part_only():
    """e_a = c + n_a, e_b = c + n_b with independent noises: the shared part is the error of GT + c alone."""
    F = 4000
    _, T_gt = _smooth_trajectory(F, seed=13)
    T_gt = torch.as_tensor(T_gt)
    g = torch.Generator().manual_seed(14)
    c, n_a, n_b = (0.002 * torch.randn(F, 3, generator=g, dtype=F64) for _ in range(3))
    T_c = _with_position_noise(T_gt, c)
    s = shared_error(_with_position_noise(T_gt, c + n_a), _with_position_noise(T_gt, c + n_b), T_gt)
    assert s.rpe_trans_m == pytest.approx(rpe(T_c, T_gt).trans_rmse_m, rel=0.05)
    assert s.ate_m == pytest.approx(ate(T_c, T_gt).rmse_m, rel=0.05)
    independent = shared_error(_with_position_noise(T_gt, n_a), _with_position_noise(T_gt, n_b), T_gt)
    assert independent.rpe_trans_m < 0.2 * rpe(T_c, T_gt).trans_rmse_m  # nothing in common: ~0


def test_shared_error_reports_each_estimates_scale():
    _, T_gt = _smooth_trajectory(100, seed=15)
    T_gt = torch.as_tensor(T_gt)
    big = T_gt.clone()
    big[:, :3, 3] *= 1.1
    s = shared_error(big, T_gt, T_gt)
    assert s.scale_a == pytest.approx(1 / 1.1, abs=1e-9) and s.scale_b == pytest.approx(1.0, abs=1e-9)
