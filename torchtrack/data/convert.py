"""Convert RGB-D datasets into the TUM layout torchtrack reads (rgb.txt, depth.txt, groundtruth.txt, intrinsics.txt).

    python -m torchtrack.data.convert frames SRC OUT --intrinsics 585 585 320 240   # Microsoft 7-Scenes sequence
    python -m torchtrack.data.convert frames SRC OUT                                # 3DMatch / SUN3D fragments
    python -m torchtrack.data.convert sun3d SRC OUT                                 # a SUN3D sequence as published

``frames``: a folder of ``frame-XXXXXX.color.png|jpg``, ``frame-XXXXXX.depth.png`` (16-bit millimetres, 65535 or 0 =
no measurement) and ``frame-XXXXXX.pose.txt`` (4x4 camera-to-world) -- Microsoft 7-Scenes' sequences and the
3DMatch toolbox's SUN3D fragments. Intrinsics from ``--intrinsics`` or a ``camera-intrinsics.txt`` (3x3) beside the
frames or one folder up. Timestamps are frame index / fps (these datasets have none). 7-Scenes' depth is not
registered to colour: track it as given, or with ``data.depth_alignment=auto data.intrinsics_camera=depth`` (its
nominal 585 px are the depth camera's).

``sun3d``: ``image/<frame>-<microseconds>.jpg``, ``depth/<frame>-<microseconds>.png`` (millimetres stored with their
bits rotated left by 3: SUN3D's depthRead), ``intrinsics.txt`` (3x3) and ``extrinsics/*.txt`` (the last file by name:
one 3x4 camera-to-world matrix per colour image, in image order). Timestamps come from the file names.

TUM RGB-D (freiburg) sequences are in this layout already: ``data=tum data.root=DIR data.camera=fr1|fr2|fr3``.
Colour images are copied unchanged; depth is rewritten as 16-bit PNG in millimetres (depth_scale 1000).
Ground truth is written by :func:`torchtrack.data.tum_io.write_tum_trajectory` (quaternions converted there).
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from torchtrack.data.errors import DataError
from torchtrack.data.tum_io import read_list_file, write_tum_trajectory
from torchtrack.io import write_atomic, write_text

FRAME = re.compile(r"frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
SUN3D_NAME = re.compile(r"(\d+)-(\d+)\.\w+$")


def convert_frames(
    src: str | Path, out: str | Path, *, intrinsics: tuple[float, float, float, float] | None = None,
    fps: float = 30.0, invalid_depth: int = 65535,
) -> Path:  # fmt: skip
    """A ``frame-XXXXXX.*`` folder (7-Scenes, 3DMatch) -> TUM layout in ``out``; returns ``out``."""
    src, out = Path(src), Path(out)
    frames = sorted((int(m.group(1)), p) for p in src.iterdir() if (m := FRAME.match(p.name)))
    if not frames:
        raise DataError(f"{src}: no frame-XXXXXX.color.png|jpg files")
    K = intrinsics or _intrinsics_beside(src)
    t = np.array([i / fps for i, _ in frames])
    rgb, depth, poses = [], [], []
    for (_, color), ti in zip(frames, t, strict=True):
        stem = color.name[: -len(".color" + color.suffix)]
        rgb.append(_copy(color, out / "rgb" / f"{ti:.6f}{color.suffix.lower()}"))
        raw = _read_depth(src / f"{stem}.depth.png")
        depth.append(_write_depth(np.where(raw == invalid_depth, 0, raw), out / "depth" / f"{ti:.6f}.png"))
        pose = src / f"{stem}.pose.txt"
        poses.append(np.loadtxt(pose).reshape(4, 4) if pose.is_file() else None)
    return _write_layout(out, t, rgb, t, depth, poses, K, f"{src} (frame-XXXXXX files; timestamps index/{fps:g})")


def convert_sun3d(src: str | Path, out: str | Path) -> Path:
    """A SUN3D sequence folder (image/, depth/, intrinsics.txt, extrinsics/) -> TUM layout in ``out``."""
    src, out = Path(src), Path(out)
    images, depths = _sun3d_files(src / "image"), _sun3d_files(src / "depth")
    K3 = np.loadtxt(src / "intrinsics.txt").reshape(3, 3)
    ext_files = sorted((src / "extrinsics").glob("*.txt"))
    if not ext_files:
        raise DataError(f"{src / 'extrinsics'}: no extrinsics file (this sequence has no camera poses)")
    Rt = np.loadtxt(ext_files[-1]).reshape(-1, 3, 4)
    if len(Rt) != len(images):
        raise DataError(f"{ext_files[-1]}: {len(Rt)} poses for {len(images)} images")
    poses = [np.vstack([m, [0.0, 0.0, 0.0, 1.0]]) for m in Rt]
    t_rgb = np.array([us * 1e-6 for us, _ in images])
    t_depth = np.array([us * 1e-6 for us, _ in depths])
    rgb = [_copy(p, out / "rgb" / f"{t:.6f}{p.suffix.lower()}") for t, (_, p) in zip(t_rgb, images, strict=True)]
    depth = []
    for t, (_, p) in zip(t_depth, depths, strict=True):
        d = _read_depth(p)
        depth.append(_write_depth((d >> 3) | (d << 13), out / "depth" / f"{t:.6f}.png"))  # SUN3D's bit rotation
    K = (K3[0, 0], K3[1, 1], K3[0, 2], K3[1, 2])
    return _write_layout(out, t_rgb, rgb, t_depth, depth, poses, K, f"{src} (SUN3D; poses {ext_files[-1].name})")


def _sun3d_files(folder: Path) -> list[tuple[int, Path]]:
    """(timestamp in microseconds, path) of SUN3D's ``<frame>-<microseconds>.<ext>`` files, in frame order."""
    found = sorted((int(m.group(1)), int(m.group(2)), p) for p in folder.iterdir() if (m := SUN3D_NAME.match(p.name)))
    if not found:
        raise DataError(f"{folder}: no <frame>-<timestamp> files")
    return [(us, p) for _, us, p in found]


