"""Perturbed variants of a TUM-layout sequence: faster motion, reversed playback, photometric change, noisier depth.

``make_variant(src, kind, out_root)`` writes ``out_root/<name>-<kind>/`` (a TUM-layout folder that
:class:`~torchtrack.data.tum.TumSequence` reads like the source: rgb.txt, depth.txt, groundtruth.txt,
intrinsics.txt when present, images) and returns it. Kinds:

* ``skip2``, ``skip3``, ``skip4`` -- every k-th frame, starting at the first: faster motion. Timestamps are
  kept, so the time between frames grows k times. Images are symlinks to the source's.
* ``reversed`` -- the frames in reverse order. TUM needs increasing time, so every timestamp (colour, depth,
  ground truth) is reflected, ``t' = t_0 + (t_last - t)`` with t_0, t_last the first and last colour
  timestamps: frame i of the variant is frame n-1-i of the source, with its ground-truth pose. Images are
  symlinks.
* ``photometric`` -- per-frame brightness change: ``I' = darken * gain_t * I ** gamma_t + noise``, gain_t in
  gain_range and gamma_t in gamma_range following a smooth random walk (log-space, the per-frame step has an
  AR(1) velocity, reflected at the bounds), i.i.d. Gaussian noise of std noise_sigma (of full scale) per
  channel, clipped and rounded to 8 bits. Colour is written as PNG (lossless: the noise is exactly what was
  added); ``photometric.txt`` lists ``timestamp gain gamma`` per frame. Depth images are symlinks.
* ``depth_noise`` -- depth ``z' = z + N(0, (sigma_k z^2)^2)`` on measured pixels (Kinect-like axial noise,
  growing with z^2), then holes: i.i.d. dropout of a ``dropout`` fraction of the pixels plus ``blobs`` discs
  of radius ``blob_radius`` (fractions of the smaller image side) per frame, written in the source's depth
  scale as 16-bit PNG (values clipped to [1, 65535] where measured: noise never makes a hole, holes are 0).
  Colour images are symlinks.
* ``jitter`` -- a tiny perturbation for estimating run-to-run spread of a deterministic tracker: colour plus
  i.i.d. Gaussian noise of ``noise_sigma`` (default half a grey level: about a third of the pixels change by
  one 8-bit level), PNG; depth symlinked.

Every kind accepts ``first=N`` (use only the first N associated colour-depth pairs of the source) and
``max_dt`` (colour-depth association, as TumSequence's). Randomness is seeded: each frame draws from
``SeedSequence(seed, spawn_key=(kind, frame))``, so a variant is reproducible bit for bit and frames can be
processed in any order. The variant is cached: when ``out_root/<folder>/VARIANT.json`` holds the same stamp
(kind, seed, resolved parameters, source path and the hash of its text files, this module's version), the
folder is returned as is. It is written into a temporary sibling and renamed, so a killed run leaves no half
folder. Seed and non-default parameters are part of the folder name (``<name>-<kind>[-first<N>][-s<seed>]
[-<hash>]``), so variants with other seeds or parameters sit side by side.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import uuid
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from torchtrack.data.cameras import TUM_DEPTH_SCALE
from torchtrack.data.errors import DataError
from torchtrack.data.tum_io import associate, read_intrinsics_file, read_list_file

log = logging.getLogger(__name__)

VERSION = 1  # bump when a kind's output for the same stamp changes: cached variants are rebuilt
COMMON = {"first": None, "max_dt": 0.02}
DEFAULTS: dict[str, dict] = {
    "skip2": {},
    "skip3": {},
    "skip4": {},
    "reversed": {},
    "photometric": {
        "gain_range": (0.6, 1.4),
        "gamma_range": (0.8, 1.25),
        "walk_step": 0.01,  # std of the per-frame change of the log-gain / log-gamma velocity
        "walk_damping": 0.8,  # AR(1) coefficient of that velocity: smooth, not a jittery walk
        "darken": 0.75,  # overall factor: a darker sequence
        "noise_sigma": 0.02,  # of full scale (about 5 grey levels)
    },
    "depth_noise": {"sigma_k": 2.5e-3, "dropout": 0.05, "blobs": 3, "blob_radius": (0.02, 0.06), "depth_scale": None},
    "jitter": {"noise_sigma": 0.5 / 255.0},
}
KINDS = tuple(DEFAULTS)


@dataclass
class Frame:
    """One associated colour-depth pair of the source: timestamps and file names relative to its folder."""

    t_rgb: float
    rgb: str
    t_depth: float
    depth: str


# ----------------------------------------------------------------------------------------------- entry point


def make_variant(src: Path, kind: str, out_root: Path, seed: int = 0, **params) -> Path:
    """Write the ``kind`` variant of the TUM-layout folder ``src`` under ``out_root`` (cached); return its folder.

    See the module docstring for the kinds and their parameters. Raises ValueError for an unknown kind or
    parameter, DataError for an unreadable source.
    """
    src = Path(src).resolve()
    if kind not in DEFAULTS:
        raise ValueError(f"make_variant: unknown kind {kind!r}; choose from {', '.join(KINDS)}")
    allowed = {**COMMON, **DEFAULTS[kind]}
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise ValueError(f"make_variant({kind}): unknown parameter(s) {unknown}; allowed: {sorted(allowed)}")
    resolved = json.loads(json.dumps({**allowed, **params}))  # tuples -> lists, as in the stamp file
    stamp = {"version": VERSION, "kind": kind, "seed": int(seed), "params": resolved, **_source_identity(src)}
    dest = Path(out_root) / _folder_name(src.name, kind, int(seed), params)
    if _stamp(dest) == stamp:
        return dest
    frames = _source_frames(src, resolved["first"], resolved["max_dt"])
    tmp = dest.parent / f".{dest.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir(parents=True)
        _WRITERS[kind](src, tmp, frames, _rng_factory(int(seed), kind), resolved)
        _copy_metadata(src, tmp, kind, stamp, reverse=kind == "reversed", frames=frames)
        _put_in_place(tmp, dest, stamp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    log.info("wrote %s variant of %s (%d frames) to %s", kind, src.name, len(frames), dest)
    return dest


def _folder_name(name: str, kind: str, seed: int, params: dict) -> str:
    parts = [name, kind]
    if params.get("first") is not None:
        parts.append(f"first{params['first']}")
    if seed:
        parts.append(f"s{seed}")
    other = {k: v for k, v in params.items() if k != "first"}
    if other:
        parts.append(hashlib.sha256(json.dumps(other, sort_keys=True).encode()).hexdigest()[:8])
    return "-".join(parts)


def _source_identity(src: Path) -> dict:
    """What a cached variant depends on besides its parameters: the source's path and text files."""
    h = hashlib.sha256()
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt"):
        f = src / name
        h.update(name.encode() + (f.read_bytes() if f.is_file() else b"<absent>"))
    return {"source": str(src), "source_sha": h.hexdigest()[:16]}


