"""The paper's panorama (§IV, Figs. 8-9): each model frame's coloured point cloud placed in the world with its
estimated pose and accumulated, here into a voxel grid so that memory stays bounded.

Frames. Points are placed with the colour camera's pose ``T_world_color``: the colour image's pixels are
back-projected through the depth registered to the colour camera (:func:`torchtrack.frontend.depth_in_colour`), and
ground truth (TUM) is the colour camera's. The tracker estimates the depth camera's motion in its own world (its
first depth camera); the mapper turns it into the colour camera's pose in the world of ``trajectory.txt`` with the
same helpers as the runner (:mod:`torchtrack.geometry.rig`), so the map and the written trajectory agree.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack.data.frame import FrameBatch
from torchtrack.frontend import depth_in_colour, smooth_depth_mask
from torchtrack.geometry import backproject, transform_points
from torchtrack.geometry.rig import color_poses, tracker_world
from torchtrack.io import write_atomic, write_json
from torchtrack.map.render import perspective_view, top_down_view
from torchtrack.map.tsdf import TsdfFusion
from torchtrack.map.voxel_grid import MapPoints, VoxelPointMap

log = logging.getLogger(__name__)


class FramePoints(NamedTuple):
    """Back-projected pixels of the selected sequences: xyz (P, 3) float64 world, rgb (P, 3), batch (P,) int64;
    depth (n, 1, H, W) the colour-registered depth of the n selected sequences ``selected`` (n,)."""

    xyz: Tensor
    rgb: Tensor
    batch: Tensor
    depth: Tensor
    selected: Tensor


def frame_points(
    frame: FrameBatch, T_world_color: Tensor, select: Tensor, *, pixel_stride: int = 1, min_depth: float = 0.1,
    max_depth: float = 4.0, edge_step: float | None = None,
) -> FramePoints:  # fmt: skip
    """The coloured points of every ``pixel_stride``-th colour pixel (in x and y) with depth in (min_depth,
    max_depth) of the sequences where ``select`` (B,) bool, placed with T_world_color (B, 4, 4) (colour camera to
    world). ``edge_step``: drop pixels whose 3x3 window of the subsampled grid has a hole or a depth step above
    ``edge_step`` times their depth (flying pixels at occlusion boundaries)."""
    if T_world_color.shape != (len(select), 4, 4) or frame.rgb.shape[0] != len(select):
        raise ValueError(f"frame_points: need T_world_color (B, 4, 4) and select (B,) for B = {frame.rgb.shape[0]}, "
                         f"got {tuple(T_world_color.shape)}, {tuple(select.shape)}")  # fmt: skip
    sel, s = select.nonzero()[:, 0], pixel_stride
    depth = depth_in_colour(frame)[sel]  # n,1,H,W
    z = depth[:, :, ::s, ::s]  # n,1,h,w
    ok = (z > min_depth) & (z < max_depth)
    if edge_step is not None:
        ok &= smooth_depth_mask(z, edge_step, radius=1)
    ok = ok[:, 0]
    i, row, col = ok.nonzero(as_tuple=True)  # P: sequence, row and column in the subsampled grid (by sequence)
    counts = ok.flatten(1).sum(1).tolist()  # points per selected sequence (nonzero orders them by sequence)
    zp = z[:, 0][i, row, col].double().split(counts)
    uv = torch.stack([col * s, row * s], -1).double().split(counts)  # colour pixels
    K, T = frame.K[sel].double(), T_world_color[sel].double()
    xyz = torch.cat([transform_points(T[k], backproject(K[k], uv[k], zp[k])) for k in range(len(sel))])
    rgb = frame.rgb[:, :, ::s, ::s][sel].permute(0, 2, 3, 1)[i, row, col]
    return FramePoints(xyz, rgb, sel[i], depth, sel)


class PanoramaMapper:
    """Streams a tracker's results into B coloured voxel-grid maps; writes ``map.ply``, ``map.png`` (and
    ``mesh.ply`` with ``tsdf``) per sequence.

    Fused frames: the first frame and every model (key) frame (``StepResult.reselected``), plus every ``every``-th
    frame when set. Each is placed with the estimate of the frame where it was taken.

    Args:
        voxel_size: point-map voxel edge, metres. every: also fuse every k-th frame (None: model frames only).
        pixel_stride: back-project every n-th pixel in x and y. min_depth, max_depth: metres.
        edge_step: relative depth step of the flying-pixel filter (None: off).
        tsdf: also fuse the same frames into an Open3D TSDF volume (``tsdf_voxel_size``, ``tsdf_trunc``) -> mesh.
        views: write ``map.png``. view_size: (H, W) of each view.
    """

    def __init__(
        self,
        *,
        voxel_size: float = 0.01,
        every: int | None = None,
        pixel_stride: int = 2,
        min_depth: float = 0.1,
        max_depth: float = 4.0,
        edge_step: float | None = 0.05,
        tsdf: bool = False,
        tsdf_voxel_size: float = 0.01,
        tsdf_trunc: float = 0.04,
        views: bool = True,
        view_size: tuple[int, int] = (480, 640),
    ) -> None:
        if voxel_size <= 0:
            raise ValueError(f"PanoramaMapper: voxel_size must be > 0, got {voxel_size}")
        if every is not None and every < 1:
            raise ValueError(f"PanoramaMapper: every must be >= 1 or None, got {every}")
        if pixel_stride < 1 or not 0 <= min_depth < max_depth:
            raise ValueError(f"PanoramaMapper: need pixel_stride >= 1 and 0 <= min_depth < max_depth, got "
                             f"{pixel_stride}, {min_depth}, {max_depth}")  # fmt: skip
        self.voxel_size, self.every, self.views, self.view_size = voxel_size, every, views, tuple(view_size)
        self.points_kw = dict(pixel_stride=pixel_stride, min_depth=min_depth, max_depth=max_depth, edge_step=edge_step)
        self.tsdf = TsdfFusion(voxel_size=tsdf_voxel_size, trunc=tsdf_trunc, max_depth=max_depth) if tsdf else None
        self.map: VoxelPointMap | None = None
        self.anchor: Tensor | None = None  # (B, 4, 4) T_world_tracker: the tracker's world in the written trajectory's
        self.started: Tensor | None = None  # (B,) the sequence's anchor is set
        self.first: Tensor | None = None  # (B, 4, 4) the first colour camera's pose, for the perspective view
        self.K: Tensor | None = None  # (B, 3, 3) colour intrinsics
        self.fused: Tensor | None = None  # (B,) frames fused

    def keyframes(self, frame: FrameBatch, reselected: Tensor) -> Tensor:
        """(B,) bool: the frames to fuse (active, and first, model frame or every k-th)."""
        key = (frame.index == 0) | reselected
        if self.every is not None:
            key |= frame.index % self.every == 0
        return key & frame.active

    def add(self, frame: FrameBatch, res) -> None:
        """Fuse this frame where it is a key frame; ``res`` a :class:`torchtrack.pipeline.StepResult`."""
        B, dev = frame.rgb.shape[0], frame.rgb.device
        if self.map is None:
            self.map = VoxelPointMap(voxel_size=self.voxel_size, batch_size=B, device=dev)
            self.anchor = torch.eye(4, dtype=torch.float64, device=dev).repeat(B, 1, 1)
            self.fused = torch.zeros(B, dtype=torch.int64, device=dev)
            self.first, self.K = self.anchor.clone(), frame.K.clone()
            self.started = torch.zeros(B, dtype=torch.bool, device=dev)
        start = frame.active & ~self.started  # each sequence's first tracked frame (frame 0 may have been dropped)
        if start.any():
            self.anchor[start] = tracker_world(
                frame.T_world_color_gt[start], frame.gt_valid[start], frame.T_color_depth[start]
            )
            self.started |= start
        T_world_color = color_poses(self.anchor, res.T_world_depth, frame.T_color_depth)
        if start.any():
            self.first[start] = T_world_color[start]
        self.fuse(frame, T_world_color, self.keyframes(frame, res.reselected))

    def fuse(self, frame: FrameBatch, T_world_color: Tensor, select: Tensor) -> None:
        """Fuse the frames of the sequences where ``select`` (B,) with the colour cameras' poses T_world_color
        (B, 4, 4) (the first call's poses are the perspective view's cameras when :meth:`add` was not used)."""
        if self.map is None:
            B, dev = len(select), frame.rgb.device
            self.map = VoxelPointMap(voxel_size=self.voxel_size, batch_size=B, device=dev)
            self.fused = torch.zeros(B, dtype=torch.int64, device=dev)
            self.first, self.K = T_world_color.double().clone(), frame.K.clone()
        if not bool(select.any()):
            return
        fp = frame_points(frame, T_world_color, select, **self.points_kw)
        self.map.add(fp.xyz, fp.rgb, fp.batch)
        self.fused[fp.selected] += 1
        if self.tsdf is not None:
            for i, b in enumerate(fp.selected.tolist()):
                self.tsdf.integrate(b, frame.rgb[b], fp.depth[i, 0], frame.K[b], T_world_color[b])

    def points(self, b: int = 0) -> MapPoints:
        """Sequence b's map so far (on the frames' device; an empty one on the CPU before any frame)."""
        if self.map is None:
            xyz = torch.zeros(0, 3, dtype=torch.float64, device="cpu")
            return MapPoints(xyz, torch.zeros(0, 3, device="cpu"), torch.zeros(0, dtype=torch.int64, device="cpu"))
        return self.map.points(b)

    def finish(self, b: int, out_dir: Path) -> dict:
        """Write sequence b's ``map.ply`` (+ ``mesh.ply``), ``map.png`` and ``map.json`` into ``out_dir``; release
        its memory. Returns the statistics written to ``map.json``."""
        out_dir = Path(out_dir)
        pts = self.points(b)
        stats = {
            "map_points": len(pts.count),
            "map_frames": int(self.fused[b]) if self.fused is not None else 0,
            "voxel_size_m": self.voxel_size,
            "map_ply_mb": 0.0,
        }
        if len(pts.count):  # PLY writers refuse an empty cloud (no depth in any fused frame)
            stats["map_ply_mb"] = write_point_cloud(out_dir / "map.ply", pts).stat().st_size / 1e6
        else:
            log.warning("map of %s is empty (no depth in the fused frames): no map.ply", out_dir.name)
        if self.tsdf is not None:
            stats["mesh_triangles"] = self.tsdf.write(b, out_dir / "mesh.ply")
        if self.views and self.first is not None:
            write_views(out_dir / "map.png", pts, self.first[b], self.K[b], self.view_size, self.voxel_size)
        if self.map is not None:
            self.map.clear(b)
        write_json(out_dir / "map.json", stats)
        log.info("map of %s: %d points from %d frames", out_dir.name, stats["map_points"], stats["map_frames"])
        return stats


def write_point_cloud(path: Path, pts: MapPoints) -> Path:
    """Binary PLY of the map (float32 x, y, z and uchar red, green, blue: 15 bytes a point) via Open3D's tensor
    point cloud, written atomically."""
    import open3d as o3d

    pcd = o3d.t.geometry.PointCloud()
    pcd.point.positions = o3d.core.Tensor(pts.xyz.float().cpu().numpy())
    pcd.point.colors = o3d.core.Tensor((pts.rgb.clamp(0, 1) * 255).round().byte().cpu().numpy())

    def writer(tmp: Path) -> None:
        if not o3d.t.io.write_point_cloud(str(tmp), pcd, write_ascii=False):
            raise OSError(f"open3d could not write {tmp}")

    return write_atomic(path, writer)


def render_views(pts: MapPoints, T_world_color0: Tensor, K: Tensor, size: tuple[int, int], voxel_size: float) -> Tensor:
    """(3, H, 2W) float32: the perspective view from the first colour camera beside the top-down view."""
    persp = perspective_view(pts.xyz, pts.rgb, T_world_color0, K, size, voxel_size)
    top = top_down_view(pts.xyz, pts.rgb, T_world_color0, size, voxel_size)
    return torch.cat([persp, top], dim=-1)


def write_views(
    path: Path, pts: MapPoints, T_world_color0: Tensor, K: Tensor, size: tuple[int, int], voxel_size: float
) -> Path:
    """``map.png``: :func:`render_views` with a caption per view, written atomically."""
    import cv2

    img = render_views(pts, T_world_color0, K, size, voxel_size)
    bgr = np.ascontiguousarray((img.flip(0).permute(1, 2, 0).clamp(0, 1) * 255).round().byte().cpu().numpy())
    for x, text in ((8, "from the first camera"), (size[1] + 8, "top-down")):
        cv2.putText(bgr, text, (x, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
    cv2.line(bgr, (size[1], 0), (size[1], size[0] - 1), (128, 128, 128), 1)

    def writer(tmp: Path) -> None:
        if not cv2.imwrite(str(tmp), bgr):
            raise OSError(f"cv2.imwrite could not write {tmp}")

    return write_atomic(path, writer)
