"""Training learned weighting through the fusion EKF: the known-optimal weighting is recovered (oracle windows with
var_xyz ~ z^4 and 10 % of the features at 400x the pixel variance), and the loop is deterministic and resumable."""

import math

import pytest
import torch

from torchtrack.filter import FixedWeighting
from torchtrack.filter.fusion import FusionEKF
from torchtrack.learn.checkpoint import load_checkpoint
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.oracle import TrueVariances, class_ratios, oracle_windows
from torchtrack.learn.rollout import pose_errors, rollout
from torchtrack.learn.train import TrainConfig, fit

T = 4


@pytest.fixture(scope="module")
def data():
    return oracle_windows(B=256, T=T, N=40, seed=0), oracle_windows(B=128, T=T, N=40, seed=1)


def mean_trans_error_mm(ekf, weighting, oracle):
    with torch.no_grad():
        out = rollout(ekf, weighting, oracle.windows)
    return 1e3 * float(pose_errors(out.T_cam_obj, oracle.windows.T_cam_obj_gt)[0].mean())


def train(train_set, loss, mode, epochs=25, **kw):
    ekf = FusionEKF(jacobian="analytic")
    torch.manual_seed(0)
    model = LearnedWeighting(mode=mode, depth_var_exponent=0.0)
    cfg = TrainConfig(window=T, batch=32, epochs=epochs, lr=1e-2, loss=loss, gate=None, refit=None, **kw)
    fit(model, ekf, train_set.windows, cfg, progress=False)
    return ekf, model


def learned_ratios(model, test):
    with torch.no_grad():
        v = model(test.windows.weighting_inputs(0))
    return class_ratios(v.var_pix, v.var_xyz, test.flagged, test.windows.points_d[0][..., 2]), v


def test_nll_recovers_the_true_variances(data):
    """Self-supervised (innovation likelihood, absolute variances): the flagged/unflagged pixel-variance ratio
    (true 400) within a factor 1.6, the depth exponent (true 4) within 0.6, the absolute pixel variance (true
    0.25 px^2) within 25 %, and the pose error within 5 % of the filter given the true variances. Measured with
    initialisation seeds 0-3 (25 epochs): ratios 396-432, exponents 3.44-4.02, variances 0.24-0.28; seed 3 at 40
    epochs: 262 — minibatch noise, hence the tolerances. Pose error seed 0: 0.556 vs the oracle's 0.557 mm."""
    train_set, test = data
    ekf, model = train(train_set, "nll", "absolute")
    ratios, v = learned_ratios(model, test)
    assert 400 / 1.6 < ratios["pix_flag_ratio"] < 400 * 1.6
    assert abs(ratios["xyz_depth_exponent"] - 4.0) < 0.6
    assert 0.25 / 1.25 < float(v.var_pix[~test.flagged].mean()) < 0.25 * 1.25
    oracle = mean_trans_error_mm(ekf, TrueVariances(test), test)
    assert mean_trans_error_mm(ekf, model, test) < 1.05 * oracle


def test_supervised_pose_loss_recovers_the_ratios(data):
    """Supervised (pose error, normalised variances): the depth exponent within 0.5 of 4; the flagged features
    down-weighted at least half as much as the truth (the pose loss bounds the ratio only from below: once they
    carry no weight, more changes nothing; measured 3700); the pose error within 15 % of the oracle's (measured
    0.61 vs 0.56 mm) and under half of fixed variances' (2.05 mm)."""
    train_set, test = data
    ekf, model = train(train_set, "supervised", "normalised")
    ratios, _ = learned_ratios(model, test)
    assert abs(ratios["xyz_depth_exponent"] - 4.0) < 0.5
    assert ratios["pix_flag_ratio"] > 200
    learned = mean_trans_error_mm(ekf, model, test)
    assert learned < 1.15 * mean_trans_error_mm(ekf, TrueVariances(test), test)
    assert learned < 0.5 * mean_trans_error_mm(ekf, FixedWeighting(1.0, 4e-6), test)