def _intrinsics_beside(src: Path) -> tuple[float, float, float, float]:
    for f in (src / "camera-intrinsics.txt", src.parent / "camera-intrinsics.txt"):
        if f.is_file():
            K = np.loadtxt(f).reshape(3, 3)
            return K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    raise DataError(f"{src}: give --intrinsics FX FY CX CY (no camera-intrinsics.txt here or one folder up)")


def _read_depth(path: Path) -> np.ndarray:
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.dtype != np.uint16 or d.ndim != 2:
        raise DataError(f"{path}: missing or not a single-channel 16-bit depth PNG")
    return d


def _write_depth(d: np.ndarray, path: Path) -> Path:
    write_atomic(path, lambda tmp: cv2.imwrite(str(tmp), d.astype(np.uint16)))
    return path


def _copy(src: Path, dst: Path) -> Path:
    write_atomic(dst, lambda tmp: shutil.copyfile(src, tmp))
    return dst


def _write_layout(out, t_rgb, rgb, t_depth, depth, poses, K, source: str) -> Path:
    def listing(what: str, ts, paths) -> str:
        return f"# {what}\n# timestamp filename\n" + "".join(
            f"{t:.6f} {p.relative_to(out).as_posix()}\n" for t, p in zip(ts, paths, strict=True)
        )

    write_text(out / "rgb.txt", listing("color images", t_rgb, rgb))
    write_text(out / "depth.txt", listing("depth maps", t_depth, depth))
    good = [i for i, T in enumerate(poses) if T is not None and np.isfinite(T).all()]  # 3DMatch marks lost poses -inf
    if good:
        write_tum_trajectory(out / "groundtruth.txt", t_rgb[good], np.stack([poses[i] for i in good]))
    write_text(out / "intrinsics.txt", "# fx fy cx cy depth_scale (depth in millimetres)\n"
               + " ".join(f"{float(v):.6f}" for v in K) + " 1000.0\n")  # fmt: skip
    write_text(out / "SOURCE.txt", f"Converted by torchtrack.data.convert from {source}.\n")
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(
        prog="python -m torchtrack.data.convert",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("kind", choices=["frames", "sun3d"], help="frames: 7-Scenes / 3DMatch frame-XXXXXX files; sun3d")
    p.add_argument("src", type=Path, help="the source sequence folder")
    p.add_argument("out", type=Path, help="the TUM-layout folder to write")
    p.add_argument("--intrinsics", type=float, nargs=4, metavar=("FX", "FY", "CX", "CY"), help="frames only")
    p.add_argument("--fps", type=float, default=30.0, help="frames only: timestamps are index / fps (30)")
    a = p.parse_args(argv)
    K = tuple(a.intrinsics) if a.intrinsics is not None else None
    try:
        if a.kind == "frames":
            out = convert_frames(a.src, a.out, intrinsics=K, fps=a.fps)
        else:
            out = convert_sun3d(a.src, a.out)
    except (DataError, OSError, ValueError) as e:
        print(f"convert: error: {e}", file=sys.stderr)
        sys.exit(2)
    print(f"{out}: {len(read_list_file(out / 'rgb.txt')[0])} frames in TUM layout")


if __name__ == "__main__":
    main()
