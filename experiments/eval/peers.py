"""Peer methods run beside torchtrack in evaluations (not used by the tracker itself).

Every peer maps a :class:`TumSequence` to ``(T_world_cam (F, 4, 4) float64, fps)``, starting at the first
ground-truth pose (identity without one), on the sequence's colour intrinsics and metric depth:

- ``o3d_hybrid``, ``o3d_color``: Open3D legacy ``compute_rgbd_odometry``, hybrid (Park et al. 2017) and colour
  (Steinbruecker et al. 2011) terms, chained frame to frame.
- ``o3d_t_hybrid``, ``o3d_t_p2plane``: Open3D tensor ``rgbd_odometry_multi_scale``, hybrid and point-to-plane.
- ``o3d_f2m``: Open3D tensor frame-to-model tracking against the raycast of a TSDF (``t.pipelines.slam.Model``,
  1 cm voxels; KinectFusion-style, Newcombe et al. 2011).
- ``cv2_rgbd``: OpenCV 5 ``cv2.Odometry`` (RGB + depth, the common algorithm).

A failed frame-to-frame step keeps the previous relative motion (constant velocity), as a tracker would.
"""

from __future__ import annotations

import hashlib
import inspect
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from torchtrack.data.tum import TumSequence

log = logging.getLogger(__name__)

MAX_DEPTH = 4.0  # m, every peer's depth cut-off


# ----------------------------------------------------------------------------------------------- shared


