"""Benchmark of the synthetic RGB-D renderer: time to render one 640x480 frame (target <= 50 ms).

    python experiments/bench/bench_synthetic.py [--frames 20] [--threads 1] [--preview /tmp/synth_preview.png]

Times ``render_frame`` (ray casting + texturing, noise-free) on the default scene and object sequences,
after a warm-up frame that bakes the planes' texture atlases (reported separately, once per scene).
Also reports the Kinect noise model and the PNG writing per frame. Wall-clock and process CPU time are
both given: on a shared machine the CPU time is the steadier number.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.data.synthetic import (
    SyntheticConfig,
    apply_kinect_noise,
    default_scene,
    frame_generator,
    render_frame,
    sequence_poses,
)

TARGET_MS = 50.0


def timed(fn, repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU milliseconds of repeats calls fn(i)."""
    wall, cpu = [], []
    for i in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn(i)
        wall.append(1e3 * (time.perf_counter() - w0))
        cpu.append(1e3 * (time.process_time() - c0))
    return wall, cpu


def preview(cfg: SyntheticConfig) -> np.ndarray:
    """One Kinect-noisy frame: colour | depth (jet, 0-4 m, black = no depth)."""
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    obj = None if poses.T_world_obj is None else poses.T_world_obj[0]
    frame = apply_kinect_noise(render_frame(scene, poses.T_world_cam[0], obj), cfg.kinect, frame_generator(cfg, 0))
    rgb = (frame.rgb.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)[:, :, ::-1]
    d = frame.depth[0].numpy()
    vis = cv2.applyColorMap((np.clip(d / 4.0, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_JET)
    vis[d == 0] = 0
    return np.concatenate([rgb, vis], axis=1)


def bench_mode(mode: str, n: int) -> float:
    """Print the timings of one mode; return the median wall milliseconds of render_frame."""
    cfg = SyntheticConfig(mode=mode, frames=n)
    scene, poses = default_scene(cfg), sequence_poses(cfg)

    def obj(i: int):
        return None if poses.T_world_obj is None else poses.T_world_obj[i]

    w0 = time.perf_counter()
    render_frame(scene, poses.T_world_cam[0], obj(0))  # bakes the plane atlases
    bake_ms = 1e3 * (time.perf_counter() - w0)
    frames = []
    wall, cpu = timed(lambda i: frames.append(render_frame(scene, poses.T_world_cam[i], obj(i))), n)
    noise_wall, _ = timed(lambda i: apply_kinect_noise(frames[i], cfg.kinect, frame_generator(cfg, i)), n)

    def write(i: int) -> None:
        cv2.imencode(".png", (frames[i].rgb.permute(1, 2, 0).numpy() * 255).astype(np.uint8))
        cv2.imencode(".png", (frames[i].depth[0].numpy() * 5000).astype(np.uint16))

    png_wall, _ = timed(write, n)
    med, med_cpu = statistics.median(wall), statistics.median(cpu)
    verdict = lambda ms: "PASS" if ms <= TARGET_MS else "FAIL"  # noqa: E731
    print(
        f"{mode:6s} 640x480 render_frame: median {med:.1f} ms wall (min {min(wall):.1f}) [{verdict(med)}], "
        f"median {med_cpu:.1f} ms CPU [{verdict(med_cpu)}]; target <= {TARGET_MS:.0f} ms"
    )
    print(
        f"{'':6s} first frame incl. atlas baking {bake_ms:.0f} ms; per frame (median): Kinect noise "
        f"{statistics.median(noise_wall):.1f} ms, PNG encode rgb+depth {statistics.median(png_wall):.1f} ms"
    )
    return med


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=20, help="timed frames per mode")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    ap.add_argument("--preview", type=Path, default=None, help="write a colour|depth PNG of frame 0 of both modes")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} intra-op thread(s) (torch.set_num_threads), {args.frames} frames")
    print(
        f"machine: {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f} (wall time inflates when it exceeds the CPUs)"
    )
    for mode in ("scene", "object"):
        bench_mode(mode, args.frames)
    if args.preview is not None:
        img = np.concatenate([preview(SyntheticConfig(mode=m)) for m in ("scene", "object")], axis=0)
        cv2.imwrite(str(args.preview), img)
        print(f"preview (scene mode top, object mode bottom; colour | depth 0-4 m) -> {args.preview}")


if __name__ == "__main__":
    main()
