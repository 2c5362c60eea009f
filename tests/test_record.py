"""Recording the front end (torchtrack/learn/record.py, learn/dataset.py) and the tracker's per-feature cues.

Oracles: the back end replayed on the recorded observations reproduces the tracker's poses; the recorded rows are
what the tracker's back end saw in a run that did not record; the cue columns at the literal positions of cue
version 1 (written out here, not read from filter/cues.py), each against an independent computation of its
definition: depth read from the depth PNG, the SI map at the nearest pixel, the fallback policy's d_TIM, age and
eq. (16) residual of the same feature one frame earlier; the LK residual against an independent bilinear sampling
of the final windows.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from PIL import Image
from test_flow import split_scene

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.filter import cues as cue_module
from torchtrack.filter.weighting import PaperWeighting
from torchtrack.image.flow import combined_track
from torchtrack.learn import record
from torchtrack.learn.cache import load_observations
from torchtrack.learn.dataset import synthetic_variants
from torchtrack.learn.record import record_sequences
from torchtrack.pipeline.state import Measure

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

CONF = CONF_DIR

# Cue version 2, written out from the documented layout (filter/cues.py's comments, DESIGN.md "Learned weighting"):
# the literal column of each cue in a recording and in a checkpoint's input. A reorder without a version bump fails.
COL = {
    "d_tim_int": 0, "d_tim_sim": 1, "sim_won": 2, "lk_residual": 3, "depth": 4, "centroid_dist": 5,
    "cornerness_int": 6, "cornerness_sim": 7, "sim_value": 8, "track_age": 9, "prev_reproj": 10, "u_norm": 11,
    "v_norm": 12, "depth_step": 13, "depth_holes": 14, "lk_min_eig": 15, "fb_error": 16,
}  # fmt: skip
D_TIM_CAP = 100.0  # px, "did not track" (cue version 2)
TIM_THRESHOLD = 1.0  # px, the default flow config's step IV of eq. (10) (checked against the config below)


def config(*overrides: str, name: str = "config"):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose(name, overrides=list(overrides))


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> TumSequence:
    """160 x 120, 8 frames, Kinect noise: ~12 features, so the tracker re-selects often (measured: 3 times)."""
    synth = SyntheticConfig(width=160, height=120, frames=8, seed=1, mode="scene", noise="kinect")
    return TumSequence(ensure_sequence(synth, tmp_path_factory.mktemp("synth")))


@pytest.fixture(scope="module")
def recorded(seq, tmp_path_factory):
    (path,) = record_sequences(config(), [seq], tmp_path_factory.mktemp("rec"), progress=False)
    return load_observations(path)


def plain_run(seq, cfg=None):
    """The tracker's StepResults without recording."""
    tracker = build_tracker(cfg or config())
    with torch.inference_mode():
        return [tracker.step(f) for f in iterate_batched([seq], prefetch=False)]


# ---------------------------------------------------------------------------------------------- replay
def test_replay_reproduces_the_tracker(recorded):
    obs = recorded
    assert int(obs.reselected[1:].sum()) >= 1, "the test needs a re-selection after the first frame"
    backend = build_tracker(config()).backend  # a fresh EKFBackend of the recording's config
    backend.reset(obs.model_T_cam_obj[:1], torch.ones(1, dtype=torch.bool))
    for t in range(1, obs.frames):
        T = backend.step(obs.observation(t), obs.variances(t)).T_cam_obj.double()
        torch.testing.assert_close(T[0], obs.T_cam_obj_est[t], atol=1e-9, rtol=0)
        if obs.reselected[t]:  # the new model's start, after this frame's update of the old one
            backend.reset(obs.model_T_cam_obj[t : t + 1], torch.ones(1, dtype=torch.bool))


def test_recorded_rows_are_what_the_back_end_saw_without_recording(seq, recorded):
    """Recording changes nothing: a plain run's observations and poses equal the recorded ones, bit for bit."""
    obs = recorded
    for t, res in enumerate(plain_run(seq)):
        assert torch.equal(res.T_cam_obj[0], obs.T_cam_obj_est[t]) and bool(res.reselected[0] == obs.reselected[t])
        if t == 0:
            assert res.observation is None and not obs.valid[0].any()
            continue
        o, n = res.observation, res.observation.valid.shape[1]
        for name in ("points_obj", "points_d", "pixels", "valid"):
            assert torch.equal(getattr(o, name)[0], getattr(obs, name)[t, :n]), name
            assert not getattr(obs, name)[t, n:].any(), f"{name}: padding must be zeros"
        assert float(o.dt[0]) == float(obs.dt[t]) and torch.equal(res.variances.var_xyz[0], obs.var_xyz[t, :n])
        if res.reselected[0]:
            assert torch.equal(res.model_T_cam_obj[0], obs.model_T_cam_obj[t])
    assert torch.equal(obs.K, seq.K.double()) and float(obs.dt[0]) == 0.0


