"""Mapping (paper §IV): the voxel-grid point map, back-projection and placement, rendering, TSDF mesh.

Oracles: a direct numpy voxelisation (counts, mean positions and colours); the renderer's analytic surfaces (a map
fused with ground-truth poses lies on them within the voxel size plus the depth noise; also with an unregistered
depth camera); grid symmetries (a trajectory moved by a 90-degree rotation and a whole number of voxels gives
exactly the moved map; any rigid motion gives it up to one voxel); batched equals looped; a z-buffer example.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from hydra import compose as compose_config
from hydra import initialize_config_dir
from reference import on_reference, requires_ops
from scipy.spatial import cKDTree

from torchtrack import ops
from torchtrack.config import CONF_DIR
from torchtrack.data.frame import FrameBatch
from torchtrack.data.synthetic.config import SyntheticConfig
from torchtrack.data.synthetic.motion import look_at
from torchtrack.data.synthetic.render import render_frame
from torchtrack.data.synthetic.scene import Primitive, frame_pose, make_scene, pose, random_texture
from torchtrack.factory import build_mapper, build_tracker
from torchtrack.geometry import T_inv, make_T, so3_exp
from torchtrack.map import (
    PanoramaMapper,
    VoxelPointMap,
    frame_points,
    perspective_view,
    splat,
    top_down_view,
    voxel_grid,
    voxel_keys,
)
from torchtrack.map.voxel_grid import spatial_hash
from torchtrack.run import run_tracker

VOXEL = 0.02
DEPTH_SIGMA = 0.002  # m, Gaussian noise added to the rendered depth


# ----------------------------------------------------------------------------------------------- synthetic scene


def scene_and_sdf():
    """A floor (z = 0, 1.5 m x 1.5 m half sizes), a sphere and a box on it; the unsigned distance to them."""
    prims = [
        Primitive("plane", (1.5, 1.5), frame_pose((0, 0, 0), (1, 0, 0), (0, 1, 0)), random_texture(1)),
        Primitive("sphere", (0.25,), pose((-0.3, 0.2, 0.25)), random_texture(2)),
        Primitive("box", (0.2, 0.15, 0.2), pose((0.35, -0.1, 0.2), (0, 0, 30)), random_texture(3)),
    ]
    scene = make_scene(prims, SyntheticConfig(width=160, height=120))
    R_box = pose((0, 0, 0), (0, 0, 30))[:3, :3]

    def distance(p: torch.Tensor) -> torch.Tensor:
        """(M,) unsigned distance of world points (M, 3) to the nearest surface (exact per primitive)."""
        ex = (p[:, :2].abs() - 1.5).clamp_min(0)
        floor = torch.sqrt(p[:, 2] ** 2 + (ex**2).sum(-1))
        sphere = ((p - torch.tensor([-0.3, 0.2, 0.25], dtype=p.dtype)).norm(dim=-1) - 0.25).abs()
        q = (p - torch.tensor([0.35, -0.1, 0.2], dtype=p.dtype)) @ R_box.to(p.dtype)  # into the box's frame
        d = q.abs() - torch.tensor([0.2, 0.15, 0.2], dtype=p.dtype)
        box = (d.clamp_min(0).norm(dim=-1) + d.max(-1).values.clamp_max(0)).abs()
        return torch.stack([floor, sphere, box]).min(0).values

    return scene, distance


def camera_poses(n: int) -> torch.Tensor:
    """(n, 4, 4) float64 colour cameras on an arc, 1.2-1.6 m from the props, looking at them."""
    out = []
    for i in range(n):
        a = -0.8 + 1.6 * i / max(n - 1, 1)
        eye = (1.3 * math.cos(a) + 0.1, 1.3 * math.sin(a), 0.9 + 0.1 * i)
        out.append(look_at(eye, (0.0, 0.0, 0.2)))
    return torch.stack(out).double()


def make_frames(scene, T_world_color: torch.Tensor, T_color_depth: torch.Tensor | None = None, seed: int = 0):
    """FrameBatch (B = len(T_world_color)) rendered with depth noise; depth from the depth camera when given."""
    B = len(T_world_color)
    T_cd = torch.eye(4, dtype=torch.float64) if T_color_depth is None else T_color_depth.double()
    rgb = render_frame(scene, T_world_color).rgb
    depth = render_frame(scene, T_world_color @ T_cd).depth  # the depth camera sits at T_world_color @ T_cd
    gen = torch.Generator().manual_seed(seed)
    depth = torch.where(depth > 0, depth + DEPTH_SIGMA * torch.randn(depth.shape, generator=gen), depth)
    K = scene.K.float().expand(B, 3, 3)
    return FrameBatch(
        rgb=rgb.float(), depth=depth.float(), K=K, K_depth=K, T_color_depth=T_cd.float().expand(B, 4, 4),
        timestamp=torch.arange(B, dtype=torch.float64), T_world_color_gt=T_world_color,
        gt_valid=torch.ones(B, dtype=torch.bool), active=torch.ones(B, dtype=torch.bool), index=torch.arange(B),
    )  # fmt: skip


@pytest.fixture(scope="module")
def synthetic():
    scene, distance = scene_and_sdf()
    poses = camera_poses(4)
    return scene, distance, poses, make_frames(scene, poses)


def fused(frames: FrameBatch, T_world_color: torch.Tensor, voxel: float = VOXEL, **kw) -> VoxelPointMap:
    """One map per frame row, each frame its own sequence b."""
    B = len(T_world_color)
    m = VoxelPointMap(voxel_size=voxel, batch_size=B)
    fp = frame_points(frames, T_world_color, torch.ones(B, dtype=torch.bool), **kw)
    m.add(fp.xyz, fp.rgb, fp.batch)
    return m


def accumulate(frames: FrameBatch, T_world_color: torch.Tensor, voxel: float = VOXEL) -> VoxelPointMap:
    """All frame rows fused into ONE map (sequence 0), frame by frame (streaming)."""
    m = VoxelPointMap(voxel_size=voxel, batch_size=1)
    for i in range(len(T_world_color)):
        sel = torch.zeros(len(T_world_color), dtype=torch.bool)
        sel[i] = True
        fp = frame_points(frames, T_world_color, sel)
        m.add(fp.xyz, fp.rgb, torch.zeros_like(fp.batch))
    return m


# ----------------------------------------------------------------------------------------------- voxel grid


def numpy_voxels(p: np.ndarray, c: np.ndarray, b: np.ndarray, voxel: float, seq: int):
    """The oracle: voxel index by floor, group by (b, i, j, k), means; sorted lexicographically by (i, j, k)."""
    keep = b == seq
    idx = np.floor(p[keep] / voxel).astype(np.int64)
    uniq, inv, count = np.unique(idx, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    xyz = np.zeros((len(uniq), 3))
    rgb = np.zeros((len(uniq), 3))
    np.add.at(xyz, inv, p[keep])
    np.add.at(rgb, inv, c[keep])
    return count, xyz / count[:, None], rgb / count[:, None]


@pytest.mark.equivalence
def test_voxel_map_equals_a_direct_numpy_computation(kernels):
    gen = torch.Generator().manual_seed(0)
    chunks = []
    m = VoxelPointMap(voxel_size=0.03, batch_size=3)
    for n in (300, 40, 30, 8, 20, 300, 5):  # clustered points (most voxels get several), 3 maps, 7 insertions
        centres = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 2 - 1
        p = centres.repeat_interleave(20, 0) + 0.01 * torch.randn(20 * n, 3, generator=gen, dtype=torch.float64)
        chunks.append((p, torch.rand(20 * n, 3, generator=gen), torch.randint(0, 3, (20 * n,), generator=gen)))
        m.add(*chunks[-1])
    # the index was exercised: the table grew (filled anew) and keys collided (some not in their first slot)
    home = voxel_grid._slot(m._keys[: len(m)], len(m._table))
    assert len(m._table) > 1024 and bool((m._table[home] != torch.arange(len(m))).any())
    P, C, Bt = (torch.cat(x).numpy() for x in zip(*chunks, strict=True))
    assert len(m) == sum(m.size(s) for s in range(3))
    for s in range(3):
        count, xyz, rgb = numpy_voxels(P, C.astype(np.float64), Bt, 0.03, s)
        got = m.points(s)
        assert len(got.count) == len(count) and int(got.count.sum()) == int((Bt == s).sum())
        np.testing.assert_array_equal(got.count.numpy(), count)  # key order = (i, j, k) order
        np.testing.assert_allclose(got.xyz.numpy(), xyz, atol=1e-12)
        np.testing.assert_allclose(got.rgb.numpy(), rgb, atol=1e-6)
        loose = m.points(s, ordered=False)  # the same points, the sort saved: the same rows, permuted
        order = torch.argsort(loose.xyz[:, 0] * 1e6 + loose.xyz[:, 1] * 1e3 + loose.xyz[:, 2])
        same = torch.argsort(got.xyz[:, 0] * 1e6 + got.xyz[:, 1] * 1e3 + got.xyz[:, 2])
        assert torch.equal(loose.xyz[order], got.xyz[same]) and torch.equal(loose.count[order], got.count[same])


@requires_ops
def test_the_fusion_operator_equals_the_reference():
    """voxel_add (csrc/voxel.cpp) against VoxelPointMap._add_torch over a stream of additions (known and new voxels
    mixed, points out of range, the table growing) and across a clear: the same voxels created (keys, rows) and added
    to (keys, rows), the same counts, the sums equal within float round-off (the same additions in the same order:
    measured equal)."""
    gen = torch.Generator().manual_seed(3)
    maps = [VoxelPointMap(voxel_size=0.02, batch_size=4) for _ in range(2)]
    for i in range(12):
        p = torch.rand(3000, 3, generator=gen, dtype=torch.float64) * (0.5 + 0.2 * i)  # growing: known + new
        p[:5] += 3000.0 * (i % 3 == 0)  # out of range every third addition
        c, b = torch.rand(3000, 3, generator=gen), torch.randint(0, 4, (3000,), generator=gen)
        made = [maps[0].add(p, c, b), on_reference(maps[1].add, p, c, b)]
        assert torch.equal(made[0].keys, made[1].keys) and torch.equal(made[0].rows, made[1].rows), i
        order = [torch.argsort(x.known_keys) for x in made]  # the operator's in the order the points came
        for name in ("known_keys", "known_rows"):
            got, ref = (getattr(x, name)[o] for x, o in zip(made, order, strict=True))
            assert torch.equal(got, ref), (i, name)
        if i == 6:
            maps[0].clear(2)
            on_reference(maps[1].clear, 2)
    assert maps[0].dropped == maps[1].dropped == 20 and len(maps[0]) == len(maps[1])
    assert len(maps[0]._table) > 1024  # refilled (compiled voxel_rehash) as it grew, and at the clear
    for m in maps:  # each table finds every voxel at its row
        assert torch.equal(m._find(m._keys[: len(m)]), torch.arange(len(m)))
    for s in range(4):
        got, ref = maps[0].points(s), maps[1].points(s)
        assert torch.equal(got.count, ref.count) and maps[0].size(s) == maps[1].size(s)
        torch.testing.assert_close(got.xyz, ref.xyz, atol=1e-15, rtol=0)
        torch.testing.assert_close(got.rgb, ref.rgb, atol=1e-7, rtol=0)


@requires_ops
def test_the_fusion_operator_schema_fallback_and_bad_inputs(monkeypatch):
    table, keys, sums = torch.full((64,), voxel_grid.EMPTY), torch.zeros(32, dtype=torch.long), torch.zeros(32, 7)
    p = torch.tensor([[0.0, 0, 0], [0.05, 0, 0], [0.001, 0.002, 0.003], [9e3, 0, 0]], dtype=torch.float64)
    rgb, b = torch.rand(4, 3, dtype=torch.float64), torch.tensor([0, 0, 0, 1])
    args = (table, keys, sums.double(), 0, p, rgb, b, 0.01)
    # the schema (mutated buffers declared) and the fake kernel; AOT functionalisation of an operator that mutates its
    # inputs and returns data-dependent sizes is beyond opcheck's dynamic test
    torch.library.opcheck(torch.ops.torchtrack.voxel_add.default, args, test_utils=("test_schema", "test_faketensor"))
    new_keys, rows, known_keys, known_rows, dropped = torch.ops.torchtrack.voxel_add(*args)
    assert rows.tolist() == [0, 1] and dropped == 1 and bool((new_keys[:-1] < new_keys[1:]).all())
    assert args[2][0, 6] == 2 and args[2][1, 6] == 1  # two points in the origin's voxel
    assert len(known_keys) == len(known_rows) == 0
    again = torch.ops.torchtrack.voxel_add(table, keys, args[2], 2, p[:2], rgb[:2], b[:2], 0.01)
    assert len(again[0]) == 0 and torch.equal(again[2], new_keys) and again[3].tolist() == [0, 1]  # both known now
    with pytest.raises(RuntimeError, match="half full"):
        torch.ops.torchtrack.voxel_add(torch.full((4,), -1), *args[1:])
    with pytest.raises(RuntimeError, match="power of two"):
        torch.ops.torchtrack.voxel_add(torch.full((48,), -1), *args[1:])
    with pytest.raises(RuntimeError, match="float64"):
        torch.ops.torchtrack.voxel_add(*args[:4], p.float(), *args[5:])
    refill = (torch.zeros(8, dtype=torch.long), new_keys, 2)
    torch.library.opcheck(
        torch.ops.torchtrack.voxel_rehash.default, refill, test_utils=("test_schema", "test_faketensor")
    )
    torch.ops.torchtrack.voxel_rehash(*refill)
    assert sorted(refill[0].tolist()) == [-1] * 6 + [0, 1]
    with pytest.raises(RuntimeError, match="half full"):
        torch.ops.torchtrack.voxel_rehash(torch.zeros(2, dtype=torch.long), new_keys, 2)
    # the alignment's pool after an add (tests/test_dense_map.py: against its reference and a pool picked anew)
    none = torch.zeros(0, dtype=torch.long)
    update = (new_keys[:1], torch.zeros(1, 3, dtype=torch.float64), args[2], new_keys[:1], known_rows[:0].new_zeros(1),
              new_keys[1:], rows[1:], 0, 1)  # fmt: skip
    torch.library.opcheck(
        torch.ops.torchtrack.pool_update.default, update, test_utils=("test_schema", "test_faketensor")
    )
    keys, xyz = torch.ops.torchtrack.pool_update(*update)
    assert torch.equal(keys, new_keys) and torch.equal(xyz, args[2][:2, :3] / args[2][:2, 6:])
    with pytest.raises(RuntimeError, match="not in the pool"):
        torch.ops.torchtrack.pool_update(none, xyz[:0], *update[2:])
    with pytest.raises(RuntimeError, match="in the pool already"):
        torch.ops.torchtrack.pool_update(keys, xyz, args[2], none, none, new_keys, rows, 0, 1)
    with pytest.raises(RuntimeError, match="outside the sums"):
        torch.ops.torchtrack.pool_update(none, xyz[:0], args[2], none, none, new_keys[:1], rows[:1] + 99, 0, 1)
    # where the operator does not build, the reference runs
    monkeypatch.setenv("TORCHTRACK_NO_BUILD", "1")
    monkeypatch.setattr(ops, "_state", {})
    m = VoxelPointMap(voxel_size=0.1)
    with pytest.warns(RuntimeWarning, match="unavailable"):
        m.add(torch.rand(50, 3, dtype=torch.float64), torch.rand(50, 3), torch.zeros(50, dtype=torch.long))


def test_clear_releases_one_map_and_keeps_the_others():
    gen = torch.Generator().manual_seed(1)
    p, c = torch.rand(5000, 3, generator=gen, dtype=torch.float64), torch.rand(5000, 3, generator=gen)
    b = torch.randint(0, 3, (5000,), generator=gen)
    m = VoxelPointMap(voxel_size=0.05, batch_size=3)
    m.add(p, c, b)
    before = [m.points(s) for s in range(3)]
    m.clear(1)
    assert m.size(1) == 0 and len(m) == m.size(0) + m.size(2)
    m.add(p[:100], c[:100], torch.zeros(100, dtype=torch.long))  # still usable after compaction
    after = VoxelPointMap(voxel_size=0.05, batch_size=3)
    after.add(torch.cat([p, p[:100]]), torch.cat([c, c[:100]]), torch.cat([b, torch.zeros(100, dtype=torch.long)]))
    for s in (0, 2):
        torch.testing.assert_close(m.points(s).xyz, after.points(s).xyz)
        torch.testing.assert_close(m.points(s).count, after.points(s).count)
    torch.testing.assert_close(m.points(2).rgb, before[2].rgb)


def test_prune_keeps_the_best_supported_voxels_of_one_map(kernels):
    """Oracle: the voxels a prune keeps are the protected ones, then those with the largest counts, equal counts
    ordered by spatial hash then key (numpy on the map's own points); their means and colours are unchanged, the other
    sequence is untouched, and the compacted map fuses later points into the voxels it kept as a map built from the
    kept voxels' points would."""
    gen = torch.Generator().manual_seed(4)
    p = torch.rand(6000, 3, generator=gen, dtype=torch.float64) ** 3  # denser near the origin: counts 1 to ~60
    c, b = torch.rand(6000, 3, generator=gen), torch.randint(0, 2, (6000,), generator=gen)
    m = VoxelPointMap(voxel_size=0.05, batch_size=2)
    m.add(p, c, b)
    before = [m.points(s) for s in range(2)]
    keys0 = m.voxels(0)[0]
    count = before[0].count.numpy()
    assert count.min() == 1 and count.max() > 20
    protect = keys0[torch.from_numpy(count == 1).nonzero().squeeze(1)[:5]]  # five of the least supported
    key = keys0.numpy()
    order = np.lexsort((key, spatial_hash(keys0).numpy(), -count, ~np.isin(key, protect.numpy())))
    keep = len(keys0) // 3
    expected = np.sort(key[order[:keep]])
    assert m.prune(0, keep, protect=protect) == len(keys0) - keep and m.prune(0, keep) == 0
    assert m.size(0) == keep and len(m) == keep + m.size(1)
    assert np.array_equal(m.voxels(0)[0].numpy(), expected) and np.isin(protect.numpy(), expected).all()
    at = np.searchsorted(key, expected)
    for field in range(3):
        assert torch.equal(m.points(0)[field], before[0][field][at])
        assert torch.equal(m.points(1)[field], before[1][field])
    more, c_more = torch.rand(500, 3, generator=gen, dtype=torch.float64) ** 3, torch.rand(500, 3, generator=gen)
    m.add(more, c_more, torch.zeros(500, dtype=torch.long))
    kept = torch.isin(voxel_keys(p, b, 0.05)[0], torch.from_numpy(expected)) & (b == 0)
    fresh = VoxelPointMap(voxel_size=0.05, batch_size=2)
    fresh.add(torch.cat([p[kept], more]), torch.cat([c[kept], c_more]), torch.zeros(int(kept.sum()) + 500).long())
    for field in range(3):
        torch.testing.assert_close(m.points(0)[field], fresh.points(0)[field])
    with pytest.raises(ValueError, match="keep"):
        m.prune(0, -1)


def test_points_out_of_range_are_dropped_and_counted():
    m = VoxelPointMap(voxel_size=0.01, batch_size=1)
    p = torch.tensor([[0.0, 0.0, 0.0], [5000.0, 0.0, 0.0], [0.0, -1400.0, 0.0]], dtype=torch.float64)
    m.add(p, torch.rand(3, 3), torch.zeros(3, dtype=torch.long))
    assert len(m) == 1 and m.dropped == 2
    keys, inside = voxel_keys(p, torch.zeros(3, dtype=torch.long), 0.01)
    assert inside.tolist() == [True, False, False]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(points=torch.zeros(4, 2)), "need points"),
        (dict(batch=torch.full((4,), 5)), "batch indices"),
    ],
)
def test_bad_input_raises(kwargs, message):
    m = VoxelPointMap(voxel_size=0.01, batch_size=2)
    args = dict(points=torch.zeros(4, 3, dtype=torch.float64), rgb=torch.zeros(4, 3), batch=torch.zeros(4).long())
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        m.add(args["points"], args["rgb"], args["batch"])
    with pytest.raises(ValueError, match="voxel_size"):
        VoxelPointMap(voxel_size=0.0)
    with pytest.raises(ValueError, match="every"):
        PanoramaMapper(every=0)


