"""Benchmark LK: one forward pass, then the combined LK + TIM tracker, torch vs OpenCV.

One pass: 300 Shi-Tomasi corners of a 640x480 intensity pair, one forward pass: the compiled operator (``cpp``,
``lk_track_flat``), the pure-torch reference (``torch``, ``lk_track_reference``), and ``cv2.calcOpticalFlowPyrLK``
(uint8 images; it builds both pyramids and the template's derivative images inside the call). The torch rows run on
prepared pyramids; "cpp + pyramid" adds ``build_pyramid`` of the next image, the per-frame cost that compares with OpenCV's
call. Target: cpp + pyramid within 1.5x OpenCV (CPU time, 1 thread).

The combined tracker runs intensity and SIM LK forward and backward (4 passes) on 300 Shi-Tomasi corners of
a 640x480 pair. OpenCV does the same four ``cv2.calcOpticalFlowPyrLK`` calls (same window, levels and
criteria, uint8 images). Both run interleaved in one process; the table gives this thread's CPU time and the
wall clock (median over the repeats) and the ratio. Two torch rows: the tracker on prepared frames, and the
steady-state cost per frame (``prepare_frame`` of the new frame + tracker), which is what compares with
OpenCV (it builds its pyramids inside each call). Then the batched throughput for B = 1, 4, 8. The speed target's
target: torch per frame within 1.5x OpenCV at B=1 (printed as met / NOT met).

    python experiments/bench/bench_lk.py                     # 1 thread, 300 features, 40 repeats
    python experiments/bench/bench_lk.py --threads 2 --repeats 100
    python experiments/bench/bench_lk.py --one-pass          # the one-pass table only

Results and the machine's load: experiments/RESULTS.md, "Speed".
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchtrack.image.flow import CombinedTracker, prepare_frame  # noqa: E402
from torchtrack.image.lk import lk_track_flat, lk_track_reference  # noqa: E402
from torchtrack.image.pyramid import build_pyramid  # noqa: E402

TARGET_RATIO = 1.5  # the speed target
DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


def load_pairs(seq: str, count: int, n_features: int):
    """count consecutive pairs (gray, sim) of a sequence, as (B, 1, H, W) tensors, and 300 corners (B, N, 2)."""
    from torchtrack.image.shape_index import compute_sim

    folder = DATA / seq
    names = [ln.split()[1] for ln in (folder / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    dnames = [ln.split()[1] for ln in (folder / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    line = [ln for ln in (folder / "intrinsics.txt").read_text().splitlines() if not ln.startswith("#")][0]
    fx, fy, cx, cy, scale = map(float, line.split())
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    grays, sims, pts = [], [], []
    for i in range(count + 1):
        g = cv2.cvtColor(cv2.imread(str(folder / names[i])), cv2.COLOR_BGR2GRAY)
        d = cv2.imread(str(folder / dnames[i]), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale
        grays.append(torch.from_numpy(g).float()[None] / 255.0)
        sims.append(compute_sim(torch.from_numpy(d)[None, None], K[None]).image[0])
        if i < count:
            c = cv2.goodFeaturesToTrack(g, n_features, 0.001, 5).reshape(-1, 2)
            pts.append(torch.from_numpy(c[:n_features]))
    n = min(len(p) for p in pts)
    gray, sim = torch.stack(grays), torch.stack(sims)
    return gray[:-1], sim[:-1], gray[1:], sim[1:], torch.stack([p[:n] for p in pts])


def opencv_four_passes(prev_u8, next_u8, pts, args):
    """Intensity and SIM, forward and backward: the combined tracker's four LK calls, per sequence."""
    for s in range(len(pts)):
        x0 = pts[s].reshape(-1, 1, 2)
        for k in range(2):
            x1, _, _ = cv2.calcOpticalFlowPyrLK(prev_u8[k][s], next_u8[k][s], x0, None, **args)
            cv2.calcOpticalFlowPyrLK(next_u8[k][s], prev_u8[k][s], x1, None, **args)


def timed(fn) -> tuple[float, float]:
    """(wall-clock ms, this thread's CPU ms) of one call: CPU time does not count time the shared machine gave
    to other processes, wall clock does."""
    w, c = time.perf_counter(), time.thread_time()
    fn()
    return (time.perf_counter() - w) * 1e3, (time.thread_time() - c) * 1e3


def bench_one_pass(data, args, levels, window, repeats) -> dict:
    """One forward LK pass of sequence 0's points on intensity: cpp, torch, cpp + next pyramid, OpenCV; medians
    (wall, cpu) in ms."""
    gray0, _, gray1, _, pts = data
    p0, p1 = build_pyramid(gray0[:1], levels, window=31), build_pyramid(gray1[:1], levels, window=31)
    x0, img = pts[0].float(), torch.zeros(pts.shape[1], dtype=torch.int64)
    u0, u1 = ((g[0, 0] * 255).round().clamp(0, 255).to(torch.uint8).numpy() for g in (gray0, gray1))
    kw = dict(window=window, levels=levels, with_residual=False)
    runs = {
        "cpp": partial(lk_track_flat, p0, p1, x0, img, x0, **kw),
        "torch": partial(lk_track_reference, p0, p1, x0, img, x0, **kw),
        "cpp + pyramid": lambda: lk_track_flat(p0, build_pyramid(gray1[:1], levels, window=31), x0, img, x0, **kw),
        "OpenCV": partial(cv2.calcOpticalFlowPyrLK, u0, u1, x0.numpy().reshape(-1, 1, 2), None, **args),
    }  # fmt: skip
    for fn in runs.values():
        fn()
    rows = {k: [] for k in runs}
    for _ in range(repeats):
        for k, fn in runs.items():
            rows[k].append(timed(fn))
    return {k: np.median(np.array(v), axis=0) for k, v in rows.items()}


