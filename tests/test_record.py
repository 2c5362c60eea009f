"""Recording the front end (torchtrack/learn/record.py, learn/dataset.py) and the tracker's per-feature cues.

Oracles: the back end replayed on the recorded observations reproduces the tracker's poses; the recorded rows are
what the tracker's back end saw in a run that did not record; cues against their definitions (learn/cues.py);
the LK residual against an independent bilinear sampling of the final windows.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from test_flow import split_scene

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.filter.weighting import PaperWeighting
from torchtrack.image.flow import combined_track
from torchtrack.learn import record
from torchtrack.learn.cache import load_observations
from torchtrack.learn.cues import CUE_INDEX, CUE_NAMES, D_TIM_CAP
from torchtrack.learn.dataset import synthetic_variants
from torchtrack.learn.record import record_sequences

CONF = CONF_DIR


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
def test_cues_follow_their_definitions(recorded):
    obs = recorded
    c = {name: obs.cues[..., i] for i, name in enumerate(CUE_NAMES)}
    valid = obs.valid
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
    assert bool(((c["sim_won"] == 0) | (c["sim_won"] == 1)).all())
    for name in ("d_tim_int", "d_tim_sim"):
        assert bool(((c[name][v] >= 0) & (c[name][v] <= D_TIM_CAP)).all())
    tracked_by_int = v & (c["sim_won"] == 0)
    assert bool((c["d_tim_int"][tracked_by_int] <= 1.0).all())  # the winner passed the TIM threshold
    assert bool((c["lk_residual"][v] > 0).all()) and bool((c["lk_residual"][v] < 0.2).all())
    assert bool(((c["sim_value"][v] >= 0) & (c["sim_value"][v] <= 1)).all())
    assert bool(((c["cornerness_int"][v] >= 0) & (c["cornerness_int"][v] < 1)).all())
    assert bool((c["prev_reproj"][v & (c["track_age"] == 1)] == 0).all())  # new features have no previous frame
    assert bool((c["prev_reproj"][v] >= 0).all()) and bool((c["prev_reproj"][v] > 0).any())


def test_survivors_keep_their_age_and_cornerness(seq):
    tracker = build_tracker(config("pipeline.reselect_fraction=0.0", "pipeline.min_features=1"))  # no re-selection
    frames = list(iterate_batched([seq], prefetch=False))[:4]
    for f in frames:
        tracker.step(f)
    s = lambda: tracker.state  # noqa: E731
    keep = s().valid[0].clone()
    age, corner = s().age[0][keep], s().cornerness[0][keep]
    assert bool((age == 3).all())  # selected at frame 0, tracked through 3 frames
    tracker._new_model(frames[-1], s().prev, torch.ones(1, dtype=torch.bool))
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
    assert all(c is not None and c.shape[-1] == len(CUE_NAMES) for c in tracker.weighting.seen)


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


def test_lk_residual_opencv_backend_in_image_units():
    """OpenCV's err (0..255, on 8-bit images) / 255 is on the torch back end's scale: within 8-bit rounding."""
    f0, f1, pts, _ = split_scene((1.3, -0.6))
    cv = combined_track(f0, f1, pts, backend="opencv", with_residual=True)
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
    path.write_bytes(b"corrupt")
    record_sequences(config(), [seq], tmp_path, progress=False)
    assert calls == [[seq.name], [seq.name]]


def test_synthetic_set_definition():
    variants = synthetic_variants(config("+dataset=synthetic", name="record").dataset)
    names = [v.name for v in variants]
    assert len(names) == len(set(names)) == 2 * 3 * 3 * 3
    assert {v.config.mode for v in variants} == {"scene", "object"}
    assert {v.region for v in variants if v.config.mode == "object"} == {"object"}
    assert {v.config.background for v in variants if v.name.startswith("object_bare")} == {False}
    noisy = [v.config.kinect.sigma_a_m for v in variants if "kinect2x" in v.name]
    assert set(noisy) == {0.0024} and {v.config.width for v in variants} == {640}


def cli(args: list[str], env_cache: Path) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("torchtrack-record")
    cmd = [str(script)] if script.is_file() else [sys.executable, "-m", "torchtrack.learn.record"]
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


def test_cues_index_matches_names():
    assert [CUE_INDEX[n] for n in CUE_NAMES] == list(range(len(CUE_NAMES)))