def test_deterministic_and_resume_equals_straight_run(tmp_path):
    """Two epochs, stop, resume to four == four straight (same seed), bit for bit; the run folder has the metrics,
    the loss curve and both checkpoints, and best.pt is the epoch with the lowest validation loss."""
    small = oracle_windows(B=64, T=3, N=20, seed=3)
    val = oracle_windows(B=32, T=3, N=20, seed=4)
    ekf = FusionEKF(jacobian="analytic")

    def run(out, epochs):
        torch.manual_seed(5)  # the initial weights
        model = LearnedWeighting(mode="absolute", depth_var_exponent=0.0)
        cfg = TrainConfig(window=3, batch=16, epochs=epochs, lr=1e-2, loss="nll", gate=None, refit=None, seed=5)
        return model, fit(model, ekf, small.windows, cfg, val=val.windows, out_dir=out, progress=False)

    straight, hist = run(tmp_path / "a", 4)
    run(tmp_path / "b", 2)
    resumed, hist_b = run(tmp_path / "b", 4)
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert [h["epoch"] for h in hist_b] == [1, 2, 3, 4]
    assert [h["val_loss"] for h in hist_b] == [h["val_loss"] for h in hist]
    for name in ("metrics.csv", "loss.png", "last.pt", "best.pt"):
        assert (tmp_path / "b" / name).is_file()
    rows = (tmp_path / "b" / "metrics.csv").read_text().splitlines()
    assert len(rows) == 5 and rows[0].startswith("epoch,")
    _, meta = load_checkpoint(tmp_path / "b" / "best.pt")
    best_epoch = min(hist, key=lambda h: h["val_loss"])["epoch"]
    assert meta["epoch"] == best_epoch


def test_bad_config_raises():
    with pytest.raises(ValueError, match="loss"):
        TrainConfig(loss="mse")
    with pytest.raises(ValueError, match="window"):
        TrainConfig(window=0)


def test_burn_in_scores_only_the_frames_after_it():
    """burn_in = k: the batch replays all k + window frames from the window's start and the loss is the NLL per
    measurement of the last ``window`` frames only (the definition, on the rollout's own numbers); its counts too."""
    from torchtrack.learn.rollout import nll_loss
    from torchtrack.learn.train import window_loss

    oracle = oracle_windows(B=8, T=5, N=20, seed=6)
    ekf, model = FusionEKF(jacobian="analytic"), LearnedWeighting(mode="absolute", depth_var_exponent=0.0)
    cfg = TrainConfig(window=3, burn_in=2, loss="nll", gate=None, refit=None)
    assert cfg.span == 5
    with torch.no_grad():
        out = rollout(ekf, model, oracle.windows, with_nll=True)
        loss, sums = window_loss(ekf, model, oracle.windows, cfg)
        whole = window_loss(ekf, model, oracle.windows, TrainConfig(window=5, loss="nll", gate=None, refit=None))[0]
    tail = out.nll[2:].sum() / out.n_used[2:].sum()
    assert float(loss) == pytest.approx(float(tail), rel=1e-12) and float(whole) == pytest.approx(float(nll_loss(out)))
    assert sums["loss"][1] == float(out.n_used[2:].sum()) and abs(float(tail) - float(whole)) > 1e-3
    with pytest.raises(ValueError, match="burn_in"):
        TrainConfig(burn_in=-1)


def test_ground_truth_start_velocity_carries_the_previous_pose_to_the_start():
    """train.start_velocity=ground_truth: the start velocity is the one the filter's constant-velocity motion
    (eqs. 3-4) needs to move the previous frame's pose onto the start pose in prev_dt (oracle windows: a constant
    twist, so the previous pose is exact); zero where prev_dt is 0; the rollout starts with it."""
    from torchtrack.geometry import make_T, so3_exp
    from torchtrack.learn.rollout import window_start_velocity

    win = oracle_windows(B=6, T=2, N=10, seed=7).windows
    win.prev_dt[0] = 0.0
    A = make_T(so3_exp(torch.tensor([0.4, -0.7, 0.2], dtype=torch.float64)), torch.tensor([0.1, 0.0, -0.05]).double())
    win.prev_T_cam_obj, win.start_T_cam_obj = win.prev_T_cam_obj @ A, win.start_T_cam_obj @ A  # another object frame
    for state in ("se3", "euler"):
        ekf = FusionEKF(jacobian="analytic", state=state)
        vel = window_start_velocity(ekf, win)
        assert float(vel[0].abs().max()) == 0.0 and float(vel[1:].abs().min()) > 0
        moved = ekf.predicted(ekf.initial_state(win.prev_T_cam_obj, vel), win.prev_dt).T_cam_obj
        assert torch.allclose(moved[1:], win.start_T_cam_obj[1:], atol=1e-12), state
    with pytest.raises(ValueError, match="start_velocity"):
        TrainConfig(start_velocity="gt")