# ----------------------------------------------------------------------------------------------- geometry oracles


def test_map_from_ground_truth_lies_on_the_analytic_surfaces(synthetic):
    scene, distance, poses, frames = synthetic
    m = accumulate(frames, poses)
    pts = m.points(0)
    assert len(pts.count) > 2000
    d = distance(pts.xyz)
    bound = math.sqrt(3) * VOXEL / 2 + 4 * DEPTH_SIGMA  # a voxel mean is within half its diagonal of the surface
    assert float(d.max()) < bound, f"max distance {float(d.max()):.4f} m"
    assert float(d.mean()) < VOXEL / 4 + DEPTH_SIGMA
    wrong = poses.clone()
    wrong[:, :3, 3] += torch.tensor([0.05, 0.0, 0.0], dtype=torch.float64)  # a 5 cm pose error must show
    assert float(distance(accumulate(frames, wrong).points(0).xyz).max()) > bound


def test_unregistered_depth_is_placed_through_the_extrinsic():
    """Depth from a second camera 5 cm to the side, rotated 3 degrees: depth_in_colour + the colour poses put the
    points back on the surfaces (treating the depth camera as the colour one would shift them by ~5 cm)."""
    scene, distance = scene_and_sdf()
    poses = camera_poses(2)
    T_cd = make_T(so3_exp(torch.tensor([0.0, math.radians(3), 0.0], dtype=torch.float64)),
                  torch.tensor([-0.05, 0.0, 0.0], dtype=torch.float64))  # fmt: skip
    frames = make_frames(scene, poses, T_cd)
    d = distance(accumulate(frames, poses).points(0).xyz)
    # forward-warped depth holes and pixel rounding of the warp: a few points sit on silhouettes
    assert float(torch.quantile(d.float(), 0.99)) < math.sqrt(3) * VOXEL / 2 + 4 * DEPTH_SIGMA
    assert float(d.mean()) < VOXEL / 4 + DEPTH_SIGMA


