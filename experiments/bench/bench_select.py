"""Benchmark of the selection stage: SIM + two Harris maps + patch selection on 640x480 frames.

    python experiments/bench/bench_select.py                 # B=1 and B=8 timings, their ratio, a stage breakdown
    python experiments/bench/bench_select.py --accuracy      # also: SIM errors on analytic surfaces, Harris vs cv2
    python experiments/bench/bench_select.py --tune-malloc   # glibc malloc tuned (see tune_malloc)

Targets: B=1 <= 15 ms per frame; B=8 <= 8x the B=1 time. Frames come from ../shared/data (8 different
frames of one sequence); both batch sizes run in one process, in alternating blocks, and the median of
the repeats is reported, as wall-clock and as process CPU time. The machine is shared: the load average
is printed beside the numbers.
"""

from __future__ import annotations

import argparse
import ctypes
import math
import os
import statistics
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from torchtrack.image.corners import harris
from torchtrack.image.select import select_features
from torchtrack.image.shape_index import compute_sim, shape_index

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def load_frames(seq: str, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """gray (n,1,H,W), depth (n,1,H,W), K (n,3,3) of n frames spread over a sequence; synthetic if absent."""
    folder = DATA / seq
    if not (folder / "rgb.txt").exists():
        g = torch.Generator().manual_seed(0)
        gray = torch.rand(n, 1, 480, 640, generator=g)
        depth = 1.0 + torch.rand(n, 1, 480, 640, generator=g)
        K = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]]).expand(n, 3, 3).clone()
        return gray, depth, K
    rows = lambda name: [ln.split() for ln in (folder / name).read_text().splitlines() if ln and ln[0] != "#"]  # noqa: E731
    rgb, dep = rows("rgb.txt"), rows("depth.txt")
    fx, fy, cx, cy, scale = (float(v) for v in rows("intrinsics.txt")[0])
    idx = np.linspace(0, len(rgb) - 1, n).round().astype(int)
    gray = [cv2.cvtColor(cv2.imread(str(folder / rgb[i][1])), cv2.COLOR_BGR2GRAY).astype(np.float32) / 255 for i in idx]
    depth = [cv2.imread(str(folder / dep[i][1]), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale for i in idx]
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32).expand(n, 3, 3).clone()
    return torch.from_numpy(np.stack(gray))[:, None], torch.from_numpy(np.stack(depth))[:, None], K


def stage(gray: torch.Tensor, depth: torch.Tensor, K: torch.Tensor):
    """The per-frame selection stage of the tracker: SIM, Harris of intensity and SIM, selection."""
    sim = compute_sim(depth, K)
    return select_features(gray, depth, K, sim=sim)


def timed(fn, *args) -> tuple[float, float]:
    """(wall, process CPU) seconds of one call. CPU time is the fairer number on a shared machine."""
    w, c = time.perf_counter(), time.process_time()
    fn(*args)
    return time.perf_counter() - w, time.process_time() - c


def tune_malloc() -> None:
    """glibc: serve big tensors from the heap and never trim it, so that freed temporaries are reused
    instead of being mmap-ed, page-faulted and unmapped on every call (M_MMAP_MAX=0, M_TRIM_THRESHOLD=1 GiB)."""
    libc = ctypes.CDLL("libc.so.6")
    libc.mallopt(-4, 0)  # M_MMAP_MAX
    libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD


def benchmark(seq: str, repeats: int) -> None:
    gray, depth, K = load_frames(seq, 8)
    one = (gray[:1], depth[:1], K[:1])
    for _ in range(3):  # warm up both shapes
        stage(*one), stage(gray, depth, K)
    t1, t8 = [], []
    for block in range(4):  # B=1, B=8, B=1, B=8 blocks: load drift hits both alike, and no call runs
        for _ in range(math.ceil(repeats / 2)):  # right after the other batch size (cold caches, allocator)
            (t8 if block % 2 else t1).append(timed(stage, *((gray, depth, K) if block % 2 else one)))
    for kind, i in (("wall", 0), ("CPU", 1)):
        m1 = statistics.median(t[i] for t in t1) * 1e3
        m8 = statistics.median(t[i] for t in t8) * 1e3
        print(
            f"{kind:4s}  B=1: {m1:7.2f} ms/frame   B=8: {m8:7.2f} ms/batch = {m8 / 8:6.2f} ms/frame   "
            f"ratio B=8/B=1 = {m8 / m1:5.2f}   (medians of {repeats}; targets: B=1 <= 15 ms, ratio <= 8)"
        )

    # stage breakdown at B=1 (CPU time)
    sim = compute_sim(*one[1:])
    images = torch.cat([one[0], sim.image], 1)
    parts = {
        "SIM (shape_index + 8-bit image)": lambda: compute_sim(*one[1:]),
        "Harris, 2 maps": lambda: harris(images),
        "selection given the SIM (Harris incl.)": lambda: select_features(*one, sim=sim),
    }
    for name, fn in parts.items():
        ts = [timed(fn)[1] for _ in range(repeats)]
        print(f"  B=1 CPU {name:40s} {statistics.median(ts) * 1e3:7.2f} ms")
    f = stage(*one)
    print(f"features selected at B=1: {int(f.valid.sum())} (padded N = {f.valid.shape[1]})")


