"""Jump recovery: each shared sequence with a block of frames removed, tracked with and without the
relocalisation (``relocalise.recover``), against the full sequence.

A removed block is a jump of several centimetres and degrees between two consecutive frames (as when a recording
drops frames); without recovery the tracker re-selects its model at a wrong pose and keeps the offset. The copies
are made in a temporary folder (list files without the block; images linked, not copied). ATE is SE(3)-aligned over
each run's own written frames (the jump runs have fewer; an interrupted trajectory omits the frames after a failed
relocalisation, so read its ATE with the interrupted count).

    python experiments/eval/jump_recovery.py                                   # the default cases below
    python experiments/eval/jump_recovery.py --case sun3d_fragment1:20:30 --case visp_rbt_sequence:40:55
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.geometry import T_inv, rotation_angle
from torchtrack.run import run_tracker
from torchtrack.runtime import configure

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
CASES = ["sun3d_fragment1:20:30", "sun3d_fragment2:20:30", "visp_rbt_sequence:40:55", "visp_castle_simu:15:22"]


def without_block(src: Path, a: int, b: int, dst: Path) -> Path:
    """A copy of the TUM folder ``src`` whose list files lack associated rows a..b-1 (by line order)."""
    dst.mkdir(parents=True)
    for entry in src.iterdir():
        if entry.name not in ("rgb.txt", "depth.txt"):
            (dst / entry.name).symlink_to(entry.resolve())
    for name in ("rgb.txt", "depth.txt"):
        lines = (src / name).read_text().splitlines()
        rows = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
        gone = set(rows[a:b])
        (dst / name).write_text("\n".join(ln for i, ln in enumerate(lines) if i not in gone) + "\n")
    return dst


def run(root: Path, out: Path, *overrides: str) -> dict:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["data=tum", f"data.root={root}", *overrides])
    (m,) = run_tracker(build_tracker(cfg), build_sequences(cfg.data), out, plots=False)
    return m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    ap.add_argument("--case", action="append", help="NAME:FIRST:END, frames FIRST..END-1 removed (repeatable)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    args = ap.parse_args(argv)
    configure(args.threads)
    logging.getLogger("torchtrack").setLevel(logging.ERROR)
    print("| sequence | removed | jump (cm, deg) | ATE full (mm) | ATE jump, recovered (mm) | lost / relocalised / interrupted frames | ATE jump, not recovered (mm) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.case or CASES:
            name, a, b = case.split(":")
            a, b = int(a), int(b)
            src = DATA / name
            if not (src / "rgb.txt").is_file():
                print(f"| {name} | skipped: {src} not found |")
                continue
            seq = TumSequence(src)
            E = T_inv(torch.as_tensor(seq.groundtruth[a - 1])) @ torch.as_tensor(seq.groundtruth[b])
            jump = without_block(src, a, b, Path(tmp) / f"{name}_{a}_{b}")
            full = run(src, Path(tmp) / "out_full")
            rec = run(jump, Path(tmp) / "out_rec")
            off = run(jump, Path(tmp) / "out_off", "relocalise.recover=false")
            print(
                f"| {name} | {a}..{b - 1} | {100 * float(E[:3, 3].norm()):.1f}, "
                f"{float(rotation_angle(E[:3, :3]).rad2deg()):.1f} | {1e3 * full['ate_rmse_m']:.1f} | "
                f"{1e3 * rec['ate_rmse_m']:.1f} | {rec['lost_frames']} / {rec['relocalisations']} / {rec['interrupted_frames']} | "
                f"{1e3 * off['ate_rmse_m']:.1f} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