def test_previous_pose_from_the_depth_camera_ground_truth():
    """The pose one frame before a window's start, in the start's object frame: the object fixed in the world at W,
    the depth camera's ground truth G = T_world_color @ T_color_depth, so it is inv(G[s-1]) @ W exactly; the start
    pose and 0 s at frame 0 and where ground truth is missing."""
    from types import SimpleNamespace

    from torchtrack.geometry import T_inv, make_T, so3_exp
    from torchtrack.learn.train import _previous_pose

    g = torch.Generator().manual_seed(0)
    F = torch.float64
    poses = make_T(so3_exp(0.3 * torch.randn(6, 3, generator=g, dtype=F)), torch.randn(6, 3, generator=g, dtype=F))
    T_cd = make_T(so3_exp(torch.tensor([0.01, -0.02, 0.005], dtype=F)), torch.tensor([0.025, 0.0, 0.001], dtype=F))
    W = make_T(so3_exp(torch.tensor([0.2, 0.1, -0.3], dtype=F)), torch.tensor([0.1, -0.2, 1.5], dtype=F))
    gt_valid = torch.tensor([True, True, True, False, True, True])
    seq = SimpleNamespace(T_world_color_gt=poses, T_color_depth=T_cd, gt_valid=gt_valid,
                          dt=torch.tensor([0.0, 0.03, 0.04, 0.03, 0.05, 0.03], dtype=F))  # fmt: skip
    G = poses @ T_cd
    s = torch.tensor([0, 1, 2, 4, 5])
    start = T_inv(G[s]) @ W
    prev, dt = _previous_pose(seq, s, start)
    assert torch.allclose(prev[[1, 2, 4]], (T_inv(G) @ W)[[0, 1, 4]], atol=1e-12)
    assert torch.equal(prev[[0, 3]], start[[0, 3]]) and dt.tolist() == [0.0, 0.03, 0.04, 0.0, 0.03]


def test_residual_nll_at_the_ground_truth_pose_matches_its_expectation():
    """The heteroscedastic residual likelihood under the true variances of oracle windows (Gaussian noise of known
    variance around eqs. 6-7 at the exact pose): r^2 / var is chi-square, so the NLL per measurement is, in
    expectation, sum 0.5 (dof + dof log(2 pi var)) / 5 per feature; 25,600 measurements: within 1 %. Frames without
    ground truth are not counted; a negative weight is refused."""
    from torchtrack.geometry import make_T, project, so3_exp, transform_points
    from torchtrack.learn.rollout import residual_nll

    oracle = oracle_windows(B=32, T=4, N=40, seed=8)
    win = oracle.windows  # with a depth -> colour extrinsic: the pixels re-drawn through it, the same noise
    P = transform_points(win.T_cam_obj_gt, win.points_obj)
    T_cd = make_T(so3_exp(torch.tensor([0.02, -0.03, 0.01], dtype=P.dtype)), torch.tensor([0.025, 0.01, 0.0]).double())
    win.T_color_depth = T_cd.expand_as(win.T_color_depth).clone()
    win.pixels = (
        project(win.K[None], transform_points(win.T_color_depth[None], P)) + win.pixels - project(win.K[None], P)
    )
    with torch.no_grad():
        out = rollout(FusionEKF(jacobian="analytic"), TrueVariances(oracle), win)
    total, n = residual_nll(out, win)
    v3, v2 = oracle.var_xyz, oracle.var_pix
    c = math.log(2 * math.pi)
    expect = (0.5 * (3 + 3 * (v3.log() + c)) + 0.5 * (2 + 2 * (v2.log() + c))).sum() / (5 * v3.numel())
    assert int(n) == 5 * v3.numel() and float(total / n) == pytest.approx(float(expect), rel=0.01)
    win.gt_valid[1:] = False
    assert int(residual_nll(out, win)[1]) == 5 * int(win.valid[0].sum())
    with pytest.raises(ValueError, match="residual_weight"):
        TrainConfig(residual_weight=-1.0)


def test_the_recipe_file_and_the_schema_agree():
    """conf/train/default.yaml (the CLI's recipe) and TrainConfig (a direct call's) hold the same values, and its
    model block is LearnedWeighting's defaults: training from Python and from torchtrack-train is the same recipe."""
    import dataclasses
    import inspect

    import yaml

    from torchtrack.config import CONF_DIR
    from torchtrack.learn.model import LearnedWeighting

    recipe = yaml.safe_load((CONF_DIR / "train" / "default.yaml").read_text())
    fields = {f.name: f.default for f in dataclasses.fields(TrainConfig) if f.name != "model"}
    assert {k: v for k, v in recipe.items() if k != "model"} == fields
    params = inspect.signature(LearnedWeighting).parameters
    assert recipe["model"] == {k: params[k].default for k in recipe["model"]}