# ---------------------------------------------------------------------------------------------- accuracy
def _rays(H=480, W=640, f=525.0):
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    return (u - (W - 1) / 2) / f, (v - (H - 1) / 2) / f


def _quadric(zc, r, far, along_y):
    x, y = _rays()
    a = x * x + (0 if along_y else y * y) + 1.0
    disc = zc * zc - a * (zc * zc - r * r)
    t = (zc + (1 if far else -1) * disc.clamp_min(0).sqrt()) / a
    return torch.where(disc > 0, t, torch.zeros_like(t))


def _saddle(z0, r):
    x, y = _rays()
    a = (x * x - y * y) / (2 * r)
    z = 2 * z0 / (1 + (1 - 4 * a * z0).clamp_min(0).sqrt())
    fx, fy = x * z / r, -y * z / r
    g = 1 + fx * fx + fy * fy
    h_up = ((1 + fy * fy) - (1 + fx * fx)) / (r * 2 * g**1.5)
    k = -1 / (r * r * g**2)
    return z, 0.5 - torch.atan2(-h_up, (h_up * h_up - k).clamp_min(0).sqrt()) / math.pi


def accuracy() -> None:
    K = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])[None]
    print("SIM error on analytic depth renders (640x480, f=525, noise 0; all valid pixels; default parameters):")
    z_s, si_s = _saddle(0.8, 0.15)
    cases = {
        "sphere r=0.15 @0.8 m -> 1.00": (_quadric(0.8, 0.15, False, False), 1.0),
        "bowl (inside) r=0.15 -> 0.00": (_quadric(0.8, 0.15, True, False), 0.0),
        "cylinder r=0.10 -> 0.75": (_quadric(0.8, 0.10, False, True), 0.75),
        "pipe (inside) r=0.10 -> 0.25": (_quadric(0.8, 0.10, True, True), 0.25),
        "saddle z=(X^2-Y^2)/0.3 -> closed form (0.5 at apex)": (z_s, si_s),
    }
    for d in (1, 2):
        for name, (z, expected) in cases.items():
            s = shape_index(z.float()[None, None], K, decimate=d)
            v = s.valid[0, 0]
            err = (s.si[0, 0].double() - expected).abs()[v]
            print(
                f"  decimate={d} {name:52s} valid px {int(v.sum()):6d}  max {float(err.max()):.4f}"
                f"  p99 {float(err.quantile(0.99)):.4f}  median {float(err.median()):.4f}"
            )
    print("Harris vs cv2.cornerHarris(blockSize=3, ksize=3, k=0.04) on real frames (4 px border excluded):")
    for seq in ("visp_rbt_sequence", "sun3d_fragment1", "7scenes_redkitchen", "visp_castle_simu"):
        if not (DATA / seq / "rgb.txt").exists():
            continue
        gray = load_frames(seq, 3)[0]
        for window in ("box", "binomial", "gaussian"):
            corr, agree = [], []
            for g in gray:
                img = g[0].numpy()
                ref = cv2.cornerHarris(img, 3, 3, 0.04)[4:-4, 4:-4]
                ours = harris(g[None], window=window, block_size=3)[0, 0].numpy()[4:-4, 4:-4]
                corr.append(np.corrcoef(ours.ravel(), ref.ravel())[0, 1])
                agree.append(_maxima_agreement(ours, ref))
            print(
                f"  {seq:20s} window={window:8s} corr {np.mean(corr):.5f}  "
                f"top-300 local maxima within 1.5 px {np.mean(agree) * 100:5.1f}%"
            )


def _maxima(R, n=300, r=3):
    peak = (R == cv2.dilate(R, np.ones((2 * r + 1,) * 2, np.uint8))) & (R > 0)
    rc = np.argwhere(peak)
    return rc[np.argsort(-R[peak])[:n]].astype(float)


def _maxima_agreement(ours, ref):
    a, b = _maxima(ours), _maxima(ref)
    return float((np.sqrt(((b[:, None] - a[None]) ** 2).sum(-1)).min(1) <= 1.5).mean())


def main() -> None:
    p = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--seq", default="7scenes_redkitchen", help="sequence folder in ../shared/data")
    p.add_argument("--repeats", type=int, default=30, help="timed calls per row")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads (1: reproducible)")
    p.add_argument("--accuracy", action="store_true", help="also print SIM errors and Harris agreement")
    p.add_argument("--tune-malloc", action="store_true", help="glibc: no mmap for big tensors, no heap trimming")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    if args.tune_malloc:
        tune_malloc()
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, cpu count {os.cpu_count()}, "
        f"load average {os.getloadavg()[0]:.2f}, sequence {args.seq}, malloc tuned: {args.tune_malloc}"
    )
    benchmark(args.seq, args.repeats)
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    if args.accuracy:
        accuracy()


if __name__ == "__main__":
    main()