def test_grid_symmetry_moves_the_map_exactly(synthetic):
    """G = 90 degrees about z and a whole number of voxels maps voxels onto voxels: the map of G @ poses is G
    applied to the map (same counts, colours; positions to float precision)."""
    scene, _, poses, frames = synthetic
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    G = make_T(R, 0.025 * torch.tensor([3.0, -7.0, 2.0], dtype=torch.float64))
    a = accumulate(frames, poses, voxel=0.025).points(0)
    b = accumulate(frames, G @ poses, voxel=0.025).points(0)
    assert len(a.count) == len(b.count)
    moved = a.xyz @ R.T + G[:3, 3]
    order_a = torch.argsort(voxel_keys(moved, torch.zeros(len(moved)).long(), 0.025)[0])
    # a voxel whose mean sits within rounding of a face could change sides: allow a few per ten thousand
    same = torch.isclose(moved[order_a], b.xyz, atol=1e-9).all(-1)
    assert float(same.float().mean()) > 0.999
    torch.testing.assert_close(a.count[order_a][same], b.count[same])
    torch.testing.assert_close(a.rgb[order_a][same], b.rgb[same])


def test_rigidly_perturbed_trajectory_gives_the_transformed_map(synthetic):
    """Any rigid G: each point of the map from G @ poses is within one voxel diagonal of G applied to the map."""
    scene, _, poses, frames = synthetic
    G = make_T(so3_exp(torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)), torch.tensor([0.7, -0.4, 0.25]).double())
    a = accumulate(frames, poses).points(0)
    b = accumulate(frames, G @ poses).points(0)
    moved = a.xyz @ G[:3, :3].T + G[:3, 3]
    for x, y in ((b.xyz, moved), (moved, b.xyz)):  # both directions (counts differ: a floor flat in the grid
        nn, _ = cKDTree(y.numpy()).query(x.numpy())  # fills one or two voxel layers, a tilted one more)
        assert nn.max() < math.sqrt(3) * VOXEL


