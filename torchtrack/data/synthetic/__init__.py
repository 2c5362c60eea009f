"""Synthetic RGB-D sequences with exact ground truth: the embedded default sequence and every stage's test bed.

A torch ray-caster renders a textured scene (planes, boxes, spheres, cylinders with procedural
textures attached to their surfaces) under smooth random camera motion (``mode="scene"``) or object
motion (``mode="object"``), optionally through a Kinect-like noise model, into a TUM-layout folder.

    cfg = SyntheticConfig(frames=30, seed=0, mode="scene", noise="kinect")
    folder = ensure_sequence(cfg)                 # cached by config digest, rendered once
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    rgb, depth = render_frame(scene, poses.T_world_cam[0])   # (3, H, W), (1, H, W) metres, exact

Command line: ``torchtrack-synth --out DIR --frames 30 --seed 0 --mode scene --noise kinect``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from torchtrack.data.synthetic.config import KinectNoise, SyntheticConfig
from torchtrack.data.synthetic.motion import SequencePoses, look_at, sequence_poses
from torchtrack.data.synthetic.noise import apply_kinect_noise, depth_sigma, edge_holes, quantise_disparity
from torchtrack.data.synthetic.render import RGBD, RayHits, raycast, render_frame, render_pixels
from torchtrack.data.synthetic.scene import Primitive, Scene, TextureParams, default_scene, make_scene, random_texture
from torchtrack.data.synthetic.writer import (
    default_cache_root,
    display_name,
    ensure_sequence,
    frame_generator,
    render_sequence,
    sequence_name,
)

__all__ = [
    "RGBD", "KinectNoise", "Primitive", "RayHits", "Scene", "SequencePoses", "SyntheticConfig", "TextureParams",
    "apply_kinect_noise", "default_cache_root", "default_scene", "depth_sigma", "display_name", "edge_holes", "ensure_sequence",
    "frame_generator", "look_at", "main", "make_scene", "quantise_disparity", "random_texture", "raycast", "render_frame", "render_pixels",
    "render_sequence", "sequence_name", "sequence_poses",
]  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Console script ``torchtrack-synth``: render a synthetic TUM-layout sequence, print its folder."""
    p = argparse.ArgumentParser(prog="torchtrack-synth", description=__doc__.splitlines()[0])
    p.add_argument("--out", help="output folder (default: the cache, $TORCHTRACK_CACHE or ~/.cache/torchtrack)")
    p.add_argument("--frames", type=int, default=SyntheticConfig.frames)
    p.add_argument("--seed", type=int, default=SyntheticConfig.seed)
    p.add_argument("--mode", choices=["scene", "object"], default=SyntheticConfig.mode)
    p.add_argument("--noise", choices=["kinect", "none"], default=SyntheticConfig.noise)
    p.add_argument("--width", type=int, default=SyntheticConfig.width)
    p.add_argument("--height", type=int, default=SyntheticConfig.height)
    p.add_argument("--trans-step", type=float, default=SyntheticConfig.trans_step_m, help="RMS metres per frame")
    p.add_argument("--rot-step-deg", type=float, default=SyntheticConfig.rot_step_deg, help="RMS degrees per frame")
    p.add_argument("--no-background", action="store_true", help="object mode: no room behind the object")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out folder")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        cfg = SyntheticConfig(
            width=args.width, height=args.height, frames=args.frames, seed=args.seed, mode=args.mode,
            noise=args.noise, background=not args.no_background, trans_step_m=args.trans_step,
            rot_step_deg=args.rot_step_deg,
        )  # fmt: skip
        if args.out is None:
            out = ensure_sequence(cfg, progress=True)
        else:
            out = render_sequence(cfg, args.out, overwrite=args.overwrite, progress=True)
    except (ValueError, OSError) as e:
        print(f"torchtrack-synth: error: {e}", file=sys.stderr)
        return 2
    print(out)
    return 0
