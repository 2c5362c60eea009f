"""The compiled LK operator (torch.ops.torchtrack.lk_track) against its pure-torch reference, and the loader.

Oracles: exact sub-pixel shifts of an analytic texture (known answer, both implementations); the reference
(tests/reference.py) on the same inputs, within tests/tolerances.py's LK_OP_* (sums in another order, a stop decision
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
from reference import on_reference, requires_ops
from test_lk import DATA, errors, gray_pair, to_t, warped_pair
from tolerances import LK_OP_OUTLIERS, LK_OP_PX, LK_OP_TIM, LK_PX, LK_RESIDUAL

from torchtrack import ops
from torchtrack.image.flow import combined_track, prepare_frame
from torchtrack.image.lk import lk_track_flat, lk_track_reference, pyramidal_lk
from torchtrack.image.pyramid import build_pyramid

pytestmark = requires_ops


def both(*args, **kwargs):
    """(reference, operator) of the same pyramidal_lk call."""
    return on_reference(pyramidal_lk, *args, **kwargs), pyramidal_lk(*args, **kwargs)


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
    batched = pyramidal_lk(i0, i1, pts)
    for b in range(3):
        one = pyramidal_lk(i0[b : b + 1], i1[b : b + 1], pts[b : b + 1])
        assert_agree(tuple(t[b : b + 1] for t in batched), one, px=LK_PX)
    p0, p1 = build_pyramid(i0, 3), build_pyramid(i1, 3)
    flat, img = pts.reshape(-1, 2), torch.arange(3).repeat_interleave(25)
    assert_agree(lk_track_reference(p0, p1, flat, img, flat, chunk=7), lk_track_flat(p0, p1, flat, img, flat))
    two = [torch.cat([x, x.flip(-1)], 1) for x in (i0, i1)]
    assert_agree(*both(*two, pts))


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
    kw = dict(policy="min_tim", with_residual=True)
    ref, op = on_reference(combined_track, f0, f1, pts, **kw), combined_track(f0, f1, pts, **kw)
    assert ref.valid.sum() >= 250
    assert_agree((ref.points, ref.valid, ref.residual), (op.points, op.valid, op.residual), outliers=LK_OP_OUTLIERS)
    for name in ("d_tim_int", "d_tim_sim"):
        dr, do = getattr(ref, name)[0], getattr(op, name)[0]
        fin = torch.isfinite(dr) & torch.isfinite(do) & (dr <= 1.0)
        assert (torch.isfinite(dr) != torch.isfinite(do)).sum() <= LK_OP_OUTLIERS * dr.numel()
        assert ((dr - do).abs()[fin] > LK_OP_TIM).sum() <= LK_OP_OUTLIERS * dr.numel()


# ---------------------------------------------------------------------------------------------- build, fallback, fake
def test_fallback_when_the_build_is_disabled(monkeypatch):
    """TORCHTRACK_NO_BUILD=1: one warning, once; the reference runs (the same computation: exact)."""
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.7, -1.3]), n=20)
    ref = on_reference(pyramidal_lk, i0, i1, pts)
    monkeypatch.setenv("TORCHTRACK_NO_BUILD", "1")
    monkeypatch.setattr(ops, "_state", {})
    with pytest.warns(RuntimeWarning, match="compiled operators unavailable"):
        out = pyramidal_lk(i0, i1, pts)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        again = pyramidal_lk(i0, i1, pts)  # no second warning
    for r in (out, again):
        assert torch.equal(r.points, ref.points) and torch.equal(r.status, ref.status)
    assert not ops.compiled(pts) and "TORCHTRACK_NO_BUILD" in ops.error()


def test_other_devices_run_the_reference():
    """The operators have CPU kernels only: a tensor elsewhere (meta, here) takes the reference."""
    assert ops.compiled(torch.zeros(1)) and not ops.compiled(torch.zeros(1, device="meta"))


def test_build_is_cached_by_source_hash(monkeypatch):
    """The library sits in $TORCHTRACK_CACHE/ext/ops_<hash of sources, flags, torch>: another flag is another build."""
    folder, library = ops._library()
    assert folder.name == f"ops_{ops.build_key()}" and library.is_file() and not (folder / "lock").exists()
    monkeypatch.setattr(ops, "CFLAGS", [*ops.CFLAGS, "-g"])
    assert ops.build_key() != folder.name[len("ops_") :]


def test_a_process_loads_the_library_once(monkeypatch, tmp_path):
    """Loaded once, the operators are never loaded again, from this cache or another (a second copy registers them
    twice, and torch aborts the process): with TORCHTRACK_CACHE moved to an empty folder and the decision forgotten,
    available() builds and loads nothing and the operators still run."""

    def refuse(*args, **kwargs):
        raise AssertionError("a second copy of the operators' library was loaded or built")

    assert ops.loaded()
    monkeypatch.setenv("TORCHTRACK_CACHE", str(tmp_path))
    monkeypatch.setattr(ops, "_state", {})
    monkeypatch.setattr(torch.ops, "load_library", refuse)
    monkeypatch.setattr("torch.utils.cpp_extension.load", refuse)
    assert not ops.needs_build() and ops.available() and ops._load() == 0.0
    assert not any(tmp_path.iterdir())
    i0, i1, pts, _ = warped_pair(np.eye(2), np.array([0.5, 0.5]), n=5)
    assert pyramidal_lk(i0, i1, pts).status.all()


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


def test_sources_ship_with_the_package():
    """Every source beside the package it speeds up, and each named in the package data (pyproject.toml)."""
    root = Path(ops.__file__).parent
    assert [s.relative_to(root).as_posix() for s in ops.SOURCES] == [
        "image/csrc/lk.cpp", "image/csrc/sim.cpp", "map/csrc/dense.cpp", "map/csrc/voxel.cpp"]  # fmt: skip
    assert all(s.exists() for s in ops.SOURCES)
    data = (root.parent / "pyproject.toml").read_text()
    assert '"torchtrack.image" = ["csrc/*.cpp"]' in data and '"torchtrack.map" = ["csrc/*.cpp"]' in data