@pytest.mark.equivalence
def test_batched_equals_looped(synthetic):
    scene, _, poses, frames = synthetic
    batched = fused(frames, poses, pixel_stride=2, edge_step=0.05)
    for b in range(len(poses)):
        one = FrameBatch(**{k: v[b : b + 1] for k, v in vars(frames).items()})
        alone = fused(one, poses[b : b + 1], pixel_stride=2, edge_step=0.05).points(0)
        got = batched.points(b)
        torch.testing.assert_close(got.count, alone.count)
        torch.testing.assert_close(got.xyz, alone.xyz, rtol=0, atol=1e-12)
        torch.testing.assert_close(got.rgb, alone.rgb, rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------------------------- mapper


class _Result:  # the fields of StepResult the mapper reads
    def __init__(self, T_world_depth: torch.Tensor, reselected: torch.Tensor):
        self.T_world_depth, self.reselected = T_world_depth, reselected


def test_mapper_fuses_first_and_model_frames_in_ground_truths_world(synthetic, tmp_path):
    """The tracker's poses (its first camera = identity) are anchored on the first ground-truth pose: fed the
    exact relative motion, the mapper's map equals the map fused directly with ground truth."""
    scene, distance, poses, frames = synthetic
    mapper = PanoramaMapper(voxel_size=VOXEL, pixel_stride=1, edge_step=None, view_size=(60, 80))
    relative = T_inv(poses[0]) @ poses
    reselected = [False, True, False, True]
    for t in range(len(poses)):
        one = FrameBatch(**{k: v[t : t + 1] for k, v in vars(frames).items()})
        one.index = torch.tensor([t])
        one.T_world_color_gt = poses[t : t + 1]
        mapper.add(one, _Result(relative[t : t + 1], torch.tensor([reselected[t]])))
    expected = accumulate(FrameBatch(**{k: v[[0, 1, 3]] for k, v in vars(frames).items()}), poses[[0, 1, 3]])
    got = mapper.points(0)
    torch.testing.assert_close(got.count, expected.points(0).count)
    torch.testing.assert_close(got.xyz, expected.points(0).xyz, rtol=0, atol=1e-9)
    stats = mapper.finish(0, tmp_path)
    assert stats["map_frames"] == 3 and stats["map_points"] == len(got.count)
    import open3d as o3d

    pcd = o3d.io.read_point_cloud(str(tmp_path / "map.ply"))
    assert len(pcd.points) == len(got.count)
    np.testing.assert_allclose(np.asarray(pcd.points), got.xyz.numpy(), atol=1e-5)  # float32 in the file
    np.testing.assert_allclose(np.asarray(pcd.colors), got.rgb.numpy(), atol=0.5 / 255 + 1e-6)
    assert (tmp_path / "map.png").stat().st_size > 0 and (tmp_path / "map.json").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left behind


def test_keyframe_policy():
    mapper = PanoramaMapper(every=3)
    idx = torch.arange(8)
    frame = FrameBatch(*([None] * 8), active=torch.tensor([True] * 7 + [False]), index=idx)
    key = mapper.keyframes(frame, idx == 4)
    assert key.tolist() == [True, False, False, True, True, False, True, False]
    assert PanoramaMapper().keyframes(frame, idx == 4).tolist() == [True] + [False] * 3 + [True] + [False] * 3


# ----------------------------------------------------------------------------------------------- rendering, TSDF


def test_splat_keeps_the_nearest_point():
    uv = torch.tensor([[5.0, 5.0], [5.2, 4.9], [1.0, 1.0]])
    z = torch.tensor([2.0, 1.0, 3.0])
    rgb = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    img, zbuf = splat(uv, z, rgb, (10, 10), radius=torch.tensor([1, 0, 0]))
    assert img[:, 5, 5].tolist() == [0.0, 1.0, 0.0]  # the nearer green point wins its pixel
    assert img[:, 4, 4].tolist() == [1.0, 0.0, 0.0]  # the red splat covers the neighbours
    assert img[:, 1, 1].tolist() == [0.0, 0.0, 1.0] and float(zbuf[1, 1]) == 3.0
    assert img[:, 8, 8].tolist() == [1.0, 1.0, 1.0] and math.isinf(float(zbuf[8, 8]))


def test_tsdf_mesh_lies_on_the_analytic_surfaces(synthetic, tmp_path):
    pytest.importorskip("open3d")
    scene, distance, poses, frames = synthetic
    mapper = PanoramaMapper(voxel_size=VOXEL, tsdf=True, tsdf_voxel_size=VOXEL, tsdf_trunc=3 * VOXEL, views=False)
    mapper.fuse(frames, poses, torch.tensor([True, False, False, False]))
    for b in (1, 2, 3):
        sel = torch.zeros(4, dtype=torch.bool)
        sel[b] = True
        mapper.fuse(frames, poses, sel)
    mesh = mapper.tsdf.mesh(0)  # only sequence 0's frame 0 went into volume 0
    vertices = torch.from_numpy(np.asarray(mesh.vertices))
    assert len(vertices) > 500
    assert float(torch.quantile(distance(vertices).float(), 0.95)) < VOXEL / 2 + 4 * DEPTH_SIGMA
    stats = mapper.finish(1, tmp_path)
    assert stats["mesh_triangles"] > 0 and (tmp_path / "mesh.ply").is_file()


# ----------------------------------------------------------------------------------------------- configuration, runner

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def compose(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose_config("config", overrides=list(overrides))


@pytest.mark.parametrize(
    ("override", "message"),
    [("mapping.voxel_size=0", "mapping.voxel_size must be > 0"), ("mapping.every=0", "must be >= 1")],
)
def test_mapping_ranges_are_checked_by_validate(override, message):
    from torchtrack.config import validate
    from torchtrack.data.errors import DataError

    with pytest.raises(DataError, match=message):
        validate(compose("mapping=panorama", override))


def test_mapping_is_off_by_default_and_one_switch_turns_it_on():
    assert build_mapper(compose()) is None
    panorama = build_mapper(compose("mapping=panorama", "mapping.voxel_size=0.02"))
    assert isinstance(panorama, PanoramaMapper) and panorama.tsdf is None and panorama.voxel_size == 0.02
    assert build_mapper(compose("mapping=tsdf")).tsdf is not None


@pytest.mark.slow
@pytest.mark.skipif(not (DATA / "sun3d_fragment1").is_dir(), reason="needs ../shared/data/sun3d_fragment1")
def test_runner_writes_the_map_and_leaves_the_trajectory_unchanged(tmp_path):
    """The runner with a mapper: same trajectory as without; map.ply has the map's points, map.png a picture."""
    import open3d as o3d

    from torchtrack.data.tum import TumSequence

    cfg = compose("data=tum", "mapping=panorama", "mapping.every=4")
    outs = {}
    for name, mapper in (("off", None), ("on", build_mapper(cfg))):
        seq = TumSequence(DATA / "sun3d_fragment1", max_frames=8)
        run_tracker(build_tracker(cfg), [seq], tmp_path / name, plots=False, mapper=mapper)
        outs[name] = tmp_path / name / seq.name
    assert (outs["on"] / "trajectory.txt").read_text() == (outs["off"] / "trajectory.txt").read_text()
    stats = json.loads((outs["on"] / "map.json").read_text())
    assert stats["map_frames"] >= 2 and not (outs["off"] / "map.ply").exists()  # frames 0 and 4 at least
    assert len(o3d.io.read_point_cloud(str(outs["on"] / "map.ply")).points) == stats["map_points"] > 10000
    assert cv2.imread(str(outs["on"] / "map.png")).shape == (480, 1280, 3)


def test_an_empty_map_writes_its_statistics_and_no_ply(tmp_path):
    stats = PanoramaMapper(views=False).finish(0, tmp_path)
    assert stats["map_points"] == 0 and stats["map_frames"] == 0 and not (tmp_path / "map.ply").exists()
    assert (tmp_path / "map.json").is_file()


def test_views_put_points_where_the_cameras_see_them():
    """Perspective: a point on the optical axis lands at the view's centre, one 0.5 m to the right at
    centre + zoom * f * 0.5 / z. Top-down: of two points on one vertical line the upper one (smaller camera y) shows."""
    K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]])
    T = look_at((0.0, -2.0, 1.0), (0.0, 0.0, 1.0))  # looking along +y, level: camera y = world -z
    xyz = torch.tensor([[0.0, 0.0, 1.0], [0.5, 0.0, 1.0]], dtype=torch.float64)
    rgb = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    img = perspective_view(xyz, rgb, T, K, (120, 160), voxel_size=0.001, zoom=0.5)
    assert img[:, 60, 80].tolist() == [1.0, 0.0, 0.0]
    assert img[:, 60, 80 + round(0.5 * 500 * 0.5 / 2.0)].tolist() == [0.0, 0.0, 1.0]
    above = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.2], [1.0, 1.0, 0.0], [-1.0, -1.0, 0.0]], dtype=torch.float64)
    colours = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    top = top_down_view(above, colours, T, (100, 100), voxel_size=0.001, margin=0.0)
    red = (top == torch.tensor([1.0, 0.0, 0.0])[:, None, None]).all(0)
    green = (top == torch.tensor([0.0, 1.0, 0.0])[:, None, None]).all(0)
    assert int(red.sum()) == 1 and int(green.sum()) == 0  # the upper point hides the lower one
