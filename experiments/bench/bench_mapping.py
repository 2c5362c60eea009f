"""Per-frame cost and memory of the panorama point map at B=1, beside Open3D doing the same job.

The frames of a real sequence are read in order (decoded in the same thread, not timed) and fed to
:meth:`torchtrack.map.PanoramaMapper.add` with ground-truth poses (the tracker's output in its own world: relative
to the first frame) and the key frames of a tracker run (``--frames-csv``: its ``reselected`` column, as the CLI's
mapper fuses them) or every k-th frame (``--key-every``). Timed: every ``add`` call (key frames and the others), so
the mean is the amortised per-frame cost; target under ~3 ms.

The peer does the same with Open3D's legacy point cloud: per key frame ``create_from_rgbd_image`` (the same pixel
stride, depth range), transform, append to the map and ``voxel_down_sample`` the whole map (mean position and
colour per voxel: the same map, rebuilt each time because Open3D keeps no per-voxel sums).

    python experiments/bench/bench_mapping.py                                   # 7-Scenes kitchen, 1000 frames
    python experiments/bench/bench_mapping.py --frames-csv runs/kitchen/7scenes_redkitchen/frames.csv
    python experiments/bench/bench_mapping.py --root ../shared/data/sun3d_fragment1 --key-every 5 --no-peer
"""

from __future__ import annotations

import argparse
import csv
import resource
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from torchtrack.data.batching import iterate_batched
from torchtrack.data.tum import TumSequence
from torchtrack.geometry import T_inv
from torchtrack.map import PanoramaMapper

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


class StepStub:
    """What the mapper reads from a :class:`torchtrack.pipeline.StepResult`."""

    def __init__(self, T_world_depth: torch.Tensor, reselected: torch.Tensor):
        self.T_world_depth, self.reselected = T_world_depth, reselected


def key_frames(n: int, frames_csv: Path | None, every: int) -> np.ndarray:
    """(n,) bool: the run's re-selections, else every k-th frame (frame 0 is always fused by the mapper)."""
    if frames_csv is None:
        return np.arange(n) % every == 0
    with open(frames_csv) as f:
        flags = [row["reselected"] == "True" for row in csv.DictReader(f)]
    return np.array((flags + [False] * n)[:n])


class Open3DPeer:
    """A voxel-downsampled Open3D map rebuilt at every key frame."""

    def __init__(self, seq: TumSequence, voxel: float, stride: int, max_depth: float):
        import open3d as o3d

        self.o3d, self.voxel, self.stride, self.max_depth = o3d, voxel, stride, max_depth
        self.map = o3d.geometry.PointCloud()
        K = seq.K.double().numpy()
        self.K = K

    def add(self, rgb: torch.Tensor, depth: torch.Tensor, T_world_color: np.ndarray) -> None:
        o3d, s = self.o3d, self.stride
        colour = np.ascontiguousarray((rgb.permute(1, 2, 0)[::s, ::s].numpy() * 255).astype(np.uint8))
        d = np.ascontiguousarray(depth[0, ::s, ::s].numpy().astype(np.float32))
        h, w = d.shape
        K = self.K
        intr = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0] / s, K[1, 1] / s, K[0, 2] / s, K[1, 2] / s)
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(colour), o3d.geometry.Image(d), depth_scale=1.0, depth_trunc=self.max_depth,
            convert_rgb_to_intensity=False,
        )  # fmt: skip
        pcd = o3d.geometry.PointCloud.create_from_rgbd_image(rgbd, intr, np.linalg.inv(T_world_color))
        self.map = (self.map + pcd).voxel_down_sample(self.voxel)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--root", type=Path, default=DATA / "7scenes_redkitchen", help="sequence folder")
    ap.add_argument("--max-frames", type=int, default=None, help="first N frames (None: all)")
    ap.add_argument("--frames-csv", type=Path, default=None, help="a run's frames.csv: its re-selections")
    ap.add_argument("--key-every", type=int, default=10, help="key frames without --frames-csv")
    ap.add_argument("--voxel-size", type=float, default=0.01, help="map voxel (m)")
    ap.add_argument("--pixel-stride", type=int, default=2, help="every k-th pixel of a key frame")
    ap.add_argument("--no-peer", action="store_true", help="skip Open3D's voxel_down_sample")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)

    seq = TumSequence(args.root, max_frames=args.max_frames)
    n = len(seq)
    keys = key_frames(n, args.frames_csv, args.key_every)
    mapper = PanoramaMapper(voxel_size=args.voxel_size, pixel_stride=args.pixel_stride, views=False)
    peer = None if args.no_peer else Open3DPeer(seq, args.voxel_size, args.pixel_stride, 4.0)
    gt = torch.as_tensor(np.asarray(seq.groundtruth), dtype=torch.float64)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    ours, theirs, peak_bytes = [], [], 0
    with torch.inference_mode():
        for frame in tqdm(iterate_batched([seq], prefetch=False), total=n, desc="mapping", unit="frame"):
            i = int(frame.index[0])
            step = StepStub(T_inv(gt[0]) @ gt[i : i + 1], torch.tensor([bool(keys[i])]))
            t0 = time.perf_counter()
            mapper.add(frame, step)
            ours.append(time.perf_counter() - t0)
            peak_bytes = max(peak_bytes, mapper.map.nbytes)
            if peer is not None and (i == 0 or keys[i]):
                t0 = time.perf_counter()
                peer.add(frame.rgb[0], frame.depth[0], gt[i].numpy())
                theirs.append(time.perf_counter() - t0)
    fused = int(mapper.fused[0])
    pts = mapper.points(0)
    print(f"{seq.name}: {n} frames, {fused} fused ({'re-selections of ' + str(args.frames_csv) if args.frames_csv else f'every {args.key_every}'}), "
          f"voxel {args.voxel_size} m, pixel stride {args.pixel_stride}, {args.threads} thread(s)")  # fmt: skip
    ms = np.array(ours) * 1e3
    key_ms = ms[[i for i in range(n) if i == 0 or keys[i]]]
    print(f"ours : {ms.sum() / n:.2f} ms/frame amortised (key frame mean {key_ms.mean():.1f} ms, median "
          f"{np.median(key_ms):.1f}, max {key_ms.max():.1f};"
          f" other frames {np.delete(ms, np.flatnonzero(keys | (np.arange(n) == 0))).mean():.3f} ms)")  # fmt: skip
    print(
        f"       map {len(pts.count)} points, buffers {peak_bytes / 1e6:.0f} MB at most, "
        f"PLY {15 * len(pts.count) / 1e6 + 0.0002:.1f} MB (15 bytes a point)"
    )
    if peer is not None:
        pms = np.array(theirs) * 1e3
        print(f"peer : {pms.sum() / n:.2f} ms/frame amortised (Open3D voxel_down_sample of the growing map), "
              f"{len(peer.map.points)} points")  # fmt: skip
        print(f"ratio peer / ours (amortised): {pms.sum() / ms.sum():.1f}x")
    print(f"max RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3:.0f} MB (at start {rss0:.0f} MB)")


if __name__ == "__main__":
    main()
