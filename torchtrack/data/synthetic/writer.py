"""Render a whole synthetic sequence into a TUM-layout folder, atomically, with a config-keyed cache."""

from __future__ import annotations

import json
import logging
import os
import shutil
import uuid
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from torchtrack.data.synthetic.config import RENDERER_VERSION, SensorEffects, SyntheticConfig
from torchtrack.data.synthetic.effects import effect_poses, flying_pixels, light_gain, shift_depth
from torchtrack.data.synthetic.motion import sequence_poses
from torchtrack.data.synthetic.noise import apply_kinect_noise
from torchtrack.data.synthetic.render import RGBD, render_frame
from torchtrack.data.synthetic.scene import Scene, default_scene
from torchtrack.geometry import T_inv, intrinsics_matrix, matrix_to_quat_xyzw

log = logging.getLogger(__name__)

_NOISE_SEED_OFFSET = 104_729
_FLYING_INDEX_OFFSET = 1_000_003  # frame_generator(cfg, i + this) draws frame i's flying pixels


def frame_generator(cfg: SyntheticConfig, index: int) -> torch.Generator:
    """Noise generator of frame `index`: depends on (seed, index) only, so frames are reproducible alone."""
    return torch.Generator().manual_seed((int(cfg.seed) * 1_000_003 + _NOISE_SEED_OFFSET + index * 7_919) % 2**62)


