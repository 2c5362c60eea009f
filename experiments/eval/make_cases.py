"""Render the pixel-only bench's synthetic cases and link every case by name under $CASES (default /tmp/cases).

Boxes (the object case's small textured box, 60 frames, 640x480, seeds 0-2): exact depth, Kinect noise, and each
with its depth from a second camera 10 cm to the side (intrinsics 600/600/320/240); rendered rooms
(320x240, 60 frames, seeds 0-1), exact and Kinect; the five shared sequences, their depth_noise copies (first 300
frames) and three jittered copies of two of those. Then: bench_cases.sh REPO LABEL "$(ls $CASES)" [overrides]."""

import os
from pathlib import Path

from torchtrack.data.perturb import make_variant
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence

out = Path(os.environ.get("CASES", "/tmp/cases"))
out.mkdir(exist_ok=True)
shared = Path(os.environ.get("SHARED", "../shared/data")).resolve()
T_cd = [[1, 0, 0, -0.10], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]  # the depth camera 10 cm to the side
rig = {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "T_color_depth": T_cd}
box = dict(mode="object", object="small", background=False, trans_step_m=0.003, rot_step_deg=1.0, frames=60)
cases = {}
for seed in (0, 1, 2):
    cases[f"boxclean{seed}"] = SyntheticConfig(**box, noise="none", seed=seed)
    cases[f"boxkinect{seed}"] = SyntheticConfig(**box, noise="kinect", seed=seed)
    cases[f"boxcleanrig{seed}"] = SyntheticConfig(**box, noise="none", seed=seed, depth_camera=rig)
    cases[f"boxkinectrig{seed}"] = SyntheticConfig(**box, noise="kinect", seed=seed, depth_camera=rig)
for seed in (0, 1):
    room = dict(mode="scene", frames=60, seed=seed, width=320, height=240)
    cases[f"scenekinect{seed}"] = SyntheticConfig(**room, noise="kinect")
    cases[f"sceneclean{seed}"] = SyntheticConfig(**room, noise="none")


def link(name: str, target: Path) -> None:
    if not (out / name).exists():
        (out / name).symlink_to(target)
    print(name, target)


for name, cfg in cases.items():
    link(name, ensure_sequence(cfg, out / "_render"))
for seq in ["visp_castle_simu", "visp_rbt_sequence", "sun3d_fragment1", "sun3d_fragment2", "7scenes_redkitchen"]:
    link(seq, shared / seq)
    noisy = make_variant(shared / seq, "depth_noise", out / "_variants", seed=0, first=300)
    link(f"{seq}_depthnoise", noisy)
    if seq in ("visp_castle_simu", "sun3d_fragment1"):
        for k in (1, 2, 3):
            link(f"{seq}_depthnoise_j{k}", make_variant(noisy, "jitter", out / "_variants", seed=k))