# ---------------------------------------------------------------------------------------------- cues
def columns(obs) -> dict[str, torch.Tensor]:
    """The recorded cues by name, at the literal column positions of cue version 2 (:data:`COL`)."""
    return {name: obs.cues[..., i] for name, i in COL.items()}


def test_cue_layout_is_version_2():
    """The module's names, index and version against the layout written out above; stack_cues puts each named cue
    in its literal column."""
    assert cue_module.CUE_NAMES == tuple(COL) and cue_module.CUE_VERSION == 2 and cue_module.D_TIM_CAP == D_TIM_CAP
    assert cue_module.CUE_INDEX == COL
    stacked = cue_module.stack_cues(**{name: torch.full((1, 2), float(i)) for name, i in COL.items()})
    assert stacked.shape == (1, 2, 17) and torch.equal(stacked[0, 0], torch.arange(17, dtype=torch.float32))


def test_cues_follow_their_definitions(recorded):
    obs = recorded
    c = columns(obs)
    valid = obs.valid & obs.has_depth  # cues are computed for the features measured with depth
    assert obs.cues.dtype == torch.float32 and bool(torch.isfinite(obs.cues).all())
    assert not obs.cues[~valid].any(), "cues of invalid features are zeros"
    v = valid
    torch.testing.assert_close(c["depth"][v], obs.points_d[..., 2][v], atol=0, rtol=0)
    torch.testing.assert_close(c["u_norm"][v] * 160, obs.pixels[..., 0][v], atol=1e-4, rtol=0)
    torch.testing.assert_close(c["v_norm"][v] * 120, obs.pixels[..., 1][v], atol=1e-4, rtol=0)
    for t in range(1, obs.frames):
        pts = obs.points_d[t][valid[t]].double()
        dist = (pts - pts.mean(0)).norm(dim=-1)
        torch.testing.assert_close(c["centroid_dist"][t][valid[t]].double(), dist, atol=1e-5, rtol=0)
        age = c["track_age"][t][valid[t]]
        assert bool(((age >= 1) & (age <= t)).all()) and bool((age == age.round()).all())
    assert bool((c["track_age"][1][v[1]] == 1).all())  # frame 0 selected every feature of frame 1
    assert bool((c["lk_residual"][v] > 0).all()) and bool((c["lk_residual"][v] < 0.2).all())
    assert bool(((c["cornerness_int"][v] >= 0) & (c["cornerness_int"][v] < 1)).all())
    assert bool((c["prev_reproj"][v & (c["track_age"] == 1)] == 0).all())  # new features have no previous frame
    assert bool((c["prev_reproj"][v] >= 0).all()) and bool((c["prev_reproj"][v] > 0).any())


def depth_at(depth: np.ndarray, u: float, v: float, max_rel_step: float = 0.02) -> float:
    """The depth of eq. (6)'s X_d at colour pixel (u, v), by its documented rule (filter.models.measure_points),
    written out in float64 for one pixel: bilinear over the 2 x 2 neighbours where all four have depth within
    ``max_rel_step`` of their minimum (a continuous surface), the nearest pixel (rounded half to even) elsewhere."""
    H, W = depth.shape
    x0, y0 = int(min(max(np.floor(u), 0), W - 2)), int(min(max(np.floor(v), 0), H - 2))
    fx, fy = u - x0, v - y0
    z = depth[y0 : y0 + 2, x0 : x0 + 2]
    nearest = depth[int(np.rint(v)), int(np.rint(u))]
    if z.min() > 0 and z.max() - z.min() <= max_rel_step * z.min() and nearest > 0:
        return float(
            (1 - fx) * (1 - fy) * z[0, 0] + fx * (1 - fy) * z[0, 1] + (1 - fx) * fy * z[1, 0] + fx * fy * z[1, 1]
        )
    return float(nearest)


def measured(obs):
    """(T, N) the features measured with their 3D point: the cues are theirs (zeros for pixel-only features)."""
    return obs.valid & obs.has_depth