def _images(seq: TumSequence) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(colour (H, W, 3) uint8, depth (H, W) float32 metres, 0 = none) per frame."""
    for i in range(len(seq)):
        f = seq[i]
        colour = np.ascontiguousarray((f.rgb.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8))
        yield colour, np.ascontiguousarray(f.depth[0].numpy().astype(np.float32))


def _first_pose(seq: TumSequence) -> np.ndarray:
    return np.asarray(seq.groundtruth[0] if bool(seq.gt_valid[0]) else np.eye(4), dtype=np.float64)


def chain_odometry(
    seq: TumSequence, prepare: Callable, relative: Callable, *, desc: str, progress: bool = True
) -> tuple[np.ndarray, float]:
    """Chain a frame-to-frame odometry: ``prepare(colour, depth) -> frame``, ``relative(prev, cur) -> T_prev_cur``
    (4, 4) mapping the current camera's points into the previous one, or None where it failed.

    Returns (T_world_cam (F, 4, 4), fps), the wall time including image conversion.
    """
    start = time.perf_counter()
    images = _images(seq)
    prev = prepare(*next(images))
    poses, step = [_first_pose(seq)], np.eye(4)
    for i, img in enumerate(tqdm(images, total=len(seq) - 1, desc=desc, disable=not progress), start=1):
        cur = prepare(*img)
        T = relative(prev, cur)
        if T is None:
            log.warning("%s failed at frame %d of %s; keeping the last motion", desc, i, seq.name)
        else:
            step = np.asarray(T, dtype=np.float64)
        poses.append(poses[-1] @ step)
        prev = cur
    return np.stack(poses), len(seq) / (time.perf_counter() - start)


def _intrinsics(seq: TumSequence) -> tuple[int, int, np.ndarray]:
    H, W = seq[0].rgb.shape[-2:]
    return H, W, seq.K.double().numpy()


# ----------------------------------------------------------------------------------------------- Open3D legacy


def open3d_rgbd_odometry(
    seq: TumSequence, *, max_depth: float = MAX_DEPTH, term: str = "hybrid", progress: bool = True
) -> tuple[np.ndarray, float]:
    """Open3D legacy ``compute_rgbd_odometry`` chained frame to frame; ``term`` "hybrid" or "color"."""
    import open3d as o3d

    H, W, K = _intrinsics(seq)
    intr = o3d.camera.PinholeCameraIntrinsic(W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = o3d.pipelines.odometry.OdometryOption()
    option.depth_max = max_depth
    odo = o3d.pipelines.odometry
    jac = {"hybrid": odo.RGBDOdometryJacobianFromHybridTerm, "color": odo.RGBDOdometryJacobianFromColorTerm}[term]()

    def prepare(colour, depth):
        return o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(colour), o3d.geometry.Image(depth), depth_scale=1.0, depth_trunc=max_depth,
            convert_rgb_to_intensity=True,
        )  # fmt: skip

    def relative(prev, cur):
        ok, T_prev_cur, _ = odo.compute_rgbd_odometry(cur, prev, intr, np.eye(4), jac, option)
        return T_prev_cur if ok else None

    return chain_odometry(seq, prepare, relative, desc=f"open3d {term} {seq.name}", progress=progress)


# ----------------------------------------------------------------------------------------------- Open3D tensor


def open3d_tensor_odometry(
    seq: TumSequence, *, max_depth: float = MAX_DEPTH, method: str = "hybrid", progress: bool = True
) -> tuple[np.ndarray, float]:
    """Open3D tensor ``rgbd_odometry_multi_scale`` (3 levels), ``method`` "hybrid" or "point_to_plane"."""
    import open3d as o3d

    odo = o3d.t.pipelines.odometry
    _, _, K = _intrinsics(seq)
    intr = o3d.core.Tensor(K, o3d.core.float64)
    kind = {"hybrid": odo.Method.Hybrid, "point_to_plane": odo.Method.PointToPlane}[method]
    eye = o3d.core.Tensor(np.eye(4), o3d.core.float64)

    def prepare(colour, depth):
        return o3d.t.geometry.RGBDImage(
            o3d.t.geometry.Image(o3d.core.Tensor(colour)), o3d.t.geometry.Image(o3d.core.Tensor(depth[..., None]))
        )

    def relative(prev, cur):
        try:
            r = odo.rgbd_odometry_multi_scale(cur, prev, intr, eye, 1.0, max_depth, method=kind)
        except RuntimeError as e:  # too few correspondences
            log.debug("tensor odometry: %s", e)
            return None
        T = r.transformation.numpy()
        return T if r.fitness > 0 and np.isfinite(T).all() else None

    return chain_odometry(seq, prepare, relative, desc=f"open3d tensor {method} {seq.name}", progress=progress)


def open3d_frame_to_model(
    seq: TumSequence, *, voxel: float = 0.01, max_depth: float = 3.0, progress: bool = True
) -> tuple[np.ndarray, float]:
    """Open3D tensor frame-to-model tracking (``t.pipelines.slam.Model``): each frame is aligned (point-to-plane)
    to the raycast of the TSDF fused so far (``voxel`` m voxels, 8-voxel truncation), then integrated."""
    import open3d as o3d

    slam, core = o3d.t.pipelines.slam, o3d.core
    H, W, K = _intrinsics(seq)
    intr = core.Tensor(K, core.float64)
    device = core.Device("CPU:0")
    T_first_cur = core.Tensor(np.eye(4), core.float64)
    model = slam.Model(voxel, 16, 40000, T_first_cur, device)
    frame, raycast = slam.Frame(H, W, intr, device), slam.Frame(H, W, intr, device)
    start, poses, last = time.perf_counter(), [], np.eye(4)
    for i, (colour, depth) in enumerate(tqdm(_images(seq), total=len(seq), desc=f"open3d f2m {seq.name}",
                                             disable=not progress)):  # fmt: skip
        frame.set_data_from_image("depth", o3d.t.geometry.Image(core.Tensor(depth[..., None])))
        rgb = core.Tensor(colour.astype(np.float32) / 255.0)  # float depth integrates with float colour only
        frame.set_data_from_image("color", o3d.t.geometry.Image(rgb))
        if i > 0:
            try:
                r = model.track_frame_to_model(frame, raycast, 1.0, max_depth, 0.07)
                T_first_cur = T_first_cur @ r.transformation
            except RuntimeError as e:
                log.warning("open3d f2m failed at frame %d of %s (%s); keeping the last motion", i, seq.name, e)
                T_first_cur = T_first_cur @ core.Tensor(last, core.float64)
            prev = poses[-1]
            last = np.linalg.solve(prev, T_first_cur.numpy())
        poses.append(T_first_cur.numpy().copy())
        model.update_frame_pose(i, T_first_cur)
        model.integrate(frame, 1.0, max_depth, 8.0)
        model.synthesize_model_frame(raycast, 1.0, 0.1, max_depth, 8.0, False)
    fps = len(seq) / (time.perf_counter() - start)
    return _first_pose(seq) @ np.stack(poses), fps


# ----------------------------------------------------------------------------------------------- OpenCV


def opencv_rgbd_odometry(
    seq: TumSequence, *, max_depth: float = MAX_DEPTH, progress: bool = True
) -> tuple[np.ndarray, float]:
    """OpenCV 5 ``cv2.Odometry`` (RGB + depth, common algorithm): camera matrix float32, depth float32 metres."""
    import cv2

    _, _, K = _intrinsics(seq)
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(K.astype(np.float32))
    settings.setMaxDepth(max_depth)
    odom = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)

    def prepare(colour, depth):
        return depth, cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY)

    def relative(prev, cur):
        ok, Rt = odom.compute(cur[0], cur[1], prev[0], prev[1])  # Rt * src = dst: src current, dst previous
        return Rt if ok and np.isfinite(Rt).all() else None

    return chain_odometry(seq, prepare, relative, desc=f"opencv odometry {seq.name}", progress=progress)


# ----------------------------------------------------------------------------------------------- registry


@dataclass(frozen=True)
class Peer:
    """A peer: ``run(seq, progress=) -> (T_world_cam (F, 4, 4), fps)``; ``label`` for tables."""

    name: str
    label: str
    run: Callable
    kwargs: dict

    def __call__(self, seq: TumSequence, progress: bool = True) -> tuple[np.ndarray, float]:
        return self.run(seq, progress=progress, **self.kwargs)

    @property
    def version(self) -> str:
        """What a cached result depends on besides the data: the library's version and this peer's code."""
        lib = "cv2" if self.run is opencv_rgbd_odometry else "open3d"
        code = inspect.getsource(self.run) + inspect.getsource(chain_odometry) + repr(sorted(self.kwargs.items()))
        return f"{lib}-{_library_version(lib)}-{hashlib.sha256(code.encode()).hexdigest()[:12]}"


def _library_version(name: str) -> str:
    return __import__(name).__version__


PEERS: dict[str, Peer] = {
    p.name: p
    for p in (
        Peer("o3d_hybrid", "Open3D legacy hybrid", open3d_rgbd_odometry, {"term": "hybrid"}),
        Peer("o3d_color", "Open3D legacy colour", open3d_rgbd_odometry, {"term": "color"}),
        Peer("o3d_t_hybrid", "Open3D tensor hybrid", open3d_tensor_odometry, {"method": "hybrid"}),
        Peer("o3d_t_p2plane", "Open3D tensor point-to-plane", open3d_tensor_odometry, {"method": "point_to_plane"}),
        Peer("o3d_f2m", "Open3D frame-to-model (TSDF 1 cm)", open3d_frame_to_model, {}),
        Peer("cv2_rgbd", "OpenCV 5 Odometry RGB-D", opencv_rgbd_odometry, {}),
    )
}