def _write_tum_trajectory(path: Path, timestamps: list[str], T: Tensor, header: list[str]) -> None:
    """TUM trajectory file: '# ...' header lines, then 'timestamp tx ty tz qx qy qz qw' per pose T (F, 4, 4)."""
    q = matrix_to_quat_xyzw(T[:, :3, :3].double()).tolist()
    t = T[:, :3, 3].double().tolist()
    lines = [f"# {h}" for h in header] + ["# timestamp tx ty tz qx qy qz qw"]
    lines += [" ".join([ts] + [f"{v:.9f}" for v in ti + qi]) for ts, ti, qi in zip(timestamps, t, q, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def _write_images(folder: Path, name: str, rgb: Tensor, depth: Tensor, depth_scale: float) -> None:
    """rgb (3, H, W) in [0, 1] -> 8-bit PNG; depth (1, H, W) metres -> 16-bit PNG of depth * depth_scale."""
    img = (rgb.permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
    d = np.round(depth[0].double().numpy() * depth_scale)
    d = np.where((d > 0) & (d <= 65535), d, 0).astype(np.uint16)  # beyond the 16-bit range: no measurement
    if not cv2.imwrite(str(folder / "rgb" / name), img[:, :, ::-1]) or not cv2.imwrite(str(folder / "depth" / name), d):
        raise OSError(f"render_sequence: could not write {name} into {folder}")


def _source_text(cfg: SyntheticConfig, T_world_cam0: Tensor) -> str:
    gt = (
        "groundtruth.txt: camera-to-world T_world_cam per frame (TUM convention); world = the static room."
        if cfg.mode == "scene"
        else "groundtruth.txt: the camera pose relative to the OBJECT, T_obj_cam = inv(T_cam_obj), i.e. the TUM\n"
        "  camera-to-world trajectory with world := object frame; tracking the object yields a trajectory\n"
        "  comparable to it. object_pose.txt: T_cam_obj (object-to-camera, maps object coordinates into the\n"
        "  camera) per frame, in the same 'timestamp tx ty tz qx qy qz qw' format. The camera itself is static\n"
        f"  in the room at T_world_cam = {[[round(v, 6) for v in row] for row in T_world_cam0.tolist()]};\n"
        "  the static background (if any) does NOT follow groundtruth.txt."
    )
    noise = (
        "none: exact depth (up to the 1/depth_scale PNG step) and exact colour (up to 8-bit rounding)."
        if cfg.noise == "none"
        else "kinect: depth + N(0, sigma(z)), sigma(z) = a + b (z - z0)^2 (Nguyen, Izadi & Lovell 2012), snapped\n"
        "  to 1/8-pixel disparity steps (Khoshelham & Elberink 2012), holes at depth jumps and random dropouts,\n"
        "  working range [min_depth_m, max_depth_m]; colour + N(0, rgb_sigma). Parameters under 'kinect' below."
    )
    return (
        f"torchtrack synthetic RGB-D sequence (torchtrack.data.synthetic, renderer version {RENDERER_VERSION})\n"
        "Analytic ray casting of textured planes, boxes, spheres and cylinders; exact poses.\n"
        f"mode: {cfg.mode}; frames: {cfg.frames}; seed: {cfg.seed}; config digest: {cfg.digest()}\n"
        f"{gt}\n"
        f"noise: {noise}\n"
        f"Timestamps: frame index / {cfg.fps:g} s; colour and depth share them and their file names.\n"
        f"Layout (TUM): rgb/*.png 8-bit RGB, depth/*.png 16-bit, metres = value / {cfg.depth_scale:g}, 0 = none;\n"
        + (
            "  rgb.txt, depth.txt 'timestamp filename'; intrinsics.txt 'fx fy cx cy depth_scale'; depth registered\n"
            "  to colour (same camera). config.json: the full resolved configuration.\n"
            if cfg.depth_camera is None
            else "  rgb.txt, depth.txt 'timestamp filename'; intrinsics.txt 'fx fy cx cy depth_scale' of the colour camera;\n"
            "  depth from a second camera: depth_camera in config.json (fx, fy, cx, cy, T_color_depth = depth-to-colour).\n"
            "  config.json: the full resolved configuration.\n"
        )
        + "Reproduce: torchtrack-synth --out DIR "
        f"--frames {cfg.frames} --seed {cfg.seed} --mode {cfg.mode} --noise {cfg.noise} "
        f"--width {cfg.width} --height {cfg.height} (other parameters: config.json)\n"
        "Licence: generated data, no third-party content.\n"
        f"Parameters:\n{json.dumps(cfg.to_dict(), indent=1, sort_keys=True)}\n"
    )


def _depth_camera(cfg: SyntheticConfig, scene: Scene) -> tuple[Scene, Tensor] | None:
    """The depth camera's scene (its intrinsics, same primitives) and T_color_depth (4, 4); None when registered."""
    d = cfg.depth_camera
    if d is None:
        return None
    K = intrinsics_matrix(d["fx"], d["fy"], d["cx"], d["cy"]).to(scene.K.dtype)
    T_color_depth = torch.tensor(d["T_color_depth"], dtype=torch.float64, device="cpu")
    return replace(scene, K=K, _dirs=None, _xy_flat=None), T_color_depth


def _render_into(cfg: SyntheticConfig, folder: Path, progress: bool) -> None:
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    depth_camera = _depth_camera(cfg, scene)
    effects = cfg.effects if cfg.effects != SensorEffects() else None
    timed = effect_poses(cfg) if effects is not None else None
    stamps = [f"{i / cfg.fps:.6f}" for i in range(cfg.frames)]
    for i in tqdm(range(cfg.frames), desc=f"synth {cfg.mode}", unit="frame", disable=not progress):
        clean = (
            _clean_frame(scene, poses, i, depth_camera)
            if timed is None
            else _timed_frame(cfg, scene, timed, i, depth_camera)
        )
        frame = apply_kinect_noise(clean, cfg.kinect, frame_generator(cfg, i)) if cfg.noise == "kinect" else clean
        if effects is not None:
            frame = _depth_effects(cfg, clean, frame, i)
        _write_images(folder, f"{stamps[i]}.png", frame.rgb, frame.depth, cfg.depth_scale)
    for kind in ("rgb", "depth"):
        lines = [f"# {kind} images", "# timestamp filename"] + [f"{s} {kind}/{s}.png" for s in stamps]
        (folder / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    header = [f"torchtrack synthetic, mode={cfg.mode}, seed={cfg.seed}; see SOURCE.txt"]
    if poses.T_world_obj is None:
        _write_tum_trajectory(folder / "groundtruth.txt", stamps, poses.T_world_cam, header + ["T_world_cam"])
    else:
        T_cam_obj = poses.T_cam_obj
        _write_tum_trajectory(
            folder / "groundtruth.txt", stamps, T_inv(T_cam_obj), header + ["T_obj_cam (world := object)"]
        )
        _write_tum_trajectory(folder / "object_pose.txt", stamps, T_cam_obj, header + ["T_cam_obj (object-to-camera)"])
    (folder / "intrinsics.txt").write_text(
        f"# fx fy cx cy depth_scale\n{cfg.fx!r} {cfg.fy!r} {cfg.cx!r} {cfg.cy!r} {cfg.depth_scale!r}\n"
    )
    (folder / "config.json").write_text(json.dumps({"digest": cfg.digest(), **cfg.to_dict()}, indent=1, sort_keys=True))
    (folder / "SOURCE.txt").write_text(_source_text(cfg, poses.T_world_cam[0]))  # written last: marks completion


def _clean_frame(scene: Scene, poses, i: int, depth_camera) -> RGBD:
    """Frame i without effects: colour and depth at the frame's pose (depth from the depth camera where given)."""
    obj = None if poses.T_world_obj is None else poses.T_world_obj[i]
    frame = render_frame(scene, poses.T_world_cam[i], obj)
    if depth_camera is not None:  # depth seen from the depth camera at T_world_cam @ T_color_depth
        depth_scene, T_color_depth = depth_camera
        T_world_depth = (poses.T_world_cam[i].double() @ T_color_depth).to(poses.T_world_cam.dtype)
        frame = RGBD(frame.rgb, render_frame(depth_scene, T_world_depth, obj).depth)
    return frame


def _timed_frame(cfg: SyntheticConfig, scene: Scene, timed, i: int, depth_camera) -> RGBD:
    """Clean frame i with the timing effects (:class:`SensorEffects`): colour averaged over the blur poses and times
    the lighting gain, depth at the depth time offset."""
    colour_poses, depth_poses = timed
    rgb = torch.stack([_clean_frame(scene, p, i, None).rgb for p in colour_poses]).mean(0)
    rgb = (rgb * light_gain(i / cfg.fps, cfg.effects)).clamp(0, 1)
    return RGBD(rgb, _clean_frame(scene, depth_poses, i, depth_camera).depth)


def _depth_effects(cfg: SyntheticConfig, clean: RGBD, frame: RGBD, i: int) -> RGBD:
    """The measured frame with the depth effects, after the noise: flying pixels at the clean depth's edges (their
    own generator, so the noise draws are those of the sequence without them), then the misregistration shift."""
    e, depth = cfg.effects, frame.depth
    if e.flying_pixel_prob > 0:
        gen = frame_generator(cfg, i + _FLYING_INDEX_OFFSET)
        depth = flying_pixels(depth[None], clean.depth[None], e.flying_pixel_prob, cfg.kinect.edge_jump_m, gen)[0]
    if e.depth_shift_px != (0, 0):
        depth = shift_depth(depth, *e.depth_shift_px)
    return RGBD(frame.rgb, depth)


def render_sequence(
    cfg: SyntheticConfig,
    out_dir: str | Path,
    *,
    overwrite: bool = False,
    progress: bool = False,
    threads: int | None = 1,
) -> Path:
    """Render cfg's sequence into out_dir (TUM layout, see SOURCE.txt inside) and return its path.

    Renders into a temporary sibling folder and renames it into place, so out_dir is either absent or
    complete. An existing non-empty out_dir raises unless overwrite=True. ``threads``: torch intra-op
    threads while rendering (restored afterwards; None leaves torch's setting). One is the default:
    a frame's operations are small, and several threads on a shared machine run many times slower.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"render_sequence: {out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"render_sequence: {out} exists and is not empty (pass overwrite=True / --overwrite)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    saved_threads = torch.get_num_threads()
    try:
        if threads is not None:
            torch.set_num_threads(threads)
        _render_into(cfg, tmp, progress)
        if out.is_dir():
            shutil.rmtree(out) if overwrite else out.rmdir()
        os.rename(tmp, out)
    finally:
        torch.set_num_threads(saved_threads)
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    log.info("wrote %d-frame synthetic %s sequence to %s", cfg.frames, cfg.mode, out)
    return out


def default_cache_root() -> Path:
    """$TORCHTRACK_CACHE/synthetic, else ~/.cache/torchtrack/synthetic."""
    root = os.environ.get("TORCHTRACK_CACHE")
    return (Path(root) if root else Path.home() / ".cache" / "torchtrack") / "synthetic"


def sequence_name(cfg: SyntheticConfig) -> str:
    """Folder name of cfg's sequence in a cache: mode, frames, seed, noise and the config digest."""
    return f"synth-{cfg.mode}-{cfg.frames}f-seed{cfg.seed}-{cfg.noise}-{cfg.digest()}"


def display_name(cfg: SyntheticConfig) -> str:
    """A name a person can read for cfg's sequence (run folders, logs, plot titles), e.g.
    ``synthetic-scene-60frames-640x480-seed0-kinect-noise``. Not unique across every parameter: the cache
    folder (:func:`sequence_name`) carries the digest for that."""
    noise = "kinect-noise" if cfg.noise == "kinect" else "noise-free"
    return f"synthetic-{cfg.mode}-{cfg.frames}frames-{cfg.width}x{cfg.height}-seed{cfg.seed}-{noise}"


def ensure_sequence(
    cfg: SyntheticConfig, cache_root: str | Path | None = None, *, progress: bool = False, threads: int | None = 1
) -> Path:
    """Path of cfg's sequence under cache_root, rendering it first only if no complete copy exists.

    The folder name carries the config digest, so any parameter change renders a new folder. Safe
    against concurrent callers: each renders into its own temporary folder and the first rename wins.
    """
    path = Path(cache_root) if cache_root is not None else default_cache_root()
    path = path / sequence_name(cfg)
    if (path / "SOURCE.txt").is_file():
        return path
    try:
        return render_sequence(cfg, path, progress=progress, threads=threads)
    except (ValueError, OSError):
        if (path / "SOURCE.txt").is_file():  # another process finished it first
            return path
        raise