def _stamp(folder: Path) -> dict | None:
    try:
        return json.loads((folder / "VARIANT.json").read_text())
    except (OSError, ValueError):
        return None


def _put_in_place(tmp: Path, dest: Path, stamp: dict) -> None:
    """Rename the finished tmp folder to dest; a stale dest (other stamp) is moved aside first and removed."""
    old = None
    if dest.exists():
        old = dest.parent / f".{dest.name}.old-{uuid.uuid4().hex[:8]}"
        os.rename(dest, old)
    try:
        os.rename(tmp, dest)
    except OSError:
        if _stamp(dest) != stamp:  # not a concurrent writer that finished the same variant first
            raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _source_frames(src: Path, first: int | None, max_dt: float) -> list[Frame]:
    """The source's associated colour-depth pairs (as TumSequence associates them), the first ``first``."""
    t_rgb, f_rgb = read_list_file(src / "rgb.txt")
    t_d, f_d = read_list_file(src / "depth.txt")
    ia, ib = associate(t_rgb, t_d, max_dt)
    if len(ia) == 0:
        raise DataError(f"{src}: no colour-depth pair within max_dt={max_dt} s")
    frames = [Frame(float(t_rgb[i]), f_rgb[i], float(t_d[j]), f_d[j]) for i, j in zip(ia, ib, strict=True)]
    return frames[:first] if first is not None else frames


def _rng_factory(seed: int, kind: str) -> Callable[[int], np.random.Generator]:
    """Generator of frame i (i = -1: per-sequence draws); depends on (seed, kind, i) only."""
    key = zlib.crc32(kind.encode())
    return lambda i: np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(key, i + 1)))


# ----------------------------------------------------------------------------------------------- files


def _write_list(path: Path, kind: str, what: str, rows: list[tuple[float, str]]) -> None:
    lines = [f"# {what} images ({kind} variant, torchtrack.data.perturb)", "# timestamp filename"]
    path.write_text("\n".join(lines + [f"{t:.6f} {name}" for t, name in rows]) + "\n")


def _link(src: Path, dest: Path, names: list[str]) -> None:
    """Symlink each listed image (relative name kept) to the source's file."""
    for name in names:
        target = dest / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if not os.path.lexists(target):
            os.symlink(src / name, target)


