"""Outside the kernels too, every tensor follows its inputs' device: the panorama mapper and its views, the metrics,
and the host-side synthetic renderer.

As in ``test_layers``: the default device is set to ``meta`` while the stages run on CPU inputs, so a tensor made
without the inputs' device lands on ``meta`` and fails the first operation that mixes it with them. The oracle is
the same call outside the ``meta`` context: results must be equal bit for bit and on the CPU.
"""

from __future__ import annotations

import math

import pytest
import torch

from torchtrack.data.frame import FrameBatch
from torchtrack.data.synthetic.config import SyntheticConfig
from torchtrack.data.synthetic.motion import look_at
from torchtrack.data.synthetic.render import render_frame
from torchtrack.data.synthetic.scene import Primitive, frame_pose, make_scene, pose, random_texture
from torchtrack.geometry import T_inv, make_T, project, so3_exp, transform_points
from torchtrack.map import PanoramaMapper, VoxelPointMap
from torchtrack.map.panorama import render_views
from torchtrack.metrics import ate, reprojection_error, rpe, trajectory_metrics


def _scene():
    prims = [
        Primitive("plane", (1.0, 1.0), frame_pose((0, 0, 0), (1, 0, 0), (0, 1, 0)), random_texture(1)),
        Primitive("sphere", (0.2,), pose((0.1, 0.0, 0.2)), random_texture(2)),
    ]
    return make_scene(prims, SyntheticConfig(width=80, height=60))


def _poses(n: int) -> torch.Tensor:
    """(n, 4, 4) float64 colour cameras on an arc looking at the sphere."""
    return torch.stack(
        [look_at((1.2 * math.cos(0.3 * i), 1.2 * math.sin(0.3 * i), 0.8), (0, 0, 0.2)) for i in range(n)]
    )


def _frame(rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T_world_color: torch.Tensor, t: int) -> FrameBatch:
    """Frame t of one sequence (B = 1); made on the CPU explicitly, as a reader does (called inside the context)."""
    cpu, yes = "cpu", torch.ones(1, dtype=torch.bool, device="cpu")
    return FrameBatch(
        rgb=rgb[t : t + 1], depth=depth[t : t + 1], K=K, K_depth=K, T_color_depth=torch.eye(4, device=cpu)[None],
        timestamp=torch.tensor([float(t)], dtype=torch.float64, device=cpu), T_world_color_gt=T_world_color[t : t + 1],
        gt_valid=yes, active=yes, index=torch.tensor([t], device=cpu),
    )  # fmt: skip


class _Result:  # the fields of StepResult the mapper reads
    def __init__(self, T_world_depth: torch.Tensor, reselected: torch.Tensor):
        self.T_world_depth, self.reselected = T_world_depth, reselected


def test_synthetic_renderer_is_host_side():
    """The renderer makes its tensors on the CPU by design: it renders the same frames whatever the default device."""
    poses = _poses(2)
    expected = render_frame(_scene(), poses)
    scene = _scene()  # fresh lazy caches (ray grid, atlases), built inside the context
    with torch.device("meta"):
        got = render_frame(scene, poses)
    assert got.rgb.device.type == "cpu" and got.depth.device.type == "cpu"
    assert torch.equal(got.rgb, expected.rgb) and torch.equal(got.depth, expected.depth)


@pytest.fixture(scope="module")
def frames():
    poses = _poses(3)
    out = render_frame(_scene(), poses)
    return out.rgb.float(), out.depth.float(), _scene().K.float().expand(1, 3, 3), poses.double()


def _map(frames, tmp_path):
    rgb, depth, K, poses = frames
    mapper = PanoramaMapper(voxel_size=0.02, pixel_stride=1, view_size=(30, 40))
    relative = T_inv(poses[0]) @ poses  # the tracker's poses: its first camera is the identity
    for t in range(len(poses)):
        mapper.add(_frame(rgb, depth, K, poses, t), _Result(relative[t : t + 1], torch.tensor([t == 2], device="cpu")))
    pts = mapper.points(0)
    views = render_views(pts, mapper.first[0], mapper.K[0], (30, 40), 0.02)
    stats = mapper.finish(0, tmp_path)
    return pts, views, stats, mapper.fused


def test_panorama_mapper_follows_the_frames_device(frames, tmp_path):
    """Anchoring, fusing, the map's read-out, its views and the files: no tensor off the frames' device."""
    expected = _map(frames, tmp_path / "plain")
    with torch.device("meta"):
        got = _map(frames, tmp_path / "meta")
    for a, b in zip([*got[0], got[1], got[3]], [*expected[0], expected[1], expected[3]], strict=True):
        assert a.device.type == "cpu" and torch.equal(a, b)
    assert got[2] == expected[2] and got[2]["map_points"] > 0 and got[2]["map_frames"] == 2
    assert (tmp_path / "meta" / "map.ply").read_bytes() == (tmp_path / "plain" / "map.ply").read_bytes()


def test_voxel_map_refuses_points_off_its_device():
    m = VoxelPointMap(voxel_size=0.1, batch_size=1)
    assert m.device.type == "cpu"
    points = torch.zeros(2, 3, dtype=torch.float64, device="meta")
    with pytest.raises(ValueError, match="device"):
        m.add(points, torch.zeros(2, 3, device="meta"), torch.zeros(2, dtype=torch.int64, device="meta"))


def _metrics(T_est, T_gt, stamps, K, X, x):
    m = trajectory_metrics(stamps, T_est, T_gt)
    a, r = ate(T_est, T_gt, align=False), rpe(T_est, T_gt, delta=0.05, unit="meters")
    return m, a.errors, a.T_align, r.pairs, r.trans_errors, reprojection_error(K, T_est[0], X, x)


def test_metrics_follow_the_inputs_device():
    g = torch.Generator().manual_seed(0)
    F = 12
    w = 0.05 * torch.randn(F, 3, generator=g, dtype=torch.float64)
    t = torch.cumsum(0.03 * torch.randn(F, 3, generator=g, dtype=torch.float64), 0)
    t[:, 2] += 1.5
    T_gt = make_T(so3_exp(w), t)
    T_est = make_T(so3_exp(w + 0.01 * torch.randn(F, 3, generator=g, dtype=torch.float64)), t + 0.005)
    stamps = torch.arange(F, dtype=torch.float64) / 30
    K = torch.tensor([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]], dtype=torch.float64)
    X = 0.2 * torch.randn(20, 3, generator=g, dtype=torch.float64)
    x = project(K, transform_points(T_est[0], X)) + 0.5
    expected = _metrics(T_est, T_gt, stamps, K, X, x)
    with torch.device("meta"):
        got = _metrics(T_est, T_gt, stamps, K, X, x)
    assert got[0] == expected[0]
    for a, b in zip(got[1:], expected[1:], strict=True):
        assert a.device.type == "cpu" and torch.equal(a, b)
    assert len(got[3]) > 0 and torch.isclose(got[5], torch.tensor(0.5 * math.sqrt(2), dtype=torch.float64))