def test_depth_cue_is_the_depth_image_at_the_feature(seq, recorded):
    """The depth cue against the depth PNG read here (TUM: uint16 / depth_scale; registered depth, so the colour
    pixel is the depth pixel). float32 tracker arithmetic on ~1-3 m: rtol 1e-6 (~8 float32 epsilons)."""
    obs, c = recorded, columns(recorded)
    assert torch.equal(obs.T_color_depth, torch.eye(4, dtype=torch.float64)) and len(seq.depth_paths) == obs.frames
    checked = 0
    for t in range(1, obs.frames):
        depth = np.asarray(Image.open(seq.depth_paths[t]), dtype=np.float64) / seq.depth_scale
        m = measured(obs)[t]
        for (u, v), z in zip(obs.pixels[t][m].double().tolist(), c["depth"][t][m].tolist(),
                             strict=True):  # fmt: skip
            assert z == pytest.approx(depth_at(depth, u, v), rel=1e-6, abs=0), (t, u, v)
            checked += 1
    assert checked >= 50


def test_window_cues_are_the_depth_png_around_the_feature(seq, recorded):
    """depth_step and depth_holes against the depth PNG read here, over the 5 x 5 window at the nearest pixel; the
    forward-backward error is the winner's d_TIM, the smaller of the two trackers' (eq. 10, step III)."""
    obs, c = recorded, columns(recorded)
    checked = 0
    for t in range(1, obs.frames):
        depth = np.pad(np.asarray(Image.open(seq.depth_paths[t]), dtype=np.float64) / seq.depth_scale, 2)
        m = measured(obs)[t]
        for (u, v), s, h in zip(obs.pixels[t][m].double().tolist(), c["depth_step"][t][m].tolist(),
                                c["depth_holes"][t][m].tolist(), strict=True):  # fmt: skip
            win = depth[round(v) : round(v) + 5, round(u) : round(u) + 5]
            ok = win[win > 0]
            assert s == pytest.approx(ok.max() - ok.min(), abs=1e-6) and h == pytest.approx(1 - ok.size / 25, abs=1e-6)
            checked += 1
    assert checked >= 50 and bool((c["depth_step"][measured(obs)] > 0).all())
    v = measured(obs)
    torch.testing.assert_close(c["fb_error"][v], torch.minimum(c["d_tim_int"], c["d_tim_sim"])[v], atol=0, rtol=0)
    assert bool((c["lk_min_eig"][v] > 0).all())


def test_sim_cue_is_the_shape_index_map_at_the_nearest_pixel(seq):
    """sim_value is the frame's SI map (eq. 8) at the tracked pixel's nearest grid point. This sequence's SI map is
    all fill (planes at 160 x 120), so the front end's map is replaced by a known one, unique per pixel (the SI map
    feeds nothing but this cue): the cue must be ramp(round(x)), from the map of the frame being tracked."""
    tracker = build_tracker(config())
    tracker.observers.append(record.Recording([]))  # an observer that asks for the cues and records nothing
    frontend = tracker.frontend

    def ramp_si(frame):
        cur = frontend(frame)
        B, _, H, W = cur.sim.si.shape
        pixel = torch.arange(H * W, dtype=torch.float32).reshape(1, 1, H, W) / (H * W)  # y * W + x, scaled
        stamp = frame.index.float().reshape(B, 1, 1, 1)  # which frame's map
        return dataclasses.replace(cur, sim=cur.sim._replace(si=pixel + stamp))

    tracker.frontend = ramp_si
    checked = 0
    with torch.inference_mode():
        for t, frame in enumerate(iterate_batched([seq], prefetch=False)):
            res = tracker.step(frame)
            if t == 0:
                continue
            ok = res.observation.valid_xyz[0]
            u, v = res.observation.pixels[0][ok].double().round().unbind(-1)  # torch rounds half to even, as rint
            expected = (v * 160 + u) / (160 * 120) + t
            got = res.cues[0][ok][:, COL["sim_value"]].double()
            torch.testing.assert_close(
                got, expected, atol=1e-6, rtol=0
            )  # float32 below 8: ulp 4.8e-7; pixels 5e-5 apart
            checked += int(ok.sum())
    assert checked >= 50