def print_one_pass(data, args, a) -> None:
    med = bench_one_pass(data, args, a.levels, a.window, a.repeats)
    cv = med["OpenCV"]
    print(f"\nOne forward LK pass, {data[4].shape[1]} points, intensity, {a.threads} thread(s); median of {a.repeats} "
          "interleaved repeats, ms\n")  # fmt: skip
    print("| implementation | CPU ms | wall ms | CPU / OpenCV | CPU / cpp |")
    print("|---|---:|---:|---:|---:|")
    for k, v in med.items():
        print(f"| {k} | {v[1]:.2f} | {v[0]:.2f} | {v[1] / cv[1]:.2f} | {v[1] / med['cpp'][1]:.2f} |")
    ratio = med["cpp + pyramid"][1] / cv[1]
    print(f"\none pass: cpp + pyramid / OpenCV = {ratio:.2f}, cpp alone {med['cpp'][1] / cv[1]:.2f} (CPU time; target "
          f"<= {TARGET_RATIO}: {'met' if ratio <= TARGET_RATIO else 'NOT met'}); torch reference / cpp = "
          f"{med['torch'][1] / med['cpp'][1]:.1f}")  # fmt: skip


def bench_batch(b, tracker, data, args, levels, repeats):
    gray0, sim0, gray1, sim1, pts = data
    f0, f1 = prepare_frame(gray0[:b], sim0[:b], levels), prepare_frame(gray1[:b], sim1[:b], levels)
    p = pts[:b]

    def u8(x):
        return [(x[s, 0] * 255).round().clamp(0, 255).to(torch.uint8).numpy() for s in range(x.shape[0])]

    prev_u8, next_u8, p_np = [u8(gray0[:b]), u8(sim0[:b])], [u8(gray1[:b]), u8(sim1[:b])], p.numpy()
    runs = {
        "track": partial(tracker, f0, f1, p),
        "frame": lambda: tracker(f0, prepare_frame(gray1[:b], sim1[:b], levels), p),
        "cv": partial(opencv_four_passes, prev_u8, next_u8, p_np, args),
    }
    for fn in runs.values():
        fn()
    rows = {k: [] for k in runs}
    for _ in range(repeats):  # interleaved, so that load changes hit both sides alike
        for k, fn in runs.items():
            rows[k].append(timed(fn))
    return {k: np.array(v) for k, v in rows.items()}  # repeats x (wall, cpu)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--threads", type=int, default=1, help="torch and OpenCV threads")
    ap.add_argument("--repeats", type=int, default=40, help="timed calls per row")
    ap.add_argument("--features", type=int, default=300, help="points tracked")
    ap.add_argument("--seq", default="sun3d_fragment1", help="sequence folder in ../shared/data")
    ap.add_argument("--window", type=int, default=21, help="LK window (px)")
    ap.add_argument("--levels", type=int, default=3, help="LK pyramid levels")
    ap.add_argument("--one-pass", action="store_true", help="only the one-pass table")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    print(f"# bench_lk: {platform.processor() or platform.machine()}, torch {torch.__version__}, OpenCV "
          f"{cv2.__version__}, {a.threads} thread(s), window {a.window}, levels {a.levels}, 30 iters, eps 0.01, "
          f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")  # fmt: skip
    data = load_pairs(a.seq, 8, a.features)
    # policy min_tim: all four passes on every point, as the OpenCV side (the default fallback policy runs the SIM
    # passes only where the intensity tracker failed)
    tracker = CombinedTracker(window=a.window, levels=a.levels, policy="min_tim")
    args = dict(
        winSize=(a.window, a.window), maxLevel=a.levels - 1, minEigThreshold=1e-4,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01),
    )  # fmt: skip
    print_one_pass(data, args, a)
    if a.one_pass:
        return
    print(f"\n{a.seq}, {data[4].shape[1]} features per sequence, 640x480, combined tracker = 4 LK passes "
          f"(intensity and SIM, forward and backward). Median over {a.repeats} interleaved repeats, ms; "
          "CPU = this thread's CPU time (robust to other processes), wall = wall clock.\n")  # fmt: skip
    print("| B | torch: track (prepared frames) | torch: per frame (prepare + track) | OpenCV: 4 passes | "
          "ratio per frame / OpenCV | torch per sequence (per frame) |")  # fmt: skip
    print("|---|---|---|---|---|---|")
    for b in (1, 4, 8):
        r = bench_batch(b, tracker, data, args, a.levels, a.repeats)
        med = {k: np.median(v, axis=0) for k, v in r.items()}  # (wall, cpu)
        if b == 1:
            first = med["frame"][1] / med["cv"][1]

        cell = {k: f"CPU {v[1]:.1f} / wall {v[0]:.1f}" for k, v in med.items()}
        ratio = med["frame"] / med["cv"]
        print(f"| {b} | {cell['track']} | {cell['frame']} | {cell['cv']} | CPU {ratio[1]:.2f} / wall {ratio[0]:.2f} "
              f"| CPU {med['frame'][1] / b:.1f} / wall {med['frame'][0] / b:.1f} |")  # fmt: skip

    verdict = "met" if first <= TARGET_RATIO else "NOT met"
    print(f"\nB=1: torch per frame / OpenCV = {first:.2f} (CPU time; target <= {TARGET_RATIO}: {verdict}); load "
          f"average {os.getloadavg()[0]:.1f} at the end")  # fmt: skip


if __name__ == "__main__":
    main()
