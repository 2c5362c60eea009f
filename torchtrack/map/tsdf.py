"""TSDF fusion of the map's frames into a coloured mesh, one Open3D tensor ``VoxelBlockGrid`` per sequence.

The integration is Open3D's (Curless-Levoy weighted truncated signed distances in a hashed voxel-block volume);
this module only converts frames and poses to its types. (Open3D 0.20's legacy ``ScalableTSDFVolume`` extracts
nothing from these inputs, not even from a constant-depth plane; the tensor grid does.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from torch import Tensor

from torchtrack.geometry import T_inv
from torchtrack.io import write_atomic


class TsdfFusion:
    """B Open3D TSDF volumes; ``integrate`` takes colour-registered depth and colour-camera poses.

    Args:
        voxel_size: TSDF voxel edge, metres. trunc: truncation distance of the signed distance, metres.
        max_depth: depth beyond this is not integrated (metres). min_views: a mesh vertex needs this many
            integrated frames (the voxels' weight).
    """

    def __init__(
        self, *, voxel_size: float = 0.01, trunc: float = 0.04, max_depth: float = 4.0, min_views: int = 1
    ) -> None:
        if voxel_size <= 0 or trunc <= 0 or min_views < 1:
            raise ValueError(f"TsdfFusion: need voxel_size, trunc > 0 and min_views >= 1, got {voxel_size}, {trunc}, "
                             f"{min_views}")  # fmt: skip
        self.voxel_size, self.trunc, self.max_depth, self.min_views = voxel_size, trunc, max_depth, min_views
        self._grids: dict[int, object] = {}

    def _grid(self, b: int):
        import open3d.core as o3c
        from open3d.t.geometry import VoxelBlockGrid

        if b not in self._grids:
            f32 = o3c.float32
            self._grids[b] = VoxelBlockGrid(
                attr_names=("tsdf", "weight", "color"),
                attr_dtypes=(f32, f32, f32),
                attr_channels=(1, 1, 3),
                voxel_size=self.voxel_size,
                block_resolution=8,
                block_count=1000,
                device=o3c.Device("CPU:0"),
            )  # fmt: skip  (the block hash map grows as needed)
        return self._grids[b]

    def integrate(self, b: int, rgb: Tensor, depth: Tensor, K: Tensor, T_world_color: Tensor) -> None:
        """Fuse one frame of sequence b: rgb (3, H, W) in [0, 1], depth (H, W) metres in the colour camera's grid,
        K (3, 3) colour intrinsics, T_world_color (4, 4) the colour camera's pose. The volume is Open3D's, on the
        CPU: the frame is brought there whatever its device."""
        import open3d.core as o3c
        from open3d.t.geometry import Image

        grid = self._grid(b)
        rgb, depth, K, T_world_color = (x.cpu() for x in (rgb, depth, K, T_world_color))
        depth_im = Image(o3c.Tensor(np.ascontiguousarray(depth.float().numpy())))
        colour_im = Image(o3c.Tensor(np.ascontiguousarray(rgb.permute(1, 2, 0).float().clamp(0, 1).numpy())))
        intr = o3c.Tensor(K.double().numpy())
        extr = o3c.Tensor(T_inv(T_world_color.double()).numpy())  # world -> camera
        mult = self.trunc / self.voxel_size
        blocks = grid.compute_unique_block_coordinates(depth_im, intr, extr, 1.0, self.max_depth, mult)
        grid.integrate(blocks, depth_im, colour_im, intr, extr, 1.0, self.max_depth, mult)

    def mesh(self, b: int):
        """Sequence b's legacy ``o3d.geometry.TriangleMesh`` (empty when nothing was integrated)."""
        import open3d as o3d

        grid = self._grids.get(b)
        if grid is None:
            return o3d.geometry.TriangleMesh()
        return grid.extract_triangle_mesh(weight_threshold=self.min_views - 0.5).to_legacy()

    def write(self, b: int, path: Path) -> int:
        """Write sequence b's mesh to ``path`` (binary PLY, atomically), release its volume; returns its triangles."""
        import open3d as o3d

        mesh = self.mesh(b)

        def writer(tmp: Path) -> None:
            if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
                raise OSError(f"open3d could not write {tmp}")

        write_atomic(path, writer)
        self._grids.pop(b, None)
        return len(mesh.triangles)