def test_d_tim_cues_follow_the_fallback_policy(recorded):
    """Step III/IV of eq. (10) with the configured "fallback" policy: an intensity winner passed the TIM threshold
    and the SIM tracker never ran for it (D_TIM_CAP exactly); a SIM winner is a failed intensity track whose SIM
    track passed."""
    flow = config().flow
    assert flow.policy == "fallback" and flow.tim_threshold == TIM_THRESHOLD
    c, v = columns(recorded), measured(recorded)
    assert bool(((c["sim_won"] == 0) | (c["sim_won"] == 1)).all())
    by_int, by_sim = v & (c["sim_won"] == 0), v & (c["sim_won"] == 1)
    assert bool((c["d_tim_int"][by_int] >= 0).all()) and bool((c["d_tim_int"][by_int] <= TIM_THRESHOLD).all())
    assert bool((c["d_tim_sim"][by_int] == D_TIM_CAP).all())
    assert bool((c["d_tim_int"][by_sim] > TIM_THRESHOLD).all()) and bool(
        (c["d_tim_sim"][by_sim] <= TIM_THRESHOLD).all()
    )
    assert int(by_int.sum()) > 50


def test_age_cornerness_and_previous_residual_follow_the_feature(recorded):
    """A feature tracked from frame t-1 to t (the same model: no re-selection at t-1; found by its model point) is
    one frame older at t, keeps its selection cornerness, and its prev_reproj cue is eq. (16) at t-1, computed here:
    || x_{t-1} - pi(K T_color_depth T_cam_obj,t-1 X_o) || with the recorded pose of t-1 (float64 here, a float32
    cue of a few px: atol 1e-5 px). A feature with no such match was added at t-1: age 1 and prev_reproj 0."""
    obs, c = recorded, columns(recorded)
    K, T_cd = obs.K.numpy(), obs.T_color_depth.numpy()
    matched = 0
    for t in range(2, obs.frames):
        if obs.reselected[t - 1]:
            continue
        prev = {tuple(p): j for j, p in enumerate(obs.points_obj[t - 1].tolist()) if obs.valid[t - 1, j]}
        T = T_cd @ obs.T_cam_obj_est[t - 1].numpy()
        for i in measured(obs)[t].nonzero().squeeze(1).tolist():
            j = prev.get(tuple(obs.points_obj[t, i].tolist()))
            if j is None:
                assert c["track_age"][t, i] == 1 and c["prev_reproj"][t, i] == 0, (t, i)
                continue
            if not obs.has_depth[t - 1, j]:  # tracked without depth at t-1: no cues there
                continue
            assert c["track_age"][t, i] == c["track_age"][t - 1, j] + 1, (t, i)
            for name in ("cornerness_int", "cornerness_sim"):
                assert c[name][t, i] == c[name][t - 1, j], (name, t, i)
            x = K @ (T[:3, :3] @ obs.points_obj[t, i].double().numpy() + T[:3, 3])
            err = np.linalg.norm(obs.pixels[t - 1, j].double().numpy() - x[:2] / x[2])
            assert float(c["prev_reproj"][t, i]) == pytest.approx(err, abs=1e-5, rel=0), (t, i)
            matched += 1
    assert matched >= 20, "the test needs features tracked across frames without re-selection"


def test_survivors_keep_their_age_and_cornerness(seq):
    tracker = build_tracker(config("reselect.fraction=0.0", "reselect.min_features=1"))  # no re-selection
    frames = list(iterate_batched([seq], prefetch=False))[:4]
    for f in frames:
        tracker.step(f)
    s = lambda: tracker.state  # noqa: E731
    keep = s().valid[0].clone()
    age, corner = s().age[0][keep], s().cornerness[0][keep]
    assert bool((age == 3).all())  # selected at frame 0, tracked through 3 frames
    measure = Measure(s().prev.depth, frames[-1].K, frames[-1].T_color_depth)
    tracker.state, _ = tracker._new_model(s(), frames[-1], s().prev, measure, torch.ones(1, dtype=torch.bool))
    k = len(age)
    assert torch.equal(s().age[0][:k], age) and torch.equal(s().cornerness[0][:k], corner)
    assert not s().age[0][k:].any(), "new features start at age 0"
    assert s().age.shape == s().valid.shape and s().cornerness.shape == (*s().valid.shape, 2)


class CueReader(PaperWeighting):
    """The paper's weighting, asking for cues: they must arrive, and change nothing."""

    needs_cues = True

    def __init__(self, **kw):
        super().__init__(**kw)
        self.seen = []

    def __call__(self, inputs):
        self.seen.append(inputs.cues)
        return super().__call__(inputs)


