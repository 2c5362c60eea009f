"""Pyramidal LK and template inverse matching.

Oracles: an analytic texture rendered exactly at shifted / affinely warped positions (no image
interpolation in the ground truth); OpenCV's calcOpticalFlowPyrLK and pyrDown on the same inputs;
d_TIM = 0 on identical images; batched, chunked and channel-stacked calls equal looped ones within
tests/tolerances.py. No autograd here (LK is not differentiated), so no gradient check. These run what a run
runs (the compiled operator where it builds); tests on the reference (``lk_track_reference``, tests/reference.py)
test its own machinery, and tests/test_lk_op.py holds the operator to the reference.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from reference import on_reference
from tolerances import F32_UNIT, LK_PX, LK_RESIDUAL

from torchtrack.image.lk import LKResult, forward_backward, lk_track_flat, lk_track_reference, pyramidal_lk
from torchtrack.image.pyramid import Pyramid, build_pyramid, pyr_down

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
H, W = 240, 320
CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)


def texture(x: np.ndarray, y: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth analytic texture in [0.1, 0.9]: a sum of 12 plane waves (periods 18-125 px)."""
    rng = np.random.default_rng(seed)
    v = np.zeros_like(x)
    for _ in range(12):
        f, th, ph = rng.uniform(0.05, 0.35), rng.uniform(0, np.pi), rng.uniform(0, 2 * np.pi)
        v += np.sin(f * (np.cos(th) * x + np.sin(th) * y) + ph) / 12
    return 0.5 + 0.8 * v


def warped_pair(A: np.ndarray, t: np.ndarray, n: int = 200, seed: int = 0):
    """I0 = texture, I1(x) = texture(A^-1 (x - c - t) + c): a point p of I0 is at A (p - c) + c + t in I1."""
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    c = np.array([W / 2, H / 2])
    src = (np.stack([xx, yy], -1) - c - t) @ np.linalg.inv(A).T + c
    i0, i1 = texture(xx, yy, seed), texture(src[..., 0], src[..., 1], seed)
    g = np.random.default_rng(seed + 1)
    pts = np.stack([g.uniform(40, W - 40, n), g.uniform(40, H - 40, n)], -1)
    true = (pts - c) @ A.T + c + t
    as_t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return as_t(i0)[None, None], as_t(i1)[None, None], as_t(pts)[None], true


def errors(res: LKResult, true: np.ndarray) -> np.ndarray:
    return np.linalg.norm(res.points[0].numpy() - true, axis=1)[res.status[0].numpy()]


