"""Perturbed variants (torchtrack.data.perturb): each kind is a TUM folder TumSequence reads, with the frames,
timestamps and ground truth it promises, and pixels changed as documented (oracles from the source images)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchtrack.data.perturb import KINDS, make_variant, smooth_walk
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import read_list_file

FRAMES = 10


@pytest.fixture(scope="module")
def src(tmp_path_factory) -> Path:
    cfg = SyntheticConfig(width=160, height=120, frames=FRAMES, seed=2, noise="kinect")
    return ensure_sequence(cfg, tmp_path_factory.mktemp("data"))


def read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img


def image_pairs(src: Path, var: Path, which: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(source image, variant image) per frame of a kind that keeps the frame order."""
    a, b = TumSequence(src), TumSequence(var)
    paths = ("rgb_paths", "depth_paths")[which == "depth"]
    return [(read(p), read(q)) for p, q in zip(getattr(a, paths), getattr(b, paths), strict=True)]


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_is_a_tum_sequence_with_increasing_time(src, tmp_path, kind):
    var = make_variant(src, kind, tmp_path)
    assert var == tmp_path / f"{src.name}-{kind}"
    seq, ref = TumSequence(var), TumSequence(src)
    k = int(kind[4:]) if kind.startswith("skip") else 1
    assert len(seq) == len(range(0, FRAMES, k))
    assert np.all(np.diff(seq.timestamps) > 0) and seq.gt_valid.all()
    assert (var / "intrinsics.txt").read_text() == (src / "intrinsics.txt").read_text()
    assert seq.depth_scale == ref.depth_scale and np.array_equal(seq.K, ref.K)
    frame = seq[len(seq) - 1]
    assert frame.rgb.shape == ref[0].rgb.shape and frame.depth.shape == ref[0].depth.shape
    assert json.loads((var / "VARIANT.json").read_text())["kind"] == kind


@pytest.mark.parametrize("k", [2, 3, 4])
def test_skip_keeps_every_kth_frame_with_its_timestamp_and_pose(src, tmp_path, k):
    seq, ref = TumSequence(make_variant(src, f"skip{k}", tmp_path)), TumSequence(src)
    np.testing.assert_array_equal(seq.timestamps, ref.timestamps[::k])
    np.testing.assert_array_equal(seq.groundtruth, ref.groundtruth[::k])
    assert [p.resolve() for p in seq.rgb_paths] == [p.resolve() for p in ref.rgb_paths[::k]]
    assert [p.resolve() for p in seq.depth_paths] == [p.resolve() for p in ref.depth_paths[::k]]
    assert all(p.is_symlink() for p in seq.rgb_paths)  # no copies of unchanged pixels


def test_reversed_plays_backwards_with_reflected_time(src, tmp_path):
    seq, ref = TumSequence(make_variant(src, "reversed", tmp_path)), TumSequence(src)
    n = len(ref)
    assert len(seq) == n
    t0, t1 = ref.timestamps[0], ref.timestamps[-1]
    np.testing.assert_allclose(seq.timestamps, t0 + (t1 - ref.timestamps[::-1]), atol=2e-6)
    for i in range(n):
        np.testing.assert_allclose(seq.groundtruth[i], ref.groundtruth[n - 1 - i], atol=1e-9)
        assert seq.rgb_paths[i].resolve() == ref.rgb_paths[n - 1 - i].resolve()
        assert seq.depth_paths[i].resolve() == ref.depth_paths[n - 1 - i].resolve()


def test_photometric_is_the_documented_change_plus_noise(src, tmp_path):
    var = make_variant(src, "photometric", tmp_path)
    p = json.loads((var / "VARIANT.json").read_text())["params"]
    t, gain, gamma = np.loadtxt(var / "photometric.txt", unpack=True)
    np.testing.assert_allclose(t, TumSequence(src).timestamps, atol=1e-6)
    assert np.all((gain >= 0.6) & (gain <= 1.4) & (gamma >= 0.8) & (gamma <= 1.25))
    assert gain.std() > 0 and gamma.std() > 0
    residuals, means = [], []
    for i, (a, b) in enumerate(image_pairs(src, var, "rgb")):
        clean = p["darken"] * gain[i] * (a / 255.0) ** gamma[i]  # the oracle: the change without noise
        inside = (clean > 0.1) & (clean < 0.9)  # away from clipping
        residuals.append((b / 255.0 - clean)[inside])
        means.append((a.mean(), b.mean()))
    (a_mean, b_mean) = np.mean(means, axis=0)
    assert b_mean < 0.9 * a_mean  # darker overall (darken 0.75; gain starts at 1)
    r = np.concatenate(residuals)
    assert abs(r.mean()) < 2e-3
    assert r.std() == pytest.approx(np.sqrt(0.02**2 + (1 / 255) ** 2 / 12), rel=0.05)  # noise + 8-bit rounding
    for a, b in image_pairs(src, var, "depth"):
        np.testing.assert_array_equal(a, b)