def test_a_weighting_that_needs_cues_gets_them(seq):
    cfg = config()
    tracker = build_tracker(cfg)
    tracker.weighting = CueReader(**{k: v for k, v in cfg.weighting.items() if k != "_target_"})
    with torch.inference_mode():
        poses = [tracker.step(f).T_cam_obj for f in iterate_batched([seq], prefetch=False)]
    plain = [r.T_cam_obj for r in plain_run(seq)]
    assert all(torch.equal(a, b) for a, b in zip(poses, plain, strict=True))
    assert len(tracker.weighting.seen) == len(seq) - 1
    assert all(c is not None and c.shape[-1] == len(COL) for c in tracker.weighting.seen)


class Seen:
    """An observer of the step: every result it is shown; it asks for the cues when ``needs_cues``."""

    def __init__(self, needs_cues: bool) -> None:
        self.needs_cues, self.results = needs_cues, []

    def __call__(self, frame, res):
        self.results.append((int(frame.index[0]), res))


@pytest.mark.parametrize("needs_cues", [False, True])
def test_an_observer_sees_every_step_and_gets_the_cues_it_asks_for(seq, needs_cues):
    """An observer is shown each step's own result after the step, frame by frame; the cues are there (and the poses
    the plain run's, bit for bit) where it asks for them, and absent where nothing asks."""
    tracker = build_tracker(config())
    seen = Seen(needs_cues)
    tracker.observers.append(seen)
    with torch.inference_mode():
        results = [tracker.step(f) for f in iterate_batched([seq], prefetch=False)]
    assert [i for i, _ in seen.results] == list(range(len(seq)))
    assert all(r is s for r, (_, s) in zip(results, seen.results, strict=True))
    assert all((r.cues is not None) == needs_cues for r in results[1:]) and results[0].cues is None
    plain = plain_run(seq)
    assert all(torch.equal(a.T_cam_obj, b.T_cam_obj) for a, b in zip(results, plain, strict=True))


# ---------------------------------------------------------------------------------------------- LK residual
def window_residual(prev, next, x0, x1, k: int, window: int = 21) -> torch.Tensor:
    """Mean |I_next(x1 + o) - I_prev(x0 + o)| over the window offsets o, bilinear (grid_sample), channel k."""
    r = torch.arange(window, dtype=torch.float64) - window // 2
    off = torch.stack(torch.meshgrid(r, r, indexing="xy"), -1).reshape(-1, 2)

    def sample(img, x):
        h, w = img.shape[-2:]
        p = x[:, None].double() + off
        grid = torch.stack([2 * p[..., 0] / (w - 1) - 1, 2 * p[..., 1] / (h - 1) - 1], -1)
        return F.grid_sample(img.double(), grid[None], align_corners=True)[0, 0]

    return (sample(next.images[k], x1) - sample(prev.images[k], x0)).abs().mean(-1)


@pytest.mark.parametrize("policy", ["min_tim", "fallback"])
def test_lk_residual_is_the_winners_final_window_difference(policy):
    f0, f1, pts, _ = split_scene((1.3, -0.6))
    plain = combined_track(f0, f1, pts, policy=policy)
    res = combined_track(f0, f1, pts, policy=policy, with_residual=True)
    assert torch.equal(plain.points, res.points) and torch.equal(plain.valid, res.valid)  # tracks unchanged
    assert not plain.residual.any()
    ok = res.valid[0]
    assert ok.sum() > 60
    for k in (0, 1):  # intensity winners, SIM winners
        sel = ok & (res.winner[0] == k)
        expected = window_residual(f0, f1, pts[0][sel], res.points[0][sel], k)
        torch.testing.assert_close(res.residual[0][sel].double(), expected, atol=2e-5, rtol=0)
    assert bool((res.residual[0][ok] < 0.02).all())  # a pure shift: only interpolation error is left


def test_lk_residual_of_opencv_in_image_units():
    """OpenCV's err (0..255, on 8-bit images) / 255 is on the torch back end's scale: within 8-bit rounding."""
    f0, f1, pts, _ = split_scene((1.3, -0.6))
    from opencv_flow import combined_track_opencv

    cv = combined_track_opencv(f0, f1, pts, with_residual=True)
    ours = combined_track(f0, f1, pts, with_residual=True)
    both = cv.valid[0] & ours.valid[0] & (cv.winner[0] == ours.winner[0])
    assert both.sum() > 60
    diff = (cv.residual[0][both] - ours.residual[0][both]).abs()
    assert float(diff.median()) < 2.0 / 255, f"median |opencv - torch| = {float(diff.median()) * 255:.2f} / 255"