def gray_pair(seq: str, i: int = 0):
    folder = DATA / seq
    names = [ln.split()[1] for ln in (folder / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    a, b = (cv2.cvtColor(cv2.imread(str(folder / names[k])), cv2.COLOR_BGR2GRAY) for k in (i, i + 1))
    return a, b


def to_t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).float()[None, None] / 255.0


# ---------------------------------------------------------------------------------------------- smoke, errors
def test_smoke_shapes():
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.5, -0.25]), n=7)
    res = pyramidal_lk(i0, i1, pts)
    assert isinstance(res, LKResult)
    assert res.points.shape == (1, 7, 2) and res.status.shape == (1, 7) and res.residual.shape == (1, 7)
    assert res.status.dtype == torch.bool and res.status.all()
    assert (res.residual >= 0).all() and (res.residual < 0.05).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(points=torch.zeros(1, 5)), "points must be"),
        (dict(window=20), "odd window"),
        (dict(levels=0), "levels"),
        (dict(init=torch.zeros(1, 4, 2)), "init must be"),
        (dict(valid=torch.ones(1, 4, dtype=torch.bool)), "valid must be"),
        (dict(prev=torch.zeros(1, 1, 32, 32)), "do not match"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = dict(prev=torch.rand(1, 1, 48, 64), next=torch.rand(1, 1, 48, 64), points=torch.full((1, 5, 2), 20.0))
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        pyramidal_lk(args.pop("prev"), args.pop("next"), args.pop("points"), **args)


def test_pyramid_too_small_raises():
    img = torch.rand(1, 1, 48, 64)
    with pytest.raises(ValueError, match="pyramid has"):
        pyramidal_lk(build_pyramid(img, 2), img, torch.full((1, 3, 2), 20.0), levels=3)
    with pytest.raises(ValueError, match="float"):
        build_pyramid(torch.zeros(1, 48, 64), 2)


# ---------------------------------------------------------------------------------------------- pyramid
@pytest.mark.parametrize("h, w", [(37, 50), (48, 64), (5, 7)])
def test_pyr_down_equals_opencv(h, w):
    x = np.random.default_rng(0).random((h, w), dtype=np.float32)
    ours = pyr_down(torch.from_numpy(x)[None, None])[0, 0].numpy()
    ref = cv2.pyrDown(x)
    assert ours.shape == ref.shape
    np.testing.assert_allclose(ours, ref, atol=1e-6)


@pytest.mark.parametrize("h, w, levels", [(37, 50, 3), (9, 7, 4)])
def test_build_pyramid_levels_are_kornia_pyr_down(h, w, levels):
    """The packed levels (the blur evaluated at the kept pixels only) equal pyr_down, kornia's Pascal filter."""
    pyr = build_pyramid(torch.rand(2, 3, h, w), levels, window=11)
    for level in range(1, levels):
        torch.testing.assert_close(pyr.images[level], pyr_down(pyr.images[level - 1]), atol=F32_UNIT, rtol=0)


def test_build_pyramid_layout():
    img = torch.rand(2, 3, 37, 50)
    pyr = build_pyramid(img, 3, window=11)  # pad 8: levels 0 and 1 have reflect-101 borders, level 2 (10x13) too
    assert isinstance(pyr, Pyramid) and pyr.levels == 3 and pyr.batch == 2 and pyr.channels == 3
    assert [pyr.size(level) for level in range(3)] == [(37, 50), (19, 25), (10, 13)]
    buf = pyr.flat.view(3, -1, pyr.stride)
    for level in range(3):
        h, w = pyr.size(level)
        for b in range(2):
            r0 = int(pyr.row_start[level, b]) + pyr.pad
            block = buf[:, r0 : r0 + h, pyr.pad : pyr.pad + w]
            torch.testing.assert_close(block, pyr.images[level][b], rtol=0, atol=0)
            above = buf[:, r0 - 2, pyr.pad : pyr.pad + w]  # reflect-101 border, as OpenCV's pyramids
            torch.testing.assert_close(above, pyr.images[level][b, :, 2], rtol=0, atol=0)
            torch.testing.assert_close(buf[:, r0 : r0 + h, pyr.pad - 3], pyr.images[level][b, :, :, 3], rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------- synthetic oracles
@pytest.mark.parametrize("t", [(0.3, -0.7), (2.45, 1.2), (-5.6, 3.3)])
def test_subpixel_translation(t):
    """Measured: median 0.004 px, 95th percentile 0.014 px (bilinear interpolation error of the texture)."""
    i0, i1, pts, true = warped_pair(np.eye(2), np.array(t))
    res = pyramidal_lk(i0, i1, pts)
    assert res.status.all()
    e = errors(res, true)
    assert np.median(e) <= 0.02 and np.percentile(e, 95) <= 0.1, (np.median(e), np.percentile(e, 95))


def test_small_affine_warp():
    """0.15 deg rotation, 0.15 % scale, 0.1 % shear, (1.3, -2.2) px: translation LK is biased by the warp over
    its window (the same bias as OpenCV's: about 0.08 px median at 1 deg and 1 %), so the warp is small.
    Measured: median 0.010 px, 95th percentile 0.022 px."""
    a = math.radians(0.15)
    A = 1.0015 * np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]) @ np.array([[1, 0.001], [0, 1]])
    i0, i1, pts, true = warped_pair(A, np.array([1.3, -2.2]))
    res = pyramidal_lk(i0, i1, pts)
    assert res.status.all()
    e = errors(res, true)
    assert np.median(e) <= 0.02 and np.percentile(e, 95) <= 0.1, (np.median(e), np.percentile(e, 95))


def test_init_guess_and_pure_inverse_compositional():
    """A 14 px shift is out of reach from the input position with 2 levels but found from a close guess;
    Newton-free iterations (ic_iters >= iters, OpenCV's loop) converge to the same points."""
    i0, i1, pts, true = warped_pair(np.eye(2), np.array([14.2, -3.4]))
    far = pyramidal_lk(i0, i1, pts, levels=2)
    assert np.median(np.linalg.norm(far.points[0].numpy() - true, axis=1)) > 1.0
    guess = pts + torch.tensor([13.0, -3.0])
    near = pyramidal_lk(i0, i1, pts, levels=2, init=guess)
    assert near.status.all() and np.median(errors(near, true)) <= 0.02
    plain = pyramidal_lk(i0, i1, pts, levels=2, init=guess, ic_iters=30)
    assert plain.status.all()
    assert (near.points - plain.points).norm(dim=-1).max() < 0.02


