"""The dense map as one concept: what the camera saw, kept per voxel, and the camera aligned to it.

- :mod:`~torchtrack.map.voxel_grid`: :class:`VoxelPointMap`, B streaming voxel-grid point maps (a hash table; the
  fusion compiled in csrc/voxel.cpp, its torch reference beside it);
- :mod:`~torchtrack.map.depth_grid`: a depth image's strided grid and its surface (vertices, normals, validity);
- :mod:`~torchtrack.map.dense_map`: :class:`DenseMap`, the keyframes' depth as a map and the camera aligned to it
  (point-to-plane Gauss-Newton, compiled in csrc/dense.cpp, its torch reference beside it);
- :mod:`~torchtrack.map.panorama`, :mod:`~torchtrack.map.tsdf`, :mod:`~torchtrack.map.render`: the paper's
  panoramic coloured map (§IV, Figs. 8-9), a TSDF mesh and point-splat views, from the estimated poses.
"""

from torchtrack.map.dense_map import Alignment, DenseMap
from torchtrack.map.panorama import FramePoints, PanoramaMapper, frame_points, write_point_cloud
from torchtrack.map.render import perspective_view, splat, top_down_view
from torchtrack.map.tsdf import TsdfFusion
from torchtrack.map.voxel_grid import MapPoints, VoxelPointMap, voxel_keys

__all__ = [
    "Alignment", "DenseMap", "FramePoints", "MapPoints", "PanoramaMapper", "TsdfFusion", "VoxelPointMap",
    "frame_points", "perspective_view", "splat", "top_down_view", "voxel_keys", "write_point_cloud",
]  # fmt: skip