# ---------------------------------------------------------------------------------------------- resume, CLI
def test_resume_skips_an_up_to_date_file_and_re_records_another_config(seq, tmp_path, monkeypatch):
    (path,) = record_sequences(config(), [seq], tmp_path, progress=False)
    stamp = path.stat().st_mtime_ns
    calls = []
    monkeypatch.setattr(record, "_record_batch", lambda *a, **k: calls.append(a[2]))
    assert record_sequences(config(), [seq], tmp_path, progress=False) == [path]
    assert calls == [] and path.stat().st_mtime_ns == stamp
    record_sequences(config("plots=false", "threads=2"), [seq], tmp_path, progress=False)  # not recording options
    assert calls == []
    record_sequences(config("weighting.sigma2_pix=2.0"), [seq], tmp_path, progress=False)
    assert calls == [[seq.name]]
    record_sequences(config("landmarks=none"), [seq], tmp_path, progress=False)  # the policy changes it too
    assert calls == [[seq.name]] * 2
    record_sequences(config("relocalise.recover=false"), [seq], tmp_path, progress=False)
    assert calls == [[seq.name]] * 3
    path.write_bytes(b"corrupt")
    record_sequences(config(), [seq], tmp_path, progress=False)
    assert calls == [[seq.name]] * 4


def test_synthetic_set_definition():
    variants = synthetic_variants(config("+dataset=synthetic", name="record").dataset)
    names = [v.name for v in variants]
    assert len(names) == len(set(names)) == 2 * 4 * 2 * 8
    assert {v.config.mode for v in variants} == {"scene", "object"}
    near = {(v.config.object, v.config.object_distance_m) for v in variants if v.name.startswith("near-")}
    assert near == {("small", 0.45)}
    perturbed = {v.name.split("-")[2]: v.perturb for v in variants if v.perturb}
    assert perturbed == {
        "depthnoise_low": {"kind": "depth_noise", "sigma_k": 1.5e-3},
        "depthnoise_high": {"kind": "depth_noise", "sigma_k": 5e-3},
    }
    assert all(v.config.noise == "none" for v in variants if v.perturb)  # the perturbation is the only noise
    rig = {v.config.depth_camera["fx"] for v in variants if "-rig-" in v.name}
    assert rig == {580.0} and all(v.config.depth_camera is None for v in variants if "-rig-" not in v.name)
    assert {v.region for v in variants if v.config.mode == "object"} == {"object"}
    assert {v.config.background for v in variants if v.name.startswith("object_bare")} == {False}
    noisy = [v.config for v in variants if "kinect3x_flying" in v.name]
    assert {(c.kinect.sigma_scale, c.effects.flying_pixel_prob) for c in noisy} == {(3.0, 0.5)}
    misreg = {v.config.effects.depth_shift_px for v in variants if "misregistered" in v.name}
    assert misreg == {(2, 1)} and {v.config.width for v in variants} == {640}


def cli(args: list[str], env_cache: Path) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("torchtrack-record")
    cmd = [str(script)] if script.is_file() else [sys.executable, "-m", "torchtrack.learn.record_app"]
    env = {**os.environ, "TORCHTRACK_CACHE": str(env_cache)}
    return subprocess.run(cmd + args, capture_output=True, text=True, env=env, timeout=300)


def test_cli_end_to_end(seq, tmp_path):
    out = tmp_path / "cache"
    run = cli(["data=tum", f"data.root={seq.root}", f"out={out}", "data.max_frames=5"], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    obs = load_observations(out / f"{seq.name}.pt")
    assert obs.frames == 5 and obs.sequence == seq.name and "weighting" in obs.config
    again = cli(["data=tum", f"data.root={seq.root}", f"out={out}", "data.max_frames=5"], tmp_path)
    assert again.returncode == 0 and "skipped" in again.stderr + again.stdout
    tiny = cli(["+dataset=synthetic_tiny", f"out={tmp_path / 'tiny'}"], tmp_path)
    assert tiny.returncode == 0, tiny.stderr[-2000:]
    files = sorted(p.name for p in (tmp_path / "tiny").glob("*.pt"))
    assert files == ["object_bare-medium-kinect-seed0.pt", "scene-medium-kinect-seed0.pt"]
    assert all(load_observations(tmp_path / "tiny" / f).frames == 6 for f in files)
    assert (tmp_path / "tiny" / "dataset.json").is_file()
    missing = cli(["data=tum", f"data.root={tmp_path / 'nothing'}", f"out={out}"], tmp_path)
    assert missing.returncode == 2