def _copy_metadata(src: Path, dest: Path, kind: str, stamp: dict, *, reverse: bool, frames: list[Frame]) -> None:
    """intrinsics.txt as is; groundtruth.txt as is or re-timed; SOURCE.txt; VARIANT.json (the stamp) last."""
    if (src / "intrinsics.txt").is_file():
        shutil.copyfile(src / "intrinsics.txt", dest / "intrinsics.txt")
    gt = src / "groundtruth.txt"
    if gt.is_file():
        text = gt.read_text()
        if reverse:
            text = _reverse_groundtruth(text, frames[0].t_rgb, frames[-1].t_rgb)
        (dest / "groundtruth.txt").write_text(text)
    source = (src / "SOURCE.txt").read_text() if (src / "SOURCE.txt").is_file() else "(no SOURCE.txt)\n"
    intro = f"'{kind}' variant of {src} written by torchtrack.data.perturb (version {VERSION})."
    doc = f"{intro}\nSeed {stamp['seed']}, parameters {json.dumps(stamp['params'])}.\n"
    (dest / "SOURCE.txt").write_text(
        f"{doc}See the module's docstring for what the kind does.\n\n--- source ---\n{source}"
    )
    (dest / "VARIANT.json").write_text(json.dumps(stamp, indent=1, sort_keys=True) + "\n")


def _reverse_groundtruth(text: str, t0: float, t_last: float) -> str:
    """Re-time every pose row t -> t0 + (t_last - t) and reverse the rows (poses kept verbatim)."""
    header, rows = [], []
    for line in text.splitlines():
        fields = line.replace(",", " ").split()
        if not fields or line.lstrip().startswith("#"):
            header.append(line)
        else:
            rows.append(f"{t0 + (t_last - float(fields[0])):.6f} " + " ".join(fields[1:]))
    note = f"# reversed variant: timestamps t' = {t0:.6f} + ({t_last:.6f} - t), rows in reverse order"
    return "\n".join(header + [note] + rows[::-1]) + "\n"


def _parallel(fn: Callable[[int], None], n: int) -> None:
    """fn(i) for i in range(n) on a few threads (image codecs release the GIL)."""
    with ThreadPoolExecutor(max_workers=max(1, min(4, os.cpu_count() or 1))) as pool:
        list(pool.map(fn, range(n)))


def _read(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DataError(f"{path}: missing, unreadable or corrupt image")
    return img


def _write(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img):
        raise OSError(f"make_variant: could not write {path}")


def _png_name(name: str) -> str:
    return str(Path(name).with_suffix(".png"))


# ----------------------------------------------------------------------------------------------- kinds


def _skip(k: int):
    def write(src: Path, dest: Path, frames: list[Frame], rng, p: dict) -> None:
        kept = frames[::k]
        _link(src, dest, [f.rgb for f in kept] + [f.depth for f in kept])
        _write_list(dest / "rgb.txt", f"skip{k}", "colour", [(f.t_rgb, f.rgb) for f in kept])
        _write_list(dest / "depth.txt", f"skip{k}", "depth", [(f.t_depth, f.depth) for f in kept])

    return write


def _reversed(src: Path, dest: Path, frames: list[Frame], rng, p: dict) -> None:
    t0, t_last = frames[0].t_rgb, frames[-1].t_rgb
    back = frames[::-1]
    _link(src, dest, [f.rgb for f in back] + [f.depth for f in back])
    _write_list(dest / "rgb.txt", "reversed", "colour", [(t0 + (t_last - f.t_rgb), f.rgb) for f in back])
    _write_list(dest / "depth.txt", "reversed", "depth", [(t0 + (t_last - f.t_depth), f.depth) for f in back])


def _to_unit(img: np.ndarray) -> np.ndarray:
    return img.astype(np.float64) / (255.0 if img.dtype == np.uint8 else 65535.0)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.round(x * 255.0), 0, 255).astype(np.uint8)


def smooth_walk(rng: np.random.Generator, n: int, lo: float, hi: float, step: float, damping: float) -> np.ndarray:
    """(n,) values in [lo, hi] (lo < 1 < hi) starting at 1: a log-space walk whose velocity is AR(1)
    (``v_t = damping v_{t-1} + N(0, step)``), reflected at log(lo) and log(hi)."""
    if not 0 < lo <= 1 <= hi:
        raise ValueError(f"smooth_walk: need 0 < lo <= 1 <= hi, got ({lo}, {hi})")
    a, b = math.log(lo), math.log(hi)
    if a == b:
        return np.ones(n)
    x, v, out = 0.0, 0.0, np.empty(n)
    for t, e in enumerate(rng.normal(0.0, step, n)):
        v = damping * v + (e if t else 0.0)
        x += v
        while not a <= x <= b:  # reflect position and velocity at the bounds
            x, v = (2 * a - x, -v) if x < a else (2 * b - x, -v)
        out[t] = math.exp(x)
    return out