def test_status_false_out_of_image_degenerate_and_invalid():
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([6.0, 0.0]), n=4)
    pts = pts.clone()
    pts[0, 0] = torch.tensor([W - 3.0, 100.0])  # moves out of the image
    pts[0, 1] = torch.tensor([-5.0, 100.0])  # starts outside
    i1 = i1.clone()
    i0 = i0.clone()
    i0[..., 150:, :] = 0.5  # uniform: degenerate gradient matrix
    pts[0, 2] = torch.tensor([160.0, 200.0])
    valid = torch.tensor([[True, True, True, False]])
    res = pyramidal_lk(i0, i1, pts, valid=valid)
    assert res.status.tolist() == [[False, False, False, False]]
    torch.testing.assert_close(res.points[0, 1:], pts[0, 1:])  # untracked points are returned unchanged
    assert (res.residual[0, 1:] == 0).all()


# ---------------------------------------------------------------------------------------------- TIM, batching
def test_forward_backward_identical_images_gives_zero_tim():
    i0, _, pts, _ = warped_pair(np.eye(2), np.zeros(2))
    fwd, back, d_tim = forward_backward(i0, i0, pts)
    assert fwd.status.all()
    assert d_tim.max() <= 1e-4  # float32 rounding of ~300 px coordinates
    torch.testing.assert_close(back, pts, atol=1e-4, rtol=0)


def test_forward_backward_tim_is_distance_and_inf_on_failure():
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([1.7, 0.6]), n=50)
    pts = torch.cat([pts, torch.tensor([[[-3.0, 10.0]]])], 1)
    fwd, back, d_tim = forward_backward(i0, i1, pts)
    ok = fwd.status[0, :50]
    assert ok.all() and not fwd.status[0, 50]
    torch.testing.assert_close(d_tim[0, :50], (pts[0, :50] - back[0, :50]).norm(dim=-1))
    assert d_tim[0, :50].median() < 0.03 and d_tim[0, :50].max() < 0.15  # bilinear interpolation error
    assert math.isinf(d_tim[0, 50])


@pytest.mark.equivalence
def test_batched_equals_looped_and_pyramids_equal_tensors():
    pairs = [
        warped_pair(np.eye(2), np.array(t), n=30, seed=s) for s, t in enumerate([(0.4, 1.1), (-2.3, 0.2), (3.1, -1.4)])
    ]
    i0 = torch.cat([p[0] for p in pairs])
    i1 = torch.cat([p[1] for p in pairs])
    pts = torch.cat([p[2] for p in pairs])
    valid = torch.rand(3, 30, generator=torch.Generator().manual_seed(0)) > 0.2
    batched = pyramidal_lk(i0, i1, pts, valid=valid)
    for b in range(3):
        one = pyramidal_lk(i0[b : b + 1], i1[b : b + 1], pts[b : b + 1], valid=valid[b : b + 1])
        torch.testing.assert_close(batched.points[b], one.points[0], atol=LK_PX, rtol=0)
        assert (batched.status[b] == one.status[0]).all()
        torch.testing.assert_close(batched.residual[b], one.residual[0], atol=LK_RESIDUAL, rtol=0)
    again = pyramidal_lk(build_pyramid(i0, 3), build_pyramid(i1, 3), pts, valid=valid)
    torch.testing.assert_close(again.points, batched.points, atol=0, rtol=0)  # the same computation: exact


def test_float64_index_arithmetic_for_large_buffers(monkeypatch):
    """Buffers of 2^24 elements and more index in float64 (float32 is exact below): same tracks."""
    import torchtrack.image.lk_window as lk_window

    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.8, -1.9]), n=40)
    ref = on_reference(pyramidal_lk, i0, i1, pts)  # the reference's sampler (the operator indexes in int64)
    monkeypatch.setattr(lk_window, "_EXACT_F32", 16)
    out = on_reference(pyramidal_lk, i0, i1, pts)
    torch.testing.assert_close(out.points, ref.points, atol=1e-5, rtol=0)
    assert (out.status == ref.status).all()


