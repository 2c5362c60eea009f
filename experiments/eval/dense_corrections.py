"""The dense map's corrections against the camera's motion: does the depth lag the colour?

    python experiments/eval/dense_corrections.py ../shared/data/visp_rbt_sequence

Tracks a sequence with the default configuration (or the overrides given after the frames) and prints, for every
alignment to the dense map (:meth:`torchtrack.map.dense_map.DenseMap.align`): whether it was applied, its pairs,
the camera's correction (mm, degrees), the camera's motion since the last frame (mm) and the cosine between the two
translations. The dense term measures the camera where its depth was taken, the features where its colour was: if the
depth lags the colour, the corrections point back along the motion (cosine near -1) and grow with it; if the
corrections are drift, the cosine has no preferred sign. The last line: the mean cosine and how many are below -0.5
and above 0.5.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.factory import build_tracker
from torchtrack.geometry import T_inv, rotation_angle


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("root", type=Path, help="a sequence in TUM layout")
    ap.add_argument("--frames", type=int, default=None, help="its first frames (default: all)")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the default configuration")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=args.overrides)
    tracker = build_tracker(cfg)
    if tracker.dense is None:
        raise SystemExit("dense_corrections: the configuration has no dense map (dense=none)")
    frame_no, last, cosines = 0, None, []
    align = tracker.dense.align

    def logged(depth, K, T_world_cam, mask, region=None):
        out = align(depth, K, T_world_cam, mask, region)
        if bool(mask[0]):
            before, after = T_world_cam[0].double(), out.T_world_cam[0]
            D = T_inv(before) @ after
            corr = after[:3, 3] - before[:3, 3]
            motion = before[:3, 3] - (last if last is not None else before[:3, 3])
            cos = float(corr @ motion / (corr.norm() * motion.norm()).clamp_min(1e-12))
            cosines.append(cos)
            print(f"frame {frame_no:4d}  applied {int(out.applied[0])}  pairs {int(out.pairs[0]):5d}  "
                  f"correction {float(D[:3, 3].norm()) * 1e3:6.2f} mm "
                  f"{math.degrees(float(rotation_angle(D[None, :3, :3])[0])):.3f} deg  "
                  f"motion {float(motion.norm()) * 1e3:6.2f} mm  cos {cos:+.2f}")  # fmt: skip
        return out

    tracker.dense.align = logged
    for frame in iterate_batched([TumSequence(args.root, max_frames=args.frames)], prefetch=False):
        tracker.step(frame)
        last = tracker.state.T_world_depth[0, :3, 3].double()  # the depth camera, which the map aligns
        frame_no += 1
    n = max(len(cosines), 1)
    print(f"{len(cosines)} alignments: mean cosine {sum(cosines) / n:+.2f}, below -0.5: "
          f"{sum(c < -0.5 for c in cosines)}, above 0.5: {sum(c > 0.5 for c in cosines)}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
