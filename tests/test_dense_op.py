"""The compiled dense alignment (torch.ops.torchtrack.dense_fit, csrc/dense.cpp) against its pure-torch reference
(``DenseMap._fit_torch``).

Oracles: the reference on a rendered room from cameras near and far from the truth (pairs, steps, the correction, its
twist and the data's information within tests/tolerances.py DENSE_OP_*), and both at the render's exact ground truth;
the same on real depth (a map of 7-Scenes keyframes placed by their ground-truth poses); fewer than 6 pairs: no
correction from either; the fallback where the operator does not build; torch.library.opcheck for the schema and the
fake kernel; bad inputs raise. The points a keyframe adds (torch.ops.torchtrack.depth_points) against their reference
(``DenseMap._points_torch``): the same pixels in the same order, the points within float round-off.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from reference import on_reference, requires_ops
from test_dense_map import keyframe_map, pose_error, room  # noqa: F401 (room: the fixture)
from tolerances import DENSE_OP_INFO, DENSE_OP_PAIRS, DENSE_OP_POSE, DEPTH_POINTS

from torchtrack import ops
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.geometry import T_inv, se3_exp
from torchtrack.map.dense_map import DenseMap
from torchtrack.map.depth_grid import grid

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
pytestmark = requires_ops

# starts around the room's current camera: its true pose, the drifted one of test_dense_map, 10 cm and 3 degrees off
STARTS = [[0.0] * 6, None, [0.1, 0, 0, 0, 0, 0], [0, 0, 0.1, 0, 0, 0], [0, 0, 0, 0.05, 0, 0], [0, 0.02, 0, 0, 0, 0.01]]


def assert_agree(dense: DenseMap, world, depth, K, T_cw) -> tuple:
    """The operator's and the reference's fits from T_cw on the depth image (1, 1, H, W) agree; returns both."""
    depth, K = (x[0] for x in grid(depth, K, dense.stride))
    op, ref = dense.fit(world, depth, K, T_cw), dense._fit_torch(world, depth, K, T_cw)
    assert abs(op.pairs - ref.pairs) <= DENSE_OP_PAIRS * ref.pairs and op.steps == ref.steps, (op, ref)
    assert op.step < dense.tolerance or math.isclose(op.step, ref.step, rel_tol=1e-3)
    torch.testing.assert_close(op.delta, ref.delta, atol=DENSE_OP_POSE, rtol=0)
    torch.testing.assert_close(op.xi, ref.xi, atol=DENSE_OP_POSE, rtol=0)
    scale = float(ref.info.abs().max())
    torch.testing.assert_close(op.info, ref.info, atol=DENSE_OP_INFO * scale, rtol=0)
    assert op.weak or float(ratios(dense, op).min()) > dense.weak  # the gate's shortcut never skips a weak direction
    return op, ref


def ratios(dense: DenseMap, fit) -> torch.Tensor:
    """The eigenvalues (6,) ascending of the fit's information whitened by the prior (the gate's ratios), by LAPACK."""
    sd = torch.tensor([dense.prior_m] * 3 + [math.radians(dense.prior_deg)] * 3, dtype=torch.float64)
    return torch.linalg.eigvalsh(fit.info * sd[:, None] * sd[None, :])


def test_the_gates_shortcut_agrees_with_the_eigenvalues(room):  # noqa: F811
    """The operator says no direction is weak (``Fit.weak`` False, the gate's eigenproblem skipped) only where the
    smallest whitened information ratio is above ``weak``, and says so where it is clearly above: over thresholds
    around the render's smallest ratio; there the gate's correction is the fit's own, as the eigenproblem finds."""
    dense = keyframe_map(room)
    (depth,), (K,) = grid(room["d_cur"], room["K"], dense.stride)
    world, T_cw = dense._pool(0), T_inv(room["drifted"])
    eig = ratios(dense, dense.fit(world, depth, K, T_cw))
    lowest = float(eig[0])
    assert float(eig[-1]) < 1e4 * lowest  # so 0.1 % of the lowest is clear of the shortcut's 1e-9 of the largest
    for factor in (0.0, 0.5, 0.999, 1.001, 2.0, 1e3):
        dense.weak = factor * lowest
        fit = dense.fit(world, depth, K, T_cw)
        assert fit.weak == (factor > 1), (factor, lowest)
        gated = dense._gated(fit._replace(weak=True))  # the eigenproblem's answer
        assert (factor > 1) or torch.equal(gated, fit.delta)


@pytest.mark.parametrize("iterations", [1, 12])
def test_the_operator_is_the_reference_on_a_render(room, iterations):  # noqa: F811
    """One Gauss-Newton step (the normal equations as built) and the whole fit, from six starts; from the truth and
    from the drifted camera both end within 1.6 mm / 0.02 degrees of the truth (test_dense_map's bound)."""
    dense = keyframe_map(room)
    dense.iterations = iterations
    world = dense._pool(0)
    for xi in STARTS:
        T = room["drifted"] if xi is None else room["T_cur"] @ se3_exp(torch.tensor(xi, dtype=torch.float64))
        op, ref = assert_agree(dense, world, room["d_cur"], room["K"], T_inv(T))
        assert ref.pairs > 1000  # measured: 1,655 to ~4,000
        if iterations == 12 and (xi is None or xi == [0.0] * 6):
            for fit in (op, ref):
                mm, deg = pose_error(room["T_cur"], T_inv(fit.delta @ T_inv(T)))
                assert mm < 1.6 and deg < 0.02, (xi, mm, deg)


def test_too_few_pairs_give_no_correction(room):  # noqa: F811
    """A camera turned away from the map (no point in view): both fits report inf and the identity."""
    dense = keyframe_map(room)
    T = room["T_cur"] @ se3_exp(torch.tensor([0, 0, 0, 0, math.pi, 0], dtype=torch.float64))
    for fit_with in (dense.fit, dense._fit_torch):
        fit = fit_with(dense._pool(0), *(x[0] for x in grid(room["d_cur"], room["K"], dense.stride)), T_inv(T))
        assert fit.step == math.inf and fit.pairs < 6 and fit.steps == 0
        assert torch.equal(fit.delta, torch.eye(4, dtype=torch.float64)) and not bool(fit.info.any())


@pytest.mark.equivalence
@pytest.mark.skipif(not (DATA / "7scenes_redkitchen").exists(), reason="needs ../shared/data/7scenes_redkitchen")
def test_real_depth_agrees_with_the_reference():
    """7-Scenes (Kinect depth, 640 x 480): a map of frames 0, 10, 20, 30 placed by their ground truth; frame 25 from
    its true pose and from 2 cm / 1 degree off."""
    frames = list(iterate_batched([TumSequence(DATA / "7scenes_redkitchen", max_frames=31)], prefetch=False))
    dense = DenseMap()
    dense.reset(1)
    for f in frames[0:31:10]:
        T_wd = f.T_world_color_gt @ f.T_color_depth.double()
        dense.add(f.depth, f.K_depth, T_wd, torch.ones(1, dtype=torch.bool))
    f = frames[25]
    T_wd = (f.T_world_color_gt @ f.T_color_depth.double())[0]
    for xi in ([0.0] * 6, [0.02, 0, 0, 0, 0.0175, 0], [0, -0.01, 0.015, 0.01, 0, -0.01]):
        T = T_wd @ se3_exp(torch.tensor(xi, dtype=torch.float64))
        op, ref = assert_agree(dense, dense._pool(0), f.depth, f.K_depth, T_inv(T))
        assert ref.pairs > 2000


def test_fallback_opcheck_and_bad_inputs(room, monkeypatch):  # noqa: F811
    dense = keyframe_map(room)
    (depth,), (K,) = grid(room["d_cur"], room["K"], dense.stride)
    world, T_cw = dense._pool(0), T_inv(room["drifted"])
    ref = dense._fit_torch(world, depth, K, T_cw)
    monkeypatch.setenv("TORCHTRACK_NO_BUILD", "1")
    monkeypatch.setattr(ops, "_state", {})
    with pytest.warns(RuntimeWarning, match="unavailable"):
        out = dense.fit(world, depth, K, T_cw)
    assert torch.equal(out.delta, ref.delta) and out.pairs == ref.pairs
    monkeypatch.undo()
    args = (world[:2000].contiguous(), depth.float().contiguous(), K.double(), T_cw.contiguous(), 500, 3, 4.0,
            0.05, 0.01, 0.005, 0.01, 0.0175, 1e-4, 0.05, 3.0)  # fmt: skip
    torch.library.opcheck(torch.ops.torchtrack.dense_fit.default, args)
    # a strided view of the full image (what align passes), with holes, NaN and negative depth: as its cleaned copy
    full = room["d_cur"][0, 0].clone()
    full[::40, ::36], full[20::40, ::36] = float("nan"), -1.0
    view, clean = full[::4, ::4], grid(full[None, None], room["K"], 4)[0][0]
    assert not view.is_contiguous() and int((clean == 0).sum()) > int((view == 0).sum())
    a, b = (torch.ops.torchtrack.dense_fit(args[0], x, *args[2:]) for x in (view, clean))
    assert all(torch.equal(x, y) for x, y in zip(a, b, strict=True)) and a[3][0] > 300
    with pytest.raises(RuntimeError, match="float64"):
        torch.ops.torchtrack.dense_fit(world.float(), *args[1:])
    with pytest.raises(RuntimeError, match="float32"):
        torch.ops.torchtrack.dense_fit(args[0], depth.double(), *args[2:])


def test_a_keyframes_points_are_the_references(room):  # noqa: F811
    """Two sequences (the second through other intrinsics, from another pose), depth with holes, NaN, negative values
    and depth beyond max_depth, with and without a region, one or both sequences masked off, a stride that divides the
    image and one that does not: the same pixels in the same (sequence, row, column) order as the reference, the points
    within DEPTH_POINTS; a masked-off sequence adds nothing."""
    g = torch.Generator().manual_seed(5)
    depth = torch.cat([room["d_kf"], room["d_cur"] * 1.5])
    depth[0, 0, :20] = 0.0
    depth[1, 0, 8, ::3] = float("nan")
    depth[1, 0, 12, ::5] = -1.0
    K = torch.cat([room["K"], room["K"] * torch.tensor([[1.1], [0.9], [1.0]])]).double()
    T = torch.stack([room["T_kf"], room["drifted"]]).contiguous()
    region = torch.rand(depth.shape, generator=g) > 0.3
    for stride in (4, 3):
        dense = DenseMap(max_depth=3.0, stride=stride)
        for mask in ([True, True], [False, True], [False, False]):
            mask = torch.tensor(mask)
            for reg in (None, region):
                ref, b_ref = dense._points_torch(depth, K, T, mask, reg)
                out, b = torch.ops.torchtrack.depth_points(depth, reg, K, T, mask, stride, dense.max_depth)
                assert torch.equal(b, b_ref) and out.shape == ref.shape
                assert torch.equal(b.unique(), mask.nonzero().squeeze(1)) and (mask.any() or len(b) == 0)
                torch.testing.assert_close(out, ref, atol=DEPTH_POINTS, rtol=0)
    for mask in ([True, False], [False, False]):  # the fake kernel's size also at 0
        torch.library.opcheck(
            torch.ops.torchtrack.depth_points.default, (depth, region, K, T, torch.tensor(mask), 3, 3.0)
        )
    args = (depth, region, K, T, torch.tensor([True, False]), 4, 3.0)
    for bad, match in (((depth.double(), *args[1:]), "float32"), ((depth, region[:1], *args[2:]), "region"),
                       ((depth, region.byte(), *args[2:]), "region"), ((depth, region, K[:1], *args[3:]), "K"),
                       ((*args[:3], T.float(), *args[4:]), "T"), ((*args[:4], args[4][:1], 4, 3.0), "mask"),
                       ((*args[:5], 0, 3.0), "stride")):  # fmt: skip
        with pytest.raises(RuntimeError, match=match):
            torch.ops.torchtrack.depth_points(*bad)


def test_the_map_is_the_same_through_the_operators_and_the_references(room):  # noqa: F811
    """DenseMap.add through the operator and through the reference, the depth an expanded (non-contiguous) batch with a
    region on the second sequence: the same voxels, their means within DEPTH_POINTS."""
    depth, K, T = room["d_kf"].expand(2, -1, -1, -1), room["K"].expand(2, -1, -1), room["T_kf"].expand(2, 4, 4)
    region = torch.ones(2, *depth.shape[1:], dtype=torch.bool)
    region[1, :, :, : depth.shape[-1] // 2] = False
    maps = []
    for reference in (False, True):
        dense = DenseMap()
        dense.reset(2)
        args = (depth, K, T, torch.tensor([True, True]), region)
        on_reference(dense.add, *args) if reference else dense.add(*args)
        maps.append([dense.map.points(b) for b in range(2)])
    for cpp, ref in zip(*maps, strict=True):
        assert torch.equal(cpp.count, ref.count) and len(cpp.count) > 1000
        torch.testing.assert_close(cpp.xyz, ref.xyz, atol=DEPTH_POINTS, rtol=0)
    assert len(maps[0][1].count) < len(maps[0][0].count)  # the region kept half the second sequence's voxels out
