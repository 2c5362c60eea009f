import sys
from pathlib import Path
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
T_cd = [[1, 0, 0, -0.10], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
rig = {"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0, "T_color_depth": T_cd}
box = dict(mode="object", object="small", background=False, trans_step_m=0.003, rot_step_deg=1.0, frames=60)
out = Path('/tmp/rigcases')
for seed in map(int, sys.argv[1:]):
    for name, cfg in [(f"boxclean{seed}", SyntheticConfig(**box, noise="none", seed=seed)),
                      (f"boxcleanrig{seed}", SyntheticConfig(**box, noise="none", seed=seed, depth_camera=rig))]:
        p = ensure_sequence(cfg, out / "_render")
        if not (out / name).exists(): (out / name).symlink_to(p)
        print(name, p, flush=True)
