"""Mapping: panoramic coloured 3D maps from the estimated poses (paper §IV, Figs. 8-9)."""

from torchtrack.mapping.panorama import FramePoints, PanoramaMapper, frame_points, write_point_cloud
from torchtrack.mapping.render import perspective_view, splat, top_down_view
from torchtrack.mapping.tsdf import TsdfFusion
from torchtrack.mapping.voxel_grid import MapPoints, VoxelPointMap, voxel_keys

__all__ = [
    "FramePoints", "MapPoints", "PanoramaMapper", "TsdfFusion", "VoxelPointMap", "frame_points", "perspective_view",
    "splat", "top_down_view", "voxel_keys", "write_point_cloud",
]  # fmt: skip