def _photometric(src: Path, dest: Path, frames: list[Frame], rng, p: dict) -> None:
    walk = rng(-1)
    gain = smooth_walk(walk, len(frames), *p["gain_range"], p["walk_step"], p["walk_damping"])
    gamma = smooth_walk(walk, len(frames), *p["gamma_range"], p["walk_step"], p["walk_damping"])

    def one(i: int) -> None:
        img = _to_unit(_read(src / frames[i].rgb))
        out = p["darken"] * gain[i] * img ** gamma[i] + rng(i).normal(0.0, p["noise_sigma"], img.shape)
        _write(dest / _png_name(frames[i].rgb), _to_u8(out))

    _parallel(one, len(frames))
    _colour_lists(src, dest, frames, "photometric")
    rows = [f"{f.t_rgb:.6f} {g:.6f} {y:.6f}" for f, g, y in zip(frames, gain, gamma, strict=True)]
    lines = ["# per-frame photometric change: I' = darken * gain * I^gamma + noise", "# timestamp gain gamma"]
    (dest / "photometric.txt").write_text("\n".join(lines + rows) + "\n")


def _jitter(src: Path, dest: Path, frames: list[Frame], rng, p: dict) -> None:
    def one(i: int) -> None:
        img = _to_unit(_read(src / frames[i].rgb))
        _write(dest / _png_name(frames[i].rgb), _to_u8(img + rng(i).normal(0.0, p["noise_sigma"], img.shape)))

    _parallel(one, len(frames))
    _colour_lists(src, dest, frames, "jitter")


def _colour_lists(src: Path, dest: Path, frames: list[Frame], kind: str) -> None:
    """Lists of a kind that rewrote colour as PNG and keeps the source's depth (symlinked)."""
    _link(src, dest, [f.depth for f in frames])
    _write_list(dest / "rgb.txt", kind, "colour", [(f.t_rgb, _png_name(f.rgb)) for f in frames])
    _write_list(dest / "depth.txt", kind, "depth", [(f.t_depth, f.depth) for f in frames])


def _depth_scale(src: Path, given: float | None) -> float:
    if given is not None:
        return float(given)
    if (src / "intrinsics.txt").is_file():
        scale = read_intrinsics_file(src / "intrinsics.txt")[1]
        if scale is not None:
            return scale
    log.warning("%s: no depth_scale in intrinsics.txt; using TUM's %g", src, TUM_DEPTH_SCALE)
    return TUM_DEPTH_SCALE


def blob_mask(rng: np.random.Generator, shape: tuple[int, int], n: int, radius: tuple[float, float]) -> np.ndarray:
    """(H, W) bool: n discs, centres uniform in the image, radii uniform in radius x min(H, W) pixels."""
    H, W = shape
    yy, xx = np.mgrid[0:H, 0:W]
    mask = np.zeros(shape, bool)
    for _ in range(n):
        cx, cy, r = rng.uniform(0, W), rng.uniform(0, H), rng.uniform(*radius) * min(H, W)
        mask |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
    return mask


def depth_noise(d: np.ndarray, scale: float, rng: np.random.Generator, p: dict) -> np.ndarray:
    """16-bit depth d (H, W) in units of 1/scale m -> noisier depth with holes (see the module docstring)."""
    valid = d > 0
    z = d.astype(np.float64) / scale
    noisy = np.round((z + rng.normal(0.0, 1.0, d.shape) * p["sigma_k"] * z * z) * scale)
    out = np.where(valid, np.clip(noisy, 1, 65535), 0).astype(np.uint16)
    holes = rng.random(d.shape) < p["dropout"]
    holes |= blob_mask(rng, d.shape, int(p["blobs"]), tuple(p["blob_radius"]))
    out[holes] = 0
    return out


def _depth_noise(src: Path, dest: Path, frames: list[Frame], rng, p: dict) -> None:
    scale = _depth_scale(src, p["depth_scale"])

    def one(i: int) -> None:
        d = _read(src / frames[i].depth)
        if d.dtype != np.uint16 or d.ndim != 2:
            raise DataError(f"{src / frames[i].depth}: depth must be single-channel 16-bit")
        _write(dest / _png_name(frames[i].depth), depth_noise(d, scale, rng(i), p))

    _parallel(one, len(frames))
    _link(src, dest, [f.rgb for f in frames])
    _write_list(dest / "rgb.txt", "depth_noise", "colour", [(f.t_rgb, f.rgb) for f in frames])
    _write_list(dest / "depth.txt", "depth_noise", "depth", [(f.t_depth, _png_name(f.depth)) for f in frames])


_WRITERS = {
    "skip2": _skip(2),
    "skip3": _skip(3),
    "skip4": _skip(4),
    "reversed": _reversed,
    "photometric": _photometric,
    "depth_noise": _depth_noise,
    "jitter": _jitter,
}
