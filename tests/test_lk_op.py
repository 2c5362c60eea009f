"""The compiled LK operator (torch.ops.torchtrack.lk_track) against its pure-torch reference.

Oracles: exact sub-pixel shifts of an analytic texture (known answer, both implementations); the reference
(``backend="torch"``) on the same inputs, within tests/tolerances.py's LK_OP_* (sums in another order, a stop decision
that can flip on their rounding); the reference's rules on degenerate windows and points outside the image; the
fallback where the build is disabled; torch.library.opcheck for the schema and the fake kernel.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from test_lk import DATA, errors, gray_pair, to_t, warped_pair
from tolerances import LK_OP_OUTLIERS, LK_OP_PX, LK_OP_TIM, LK_PX, LK_RESIDUAL

from torchtrack.image import lk_op
from torchtrack.image.flow import combined_track, prepare_frame
from torchtrack.image.lk import lk_track_flat, pyramidal_lk
from torchtrack.image.pyramid import build_pyramid

pytestmark = pytest.mark.skipif(not lk_op.available(), reason="the LK operator does not build here")


def both(*args, **kwargs):
    return (pyramidal_lk(*args, **kwargs, backend=b) for b in ("torch", "cpp"))


def assert_agree(ref, op, px=LK_OP_PX, outliers=0.0):
    """(points, status, residual) of both: all but a fraction ``outliers`` of the points have the same status and,
    where both tracked, points within px and residuals within LK_RESIDUAL."""
    st_ref, st_op = ref[1].reshape(-1), op[1].reshape(-1)
    ok = st_ref & st_op
    d = (ref[0].reshape(-1, 2) - op[0].reshape(-1, 2)).abs().amax(-1)
    dr = (ref[2].reshape(-1) - op[2].reshape(-1)).abs()
    bad = (st_ref != st_op) | (ok & ((d > px) | (dr > LK_RESIDUAL)))
    assert bad.sum() <= outliers * bad.numel(), (bad.sum(), d[ok].max(), dr[ok].max())


# ---------------------------------------------------------------------------------------------- known answers
@pytest.mark.equivalence
@pytest.mark.parametrize("t", [(0.3, -0.7), (2.45, 1.2), (-5.6, 3.3)])
def test_subpixel_shift_known_answer_and_reference(t):
    """Exact shifted texture: both find the shift (median error <= 0.02 px, the bilinear interpolation's) and agree
    within LK_OP_PX on every point, status equal."""
    i0, i1, pts, true = warped_pair(np.eye(2), np.array(t))
    ref, op = both(i0, i1, pts)
    assert op.status.all() and np.median(errors(op, true)) <= 0.02 and np.percentile(errors(op, true), 95) <= 0.05
    assert_agree(ref, op)


@pytest.mark.equivalence
def test_newton_and_plain_inverse_compositional_agree_with_reference():
    """From a guess near the answer (Newton steps from ic_iters on) and with plain IC iterations (ic_iters >= iters)."""
    i0, i1, pts, true = warped_pair(np.array([[1.01, 0.02], [-0.015, 0.99]]), np.array([1.3, -0.8]))
    guess = torch.tensor(true, dtype=torch.float32)[None] + 0.4
    for kw in (dict(init=guess, levels=2), dict(ic_iters=30), dict(ic_iters=0, iters=10)):
        ref, op = both(i0, i1, pts, **kw)
        assert op.status.sum() >= 0.95 * pts.shape[1]
        assert_agree(ref, op)


def test_outside_degenerate_invalid_follow_the_reference():
    """Start outside, leave the image, a uniform (degenerate) window, an invalid entry: not tracked, input returned,
    residual 0, as the reference (exactly: these points take no arithmetic)."""
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([6.0, 0.0]), n=6)
    pts = pts.clone()
    pts[0, 0] = torch.tensor([317.0, 100.0])  # moves out of the image
    pts[0, 1] = torch.tensor([-5.0, 100.0])  # starts outside
    pts[0, 2] = torch.tensor([160.0, 200.0])  # uniform below row 150
    pts[0, 3] = torch.tensor([float("nan"), 3.0])
    i0 = i0.clone()
    i0[..., 150:, :] = 0.5
    valid = torch.tensor([[True, True, True, True, False, True]])
    ref, op = both(i0, i1, pts, valid=valid)
    assert op.status.tolist() == ref.status.tolist() == [[False, False, False, False, False, True]]
    torch.testing.assert_close(op.points[0, 1:5], pts[0, 1:5], equal_nan=True)
    assert (op.residual[0, :5] == 0).all()
    assert op.points[0, 0, 0] > 318.5 and ref.points[0, 0, 0] > 318.5  # its last position: past the border (319)


# ---------------------------------------------------------------------------------------------- batching, channels
@pytest.mark.equivalence
def test_batched_chunked_and_channels_equal_reference():
    """B = 3 images in one call equal each alone; the op (one call) equals the reference tracked in chunks of 7; two
    channels track jointly."""
    pairs = [
        warped_pair(np.eye(2), np.array(t), n=25, seed=s) for s, t in enumerate([(0.4, 1.1), (-2.3, 0.2), (3.1, -1.4)])
    ]
    i0, i1, pts = (torch.cat([p[k] for p in pairs]) for k in range(3))
    batched = pyramidal_lk(i0, i1, pts, backend="cpp")
    for b in range(3):
        one = pyramidal_lk(i0[b : b + 1], i1[b : b + 1], pts[b : b + 1], backend="cpp")
        assert_agree(tuple(t[b : b + 1] for t in batched), one, px=LK_PX)
    p0, p1 = build_pyramid(i0, 3), build_pyramid(i1, 3)
    flat, img = pts.reshape(-1, 2), torch.arange(3).repeat_interleave(25)
    assert_agree(lk_track_flat(p0, p1, flat, img, flat, backend="torch", chunk=7),
                 lk_track_flat(p0, p1, flat, img, flat, backend="cpp"))  # fmt: skip
    two = [torch.cat([x, x.flip(-1)], 1) for x in (i0, i1)]
    assert_agree(pyramidal_lk(*two, pts, backend="torch"), pyramidal_lk(*two, pts, backend="cpp"))


# ---------------------------------------------------------------------------------------------- real frames
@pytest.mark.equivalence
@pytest.mark.skipif(not DATA.exists(), reason="needs ../shared/data")
@pytest.mark.parametrize("seq", ["sun3d_fragment1", "visp_rbt_sequence"])
def test_real_frames_tracks_and_tim_agree(seq):
    """Frames 10 -> 12, 300 corners and 100 random points, intensity and SIM-like (the image's gradient magnitude)
    channels, combined tracker: tracks, status and TIM errors of the op within LK_OP_* of the reference."""
    if not (DATA / seq).exists():
        pytest.skip(f"{seq} not in ../shared/data")
    a, b = gray_pair(seq, 10)
    corners = torch.from_numpy(cv2.goodFeaturesToTrack(a, 300, 0.001, 5).reshape(-1, 2))
    rand = torch.rand(100, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor(
        [a.shape[1] - 1.0, a.shape[0] - 1.0]
    )
    pts = torch.cat([corners, rand])[None]
    g0, g1 = to_t(a), to_t(b)
    s0, s1 = (
        torch.from_numpy(cv2.Laplacian(x, cv2.CV_32F, ksize=3)).abs().clamp(max=255)[None, None] / 255 for x in (a, b)
    )
    f0, f1 = prepare_frame(g0, s0), prepare_frame(g1, s1)
    res = {
        be: combined_track(f0, f1, pts, policy="min_tim", with_residual=True, lk_backend=be) for be in ("torch", "cpp")
    }
    ref, op = res["torch"], res["cpp"]
    assert ref.valid.sum() >= 250
    assert_agree((ref.points, ref.valid, ref.residual), (op.points, op.valid, op.residual), outliers=LK_OP_OUTLIERS)
    for name in ("d_tim_int", "d_tim_sim"):
        dr, do = getattr(ref, name)[0], getattr(op, name)[0]
        fin = torch.isfinite(dr) & torch.isfinite(do) & (dr <= 1.0)
        assert (torch.isfinite(dr) != torch.isfinite(do)).sum() <= LK_OP_OUTLIERS * dr.numel()
        assert ((dr - do).abs()[fin] > LK_OP_TIM).sum() <= LK_OP_OUTLIERS * dr.numel()


# ---------------------------------------------------------------------------------------------- build, fallback, fake
def test_fallback_when_the_build_is_disabled(monkeypatch):
    """TORCHTRACK_NO_BUILD=1: one warning, once; auto runs the reference (the same computation: exact); cpp raises."""
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.7, -1.3]), n=20)
    ref = pyramidal_lk(i0, i1, pts, backend="torch")
    monkeypatch.setenv("TORCHTRACK_NO_BUILD", "1")
    monkeypatch.setattr(lk_op, "_state", {})
    with pytest.warns(RuntimeWarning, match="compiled LK operator unavailable"):
        out = pyramidal_lk(i0, i1, pts, backend="auto")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = pyramidal_lk(i0, i1, pts)  # no second warning
    for r in (out, again):
        assert torch.equal(r.points, ref.points) and torch.equal(r.status, ref.status)
    with pytest.raises(RuntimeError, match="could not be built"):
        pyramidal_lk(i0, i1, pts, backend="cpp")
    with pytest.raises(ValueError, match="backend"):
        pyramidal_lk(i0, i1, pts, backend="cuda")


def test_build_is_cached_by_source_hash():
    """The library sits in $TORCHTRACK_CACHE/ext/lk_<hash of source, flags, torch>; a second load is quick."""
    folder = lk_op.cache_dir() / "ext" / f"lk_{lk_op.build_key()}"
    assert any(folder.glob("*.so")) and not (folder / "lock").exists()
    assert lk_op._build() < 5.0  # nothing to compile: ninja finds the library up to date


def _op_args(n=5):
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.5, 0.5]), n=n)
    p0, p1 = build_pyramid(i0, 3), build_pyramid(i1, 3)
    base = ((p0.row_start + p0.pad) * p0.stride + p0.pad).contiguous()
    sizes = torch.tensor([p0.size(lv) for lv in range(3)])
    x = pts[0].contiguous()
    return (p0.flat, p1.flat, base, base.clone(), sizes, x, torch.zeros(n, dtype=torch.long), x.clone(),
            p0.stride, p0.plane, p0.pad, 21, 30, 3, 0.01, 1e-4, True)  # fmt: skip


def test_opcheck_schema_and_fake_kernel():
    args = _op_args()
    torch.library.opcheck(torch.ops.torchtrack.lk_track.default, args)
    from torch._subclasses.fake_tensor import FakeTensorMode

    with FakeTensorMode() as mode:
        fake = [mode.from_tensor(a) if isinstance(a, torch.Tensor) else a for a in args]
        pts, status, res = torch.ops.torchtrack.lk_track(*fake)
    assert pts.shape == (5, 2) and status.shape == (5,) and status.dtype == torch.bool and res.shape == (5,)


def test_op_bad_input_raises():
    args = list(_op_args())
    bad_index = list(args)
    bad_index[6] = torch.full((5,), 7, dtype=torch.long)
    with pytest.raises(RuntimeError, match="image_index out of range"):
        torch.ops.torchtrack.lk_track(*bad_index)
    bad_window = list(args)
    bad_window[11] = 40
    with pytest.raises(RuntimeError, match="odd window"):
        torch.ops.torchtrack.lk_track(*bad_window)
    bad_dtype = list(args)
    bad_dtype[5] = args[5].double()
    with pytest.raises(RuntimeError, match="float32"):
        torch.ops.torchtrack.lk_track(*bad_dtype)


def test_source_ships_with_the_package():
    assert lk_op.SOURCE.exists() and Path(lk_op.__file__).parent / "csrc" == lk_op.SOURCE.parent