def test_depth_noise_std_grows_with_z_squared_and_holes_have_the_target_fraction(src, tmp_path):
    var = make_variant(src, "depth_noise", tmp_path, blobs=0)
    scale = TumSequence(src).depth_scale
    holes, valid, rel = 0, 0, []
    for a, b in image_pairs(src, var, "depth"):
        assert b.dtype == np.uint16 and b.shape == a.shape
        assert not np.any(b[a == 0])  # no depth appears where there was none
        ok = a > 0
        holes, valid = holes + np.count_nonzero(ok & (b == 0)), valid + np.count_nonzero(ok)
        both = ok & (b > 0)
        z = a[both] / scale
        rel.append((b[both] / scale - z) / z**2)
    assert holes / valid == pytest.approx(0.05, abs=0.006)
    r = np.concatenate(rel)
    assert abs(r.mean()) < 1e-4 and r.std() == pytest.approx(2.5e-3, rel=0.05)
    with_blobs = make_variant(src, "depth_noise", tmp_path)  # default: 3 blobs per frame on top of the dropout
    frac = np.mean([np.mean(b[a > 0] == 0) for a, b in image_pairs(src, with_blobs, "depth")])
    assert 0.06 < frac < 0.5
    for a, b in image_pairs(src, var, "rgb"):
        np.testing.assert_array_equal(a, b)


def test_jitter_changes_pixels_by_about_one_level(src, tmp_path):
    var = make_variant(src, "jitter", tmp_path)
    d = np.concatenate([(b.astype(int) - a.astype(int)).ravel() for a, b in image_pairs(src, var, "rgb")])
    assert np.abs(d).max() <= 3 and 0.2 < np.mean(d != 0) < 0.45  # P(|N(0, 0.5)| > 0.5) = 0.32


@pytest.mark.parametrize("kind", ["photometric", "depth_noise", "jitter"])
def test_deterministic_by_seed(src, tmp_path, kind):
    a = make_variant(src, kind, tmp_path / "a", seed=1)
    b = make_variant(src, kind, tmp_path / "b", seed=1)
    c = make_variant(src, kind, tmp_path / "a", seed=2)
    assert a.name == b.name != c.name and a.parent == c.parent

    def files(v):
        return {p.relative_to(v): p.read_bytes() for p in sorted(v.rglob("*.png")) if not p.is_symlink()}

    assert files(a) == files(b) and files(a).keys() == files(c).keys() and files(a) != files(c)


def test_cached_rebuilt_when_stale_and_first_n(src, tmp_path):
    var = make_variant(src, "photometric", tmp_path)
    marker = var / "rgb.txt"
    mtime = marker.stat().st_mtime_ns
    assert make_variant(src, "photometric", tmp_path) == var and marker.stat().st_mtime_ns == mtime
    stamp = json.loads((var / "VARIANT.json").read_text())
    (var / "VARIANT.json").write_text(json.dumps({**stamp, "version": -1}))  # a stale stamp: rebuilt in place
    assert make_variant(src, "photometric", tmp_path) == var
    assert json.loads((var / "VARIANT.json").read_text()) == stamp
    short = make_variant(src, "reversed", tmp_path, first=4)
    assert short.name.endswith("-reversed-first4") and len(TumSequence(short)) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([var.name, short.name])  # no temporary left


def test_killed_write_leaves_no_folder(src, tmp_path, monkeypatch):
    import torchtrack.data.perturb as perturb

    def boom(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(perturb, "_copy_metadata", boom)
    with pytest.raises(KeyboardInterrupt):
        make_variant(src, "jitter", tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_bad_input_raises_clearly(src, tmp_path):
    with pytest.raises(ValueError, match="unknown kind"):
        make_variant(src, "blur", tmp_path)
    with pytest.raises(ValueError, match="unknown parameter"):
        make_variant(src, "skip2", tmp_path, sigma_k=1.0)
    with pytest.raises(Exception, match="rgb.txt"):
        make_variant(tmp_path, "skip2", tmp_path / "out")


def test_smooth_walk_stays_in_bounds_and_moves_smoothly():
    w = smooth_walk(np.random.default_rng(0), 2000, 0.6, 1.4, 0.01, 0.8)
    assert w[0] == 1.0 and w.min() >= 0.6 and w.max() <= 1.4
    assert w.max() - w.min() > 0.4  # it explores the range...
    assert np.abs(np.diff(np.log(w))).max() < 0.15  # ...in small steps
    assert np.all(smooth_walk(np.random.default_rng(0), 5, 1.0, 1.0, 0.1, 0.8) == 1.0)


def test_lists_are_relative_and_timestamps_six_decimals(src, tmp_path):
    var = make_variant(src, "depth_noise", tmp_path)
    t, names = read_list_file(var / "depth.txt")
    assert all(not os.path.isabs(n) for n in names) and len(t) == FRAMES
    row = next(line for line in (var / "rgb.txt").read_text().splitlines() if not line.startswith("#"))
    assert len(row.split()[0].split(".")[1]) == 6
