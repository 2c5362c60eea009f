"""Peer methods run beside torchtrack in evaluations (not used by the tracker itself).

Open3D's frame-to-frame RGB-D odometry (Steinbrücker et al. / Park et al. hybrid term), chained
over a sequence, is the peer of the issue's accuracy table.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from tqdm import tqdm

from torchtrack.data.tum import TumSequence

log = logging.getLogger(__name__)


def open3d_rgbd_odometry(
    seq: TumSequence, *, max_depth: float = 4.0, progress: bool = True
) -> tuple[np.ndarray, float]:
    """Chain ``compute_rgbd_odometry`` (hybrid Jacobian) frame to frame.

    Returns (T_world_cam (F, 4, 4) starting at the first ground-truth pose or identity, fps). A failed
    frame keeps the previous relative motion (constant velocity), as a tracker would.
    """
    import open3d as o3d

    H, W = seq[0].rgb.shape[-2:]
    K = seq.K.double().numpy()
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = max_depth
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(i: int):
        f = seq[i]
        colour = np.ascontiguousarray((f.rgb.permute(1, 2, 0).numpy() * 255).astype(np.uint8))
        depth = np.ascontiguousarray(f.depth[0].numpy().astype(np.float32))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(colour), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=max_depth,
            convert_rgb_to_intensity=True,
        )  # fmt: skip

    T0 = seq.groundtruth[0] if bool(seq.gt_valid[0]) else np.eye(4)
    poses = [np.asarray(T0, dtype=np.float64)]
    step = np.eye(4)
    start = time.perf_counter()
    prev = rgbd(0)
    for i in tqdm(range(1, len(seq)), desc=f"open3d odometry {seq.name}", disable=not progress):
        cur = rgbd(i)
        ok, T_prev_cur, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            cur, prev, intr, np.eye(4), jac, option
        )  # maps points of the current frame into the previous one: T_prev_cur
        if ok:
            step = T_prev_cur
        else:
            log.warning("open3d odometry failed at frame %d of %s; keeping the last motion", i, seq.name)
        poses.append(poses[-1] @ step)
        prev = cur
    fps = len(seq) / (time.perf_counter() - start)
    return np.stack(poses), fps
