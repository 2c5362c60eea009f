"""The combined intensity + SIM tracker (paper §III-C, eq. (10)).

Oracles: images where one channel is blank (uniform) and the other textured, so that the tracker must
pick the textured one, with exact ground truth from an analytic texture; OpenCV's LK (tests/opencv_flow.py) on real
frames; batched equals looped (within tests/tolerances.py); the class equals the function.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from opencv_flow import combined_track_opencv
from test_lk import texture
from tolerances import LK_PX, TIM_PX

from torchtrack.image.flow import CombinedTracker, FlowFrame, TrackResult, combined_track, prepare_frame

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TRACKERS = {"torchtrack": combined_track, "opencv": combined_track_opencv}  # the same steps III-IV on either LK
H, W = 240, 320


def split_scene(t: tuple[float, float], seed: int = 0):
    """Frames shifted by t; intensity is textured on the left half and blank on the right, SIM the reverse.

    Returns prev and next FlowFrames, points (1, 2n, 2) (n left, then n right) and their true positions.
    """
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    left = xx < W / 2

    def render(dx, dy):
        gray = np.where(left, texture(xx - dx, yy - dy, seed), 0.5)
        sim = np.where(left, 0.5, texture(xx - dx, yy - dy, seed + 7))
        return [torch.tensor(a, dtype=torch.float32)[None, None] for a in (gray, sim)]

    g = np.random.default_rng(seed + 1)
    n = 40
    xs = np.concatenate([g.uniform(30, W / 2 - 30, n), g.uniform(W / 2 + 30, W - 30, n)])
    pts = np.stack([xs, g.uniform(30, H - 30, 2 * n)], -1)
    f0, f1 = prepare_frame(*render(0.0, 0.0)), prepare_frame(*render(*t))
    return f0, f1, torch.tensor(pts, dtype=torch.float32)[None], pts + np.array(t)


# ---------------------------------------------------------------------------------------------- smoke, errors
def test_smoke_shapes_and_prepare():
    f0, f1, pts, _ = split_scene((0.7, -0.4))
    assert isinstance(f0, FlowFrame) and f0.has_sim and f0.batch == 1
    assert f0.pyramid.batch == 2 and [x.shape for x in f0.images] == [(1, 1, H, W)] * 2  # intensity and SIM
    res = combined_track(f0, f1, pts)
    assert isinstance(res, TrackResult)
    for x in (res.valid, res.d_tim, res.d_tim_int, res.d_tim_sim, res.winner, res.status_int, res.status_sim):
        assert x.shape == (1, 80)
    assert res.points.shape == (1, 80, 2) and res.winner.dtype == torch.int64 and res.valid.dtype == torch.bool


def test_bad_input_raises():
    f0, f1, pts, _ = split_scene((0.5, 0.5))
    gray_only = prepare_frame(f0.images[0])
    with pytest.raises(ValueError, match="mode"):
        combined_track(f0, f1, pts, mode="depth")
    with pytest.raises(ValueError, match="SIM"):
        combined_track(gray_only, gray_only, pts, mode="combined")
    with pytest.raises(ValueError, match="points must be"):
        combined_track(f0, f1, pts[0])
    with pytest.raises(ValueError, match="valid must be"):
        combined_track(f0, f1, pts, torch.ones(1, 3, dtype=torch.bool))
    with pytest.raises(ValueError, match="policy"):
        combined_track(f0, f1, pts, policy="max_tim")
    with pytest.raises(ValueError, match="window"):
        combined_track(f0, f1, pts, window=41)
    with pytest.raises(ValueError, match="gray must be"):
        prepare_frame(torch.zeros(1, 3, 8, 8))
    with pytest.raises(ValueError, match="sim must match"):
        prepare_frame(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 9))


# ---------------------------------------------------------------------------------------------- steps I-IV
@pytest.mark.parametrize("lk", ["torchtrack", "opencv"])
def test_picks_the_tracker_with_smaller_tim(lk):
    """Left half: intensity textured, SIM blank (degenerate): intensity must win. Right half: the reverse."""
    f0, f1, pts, true = split_scene((1.6, -0.8))
    res = TRACKERS[lk](f0, f1, pts)
    assert (res.winner[0, :40] == 0).all() and (res.winner[0, 40:] == 1).all()
    assert res.status_int[0, :40].all() and not res.status_int[0, 40:].any()
    assert res.status_sim[0, 40:].all() and not res.status_sim[0, :40].any()
    assert torch.isinf(res.d_tim_sim[0, :40]).all() and torch.isinf(res.d_tim_int[0, 40:]).all()
    torch.testing.assert_close(res.d_tim, torch.minimum(res.d_tim_int, res.d_tim_sim))  # step III
    assert res.valid.all()
    err = np.linalg.norm(res.points[0].numpy() - true, axis=1)
    assert np.median(err) <= 0.03 and err.max() <= 0.1


def test_winner_is_argmin_where_both_track():
    """Both channels textured: the winner's d_TIM is the smaller one and its point is that tracker's."""
    f0, f1, pts, _ = split_scene((0.9, 0.3))
    both0 = prepare_frame(f0.images[0] + f0.images[1] - 0.5, f0.images[1] + f0.images[0] - 0.5)
    both1 = prepare_frame(f1.images[0] + f1.images[1] - 0.5, f1.images[1] + f1.images[0] - 0.5)
    res = combined_track(both0, both1, pts, policy="min_tim")  # the paper's step III (the default is fallback)
    ok = res.status_int & res.status_sim
    assert ok.sum() > 60
    expect = (res.d_tim_sim < res.d_tim_int).long()
    assert (res.winner[ok] == expect[ok]).all()
    only_int = combined_track(both0, both1, pts, mode="intensity")
    only_sim = combined_track(both0, both1, pts, mode="sim")
    chosen = torch.where((res.winner == 1)[..., None], only_sim.points, only_int.points)
    torch.testing.assert_close(res.points[res.valid], chosen[res.valid])


@pytest.mark.parametrize("lk", ["torchtrack", "opencv"])
def test_fallback_policy_uses_sim_only_where_intensity_fails(lk):
    """The intensity result wherever it passes the TIM test, the SIM result only where it does not; the SIM
    tracker is not even run on the others (d_TIM_SIM = inf). Left half: intensity textured; right: SIM."""
    f0, f1, pts, _ = split_scene((0.9, 0.3))
    track = TRACKERS[lk]
    res = track(f0, f1, pts, policy="fallback")
    only_int = track(f0, f1, pts, mode="intensity")
    only_sim = track(f0, f1, pts, mode="sim")
    int_ok = only_int.valid
    assert int_ok[0, :40].all() and not int_ok[0, 40:].any()
    assert (res.winner[int_ok] == 0).all() and torch.isinf(res.d_tim_sim[int_ok]).all()
    torch.testing.assert_close(res.points[int_ok], only_int.points[int_ok])
    rescued = ~int_ok & only_sim.valid
    assert rescued.any() and (res.winner[rescued] == 1).all() and res.valid[rescued].all()
    torch.testing.assert_close(res.points[rescued], only_sim.points[rescued])
    assert (res.valid == (int_ok | only_sim.valid)).all()


def test_threshold_and_single_tracker_modes():
    f0, f1, pts, _ = split_scene((2.2, 1.1))
    full = combined_track(f0, f1, pts, tim_threshold=1.0, policy="min_tim")  # both trackers run on every feature
    thr = float(full.d_tim[full.valid].median())
    cut = combined_track(f0, f1, pts, tim_threshold=thr, policy="min_tim")  # step IV
    assert (cut.valid == (full.valid & (full.d_tim <= thr))).all() and 0 < cut.valid.sum() < full.valid.sum()
    torch.testing.assert_close(cut.points[~cut.valid], pts[~cut.valid])  # dropped features keep the input
    intensity = CombinedTracker(mode="intensity")(f0, f1, pts)
    assert (intensity.winner == 0).all() and torch.isinf(intensity.d_tim_sim).all() and not intensity.status_sim.any()
    assert intensity.valid[0, :40].all() and not intensity.valid[0, 40:].any()
    sim = CombinedTracker(mode="sim")(f0, f1, pts)
    assert (sim.winner == 1).all() and torch.isinf(sim.d_tim_int).all()
    assert sim.valid[0, 40:].all() and not sim.valid[0, :40].any()
    gray_only = combined_track(prepare_frame(f0.images[0]), prepare_frame(f1.images[0]), pts, mode="intensity")
    torch.testing.assert_close(gray_only.points, intensity.points)


def test_identical_frames_zero_tim_and_valid_mask():
    f0, _, pts, _ = split_scene((0.0, 0.0))
    valid = torch.ones(1, 80, dtype=torch.bool)
    valid[0, ::3] = False
    res = combined_track(f0, f0, pts, valid)
    assert (res.valid == valid).all()
    assert res.d_tim[valid].max() <= 1e-4 and torch.isinf(res.d_tim[~valid]).all()


def test_no_features_and_no_valid_features():
    f0, f1, pts, _ = split_scene((0.5, 0.5))
    empty = combined_track(f0, f1, pts[:, :0])
    assert empty.points.shape == (1, 0, 2) and empty.valid.shape == (1, 0)
    none = combined_track(f0, f1, pts, torch.zeros(1, 80, dtype=torch.bool))
    assert not none.valid.any() and torch.isinf(none.d_tim).all()
    torch.testing.assert_close(none.points, pts)


# ---------------------------------------------------------------------------------------------- batching, class
@pytest.mark.equivalence
def test_batched_equals_looped_and_class_equals_function():
    scenes = [split_scene(t, seed=s) for s, t in enumerate([(1.2, 0.4), (-0.6, 2.1)])]
    f0 = prepare_frame(torch.cat([s[0].images[0] for s in scenes]), torch.cat([s[0].images[1] for s in scenes]))
    f1 = prepare_frame(torch.cat([s[1].images[0] for s in scenes]), torch.cat([s[1].images[1] for s in scenes]))
    pts = torch.cat([s[2] for s in scenes])
    tracker = CombinedTracker(tim_threshold=0.5)
    batched = tracker(f0, f1, pts)
    torch.testing.assert_close(batched, combined_track(f0, f1, pts, tim_threshold=0.5))
    assert tracker.prepare(scenes[0][0].images[0], scenes[0][0].images[1]).pyramid.batch == 2
    for b, (s0, s1, p, _) in enumerate(scenes):
        one = combined_track(s0, s1, p, tim_threshold=0.5)
        torch.testing.assert_close(batched.points[b], one.points[0], atol=LK_PX, rtol=0)
        torch.testing.assert_close(batched.d_tim[b], one.d_tim[0], atol=TIM_PX, rtol=0)
        assert (batched.valid[b] == one.valid[0]).all() and (batched.winner[b] == one.winner[0]).all()


# ---------------------------------------------------------------------------------------------- real data
@pytest.mark.skipif(not (DATA / "sun3d_fragment1").exists(), reason="needs ../shared/data/sun3d_fragment1")
def test_torch_matches_opencv_on_real_frames():
    """Intensity from colour, SIM from depth (shape_index), 300 Shi-Tomasi corners, frames 0 -> 1."""
    from torchtrack.image.shape_index import compute_sim

    folder = DATA / "sun3d_fragment1"
    rgb = [ln.split()[1] for ln in (folder / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    dep = [ln.split()[1] for ln in (folder / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    fx, fy, cx, cy, scale = map(float, [ln for ln in (folder / "intrinsics.txt").read_text().splitlines()
                                         if not ln.startswith("#")][0].split())  # fmt: skip
    K = torch.tensor([[[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]])
    frames = []
    for i in (0, 1):
        g = cv2.cvtColor(cv2.imread(str(folder / rgb[i])), cv2.COLOR_BGR2GRAY)
        d = cv2.imread(str(folder / dep[i]), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale
        sim = compute_sim(torch.from_numpy(d)[None, None], K).image
        frames.append((g, prepare_frame(torch.from_numpy(g).float()[None, None] / 255.0, sim)))
    pts = torch.from_numpy(cv2.goodFeaturesToTrack(frames[0][0], 300, 0.001, 5).reshape(1, -1, 2))
    ours = combined_track(frames[0][1], frames[1][1], pts)
    ref = combined_track_opencv(frames[0][1], frames[1][1], pts)
    # Intensity: nearly the same accepted set. SIM (low texture, 8-bit steps): ours require convergence and give
    # up on steps that stop shrinking, OpenCV accepts whatever it has after 30 iterations: ours is a subset.
    assert (ours.status_int & ref.status_int).sum() >= 0.95 * ref.status_int.sum()
    assert (ours.status_sim & ~ref.status_sim).sum() <= 0.05 * ref.status_sim.sum()
    both = ours.valid & ref.valid  # measured: 288 of OpenCV's 293 valid, median 0.0006 px, winners 98.6 % equal
    assert both.sum() >= 0.95 * ref.valid.sum()
    assert (ours.winner[both] == ref.winner[both]).float().mean() >= 0.95
    assert (ours.points - ref.points).norm(dim=-1)[both].median() <= 0.1


@pytest.mark.parametrize("lk", ["torchtrack", "opencv"])
def test_init_starts_the_forward_pass_there(lk):
    """init = points is the default exactly; a shift beyond the pyramid's reach (60 px with 2 levels: ~3x the
    coarsest level's window radius) is tracked only when init starts the forward pass near the answer, and d_TIM
    is still measured against the original points (small when tracked)."""
    t = (60.0, 0.0)
    f0, f1, pts, true = split_scene(t)
    track, kw = TRACKERS[lk], dict(mode="intensity", levels=2, window=15)
    torch.testing.assert_close(track(f0, f1, pts, **kw), track(f0, f1, pts, init=pts, **kw))
    inside = torch.from_numpy((true[:, 0] < W - 12) & (true[:, 0] > 12))[None] & (pts[..., 0] < W / 2 - 40)
    lost = track(f0, f1, pts, **kw)
    err0 = np.linalg.norm(lost.points[0].numpy() - true, axis=1)[inside[0].numpy()]
    assert np.median(err0) > 5.0  # without a prior the shift is out of reach
    guess = pts + torch.tensor([t[0] - 2.5, 1.5])
    res = track(f0, f1, pts, init=guess, **kw)
    err = np.linalg.norm(res.points[0].numpy() - true, axis=1)[inside[0].numpy()]
    assert res.valid[inside].float().mean() > 0.8 and np.median(err) < 0.05
    assert res.d_tim[res.valid & inside].median() < 0.01
    with pytest.raises(ValueError, match="init must be"):
        combined_track(f0, f1, pts, init=pts[:, :3], **kw)