@pytest.mark.equivalence
def test_channels_tracked_jointly():
    """Two channels carrying the same shifted texture track like one; a blank second channel changes nothing."""
    i0, i1, pts, true = warped_pair(np.eye(2), np.array([1.25, -0.5]), n=60)
    one = pyramidal_lk(i0, i1, pts)
    two = pyramidal_lk(torch.cat([i0, i0], 1), torch.cat([i1, i1], 1), pts)
    blank = pyramidal_lk(
        torch.cat([i0, torch.full_like(i0, 0.3)], 1), torch.cat([i1, torch.full_like(i1, 0.3)], 1), pts
    )
    torch.testing.assert_close(two.points, one.points, atol=LK_PX, rtol=0)
    torch.testing.assert_close(blank.points, one.points, atol=LK_PX, rtol=0)
    assert np.median(errors(two, true)) <= 0.02


def test_flat_entry_point_matches():
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.6, 0.9]), n=20)
    ref = pyramidal_lk(i0, i1, pts)
    p0, p1 = build_pyramid(i0, 3), build_pyramid(i1, 3)
    x, ok, res = lk_track_flat(p0, p1, pts[0], torch.zeros(20, dtype=torch.long), pts[0])
    torch.testing.assert_close(x, ref.points[0])
    assert (ok == ref.status[0]).all()


@pytest.mark.equivalence
def test_chunks_track_as_one_call():
    """Points are tracked in chunks of at most ``chunk`` (cache-sized): each track is independent of the others, so
    chunks of at most 7 points (four of 6, 6, 6, 4) give the one-call result within float32 rounding (LK_PX: other
    chunk sizes run other kernels), outside points and the status included."""
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([1.4, -0.7]), n=20)
    pts = torch.cat([pts[0], torch.tensor([[-3.0, 5.0], [500.0, 2.0]])])  # two points outside the image
    p0, p1 = build_pyramid(i0, 3), build_pyramid(i1, 3)
    img = torch.zeros(len(pts), dtype=torch.long)
    one = lk_track_reference(p0, p1, pts, img, pts + 0.5, chunk=len(pts), with_residual=True)
    chunked = lk_track_reference(p0, p1, pts, img, pts + 0.5, chunk=7, with_residual=True)
    assert one[1].sum() >= 15 and not one[1][-2:].any() and (one[2][one[1]] > 0).all()
    torch.testing.assert_close(chunked[0], one[0], atol=LK_PX, rtol=0)
    assert torch.equal(chunked[1], one[1])  # status: a flip needs an update within rounding of eps (none here)
    torch.testing.assert_close(chunked[2], one[2], atol=LK_RESIDUAL, rtol=0)
    with pytest.raises(ValueError, match="chunk"):
        lk_track_flat(p0, p1, pts, img, pts, chunk=0)


# ---------------------------------------------------------------------------------------------- OpenCV on real frames
@pytest.mark.skipif(not DATA.exists(), reason="needs ../shared/data")
@pytest.mark.parametrize("seq", ["sun3d_fragment1", "visp_rbt_sequence"])
def test_matches_opencv_on_real_frames(seq):
    """Median distance to OpenCV's points on the points both accept, frames 10 -> 11, 300 corners: measured
    0.00008 px on 294 points (sun3d_fragment1) and 0.00006 px on 299 (visp_rbt_sequence); the bound is
    0.1 px."""
    if not (DATA / seq).exists():
        pytest.skip(f"{seq} not in ../shared/data")
    a, b = gray_pair(seq, 10)
    p0 = cv2.goodFeaturesToTrack(a, 300, 0.001, 5).reshape(-1, 2)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(a, b, p0, None, winSize=(21, 21), maxLevel=2, criteria=CRITERIA)
    res = pyramidal_lk(to_t(a), to_t(b), torch.from_numpy(p0)[None], window=21, levels=3)
    both = res.status[0].numpy() & (st[:, 0] == 1)
    assert both.sum() >= 0.9 * (st[:, 0] == 1).sum()
    d = np.linalg.norm(res.points[0].numpy() - p1, axis=1)[both]
    assert np.median(d) <= 0.1, np.median(d)
    assert np.median(d) <= 0.001  # in fact much closer: same pyramid, gradients, interpolation and criteria
