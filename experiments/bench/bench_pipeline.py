"""Benchmark the whole torchtrack pipeline: fps at B=1 with a per-stage breakdown, batch scaling,
start-up.

Everything runs as the CLI runs it: the Hydra config composed in-process, the CLI's process settings
(``torchtrack.runtime.configure``: glibc allocator tuning and the thread count), the real loader
(``iterate_batched``: PNG/JPEG decoding in background threads, overlapping compute) and the CLI's loop
(``torchtrack.run.run_tracker``: per-frame recording, then trajectory.txt, metrics.json and frames.csv written
into a temporary folder; no plots). So decoding and writing are included. Reported:

- B=1: median fps of ``--repeats`` runs and the stage breakdown of one instrumented run (timing proxies wrap the
  tracker's components from the outside; nothing in the package is edited). Target: >= 30 fps.
- B=``--batch`` (default 8) lockstep in one process, with 1 and with 2 torch threads: aggregate frames/s and its
  ratio to B=1 (target >= 3x), and against the same B sequences run as two parallel B=1 processes of B/2
  sequences each (what a user would do with joblib; started together, start-up excluded; target: lockstep at
  least as fast).
- start-up: seconds from spawning ``python -m torchtrack.cli`` (the default demo: the synthetic sequence, cached
  after its first render) to the end of its first tracked frame (target <= 2 s); median of 3.
- Open3D's RGB-D odometry (the accuracy peer) on the same frames, for a ratio (``--no-peer`` skips it).
- An OpenCV KLT + Horn pipeline on the same frames (the speed reference, ``opencv_klt_horn``): decode, grey,
  forward and backward ``cv2.calcOpticalFlowPyrLK`` (the CLI's LK parameters, forward-backward error <= 1 px),
  depth at the tracked points, Horn's closed form frame to frame, Shi-Tomasi re-detection when half are lost.
  Target: the CLI's ms per frame <= 1.45x it, and >= 30 fps.
- Landmark re-acquisition (``--only reacquire``): main-thread CPU per call and per frame of
  ``LandmarkMap.reacquire`` with one batched LK call over all keyframe slots vs one call per slot (the reference),
  alternating in this process. Target: <= 2 ms per frame.
- One LK forward pass of 300 points vs OpenCV's (``--only lk``): ``bench_lk.py --one-pass``'s table.

All timings are wall clock on a shared machine: the header prints the load average; ratios come from runs
interleaved in one session.

    python experiments/bench/bench_pipeline.py                        # ../shared/data/sun3d_fragment1, 50 frames, 1 thread
    python experiments/bench/bench_pipeline.py --root ../shared/data/visp_rbt_sequence --frames 99 --repeats 5
    python experiments/bench/bench_pipeline.py --only b1 estimator=icp  # Hydra overrides pass through
"""

from __future__ import annotations

import os

os.environ.setdefault("TQDM_DISABLE", "1")  # before tqdm is imported: no progress bars inside the timed runs

import argparse
import contextlib
import functools
import json
import logging
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig
from torch.utils._python_dispatch import TorchDispatchMode

import torchtrack.frontend as frontend_module
import torchtrack.pipeline.tracker as tracker_module
import torchtrack.run as run_module
from torchtrack.config import CONF_DIR
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.runtime import configure

REPO = Path(__file__).resolve().parents[2]
CONF = CONF_DIR
DATA = REPO.parent / "shared" / "data"
DEFAULT_ROOT = DATA / "sun3d_fragment1"
TARGET_FPS, TARGET_BATCH, TARGET_STARTUP_S = 30.0, 3.0, 2.0  # fps at B=1, B=8 lockstep vs B=1, start-up seconds
TARGET_KLT_RATIO, TARGET_BATCH_25 = 1.45, 2.0  # per frame vs OpenCV KLT + Horn; B=8 lockstep vs B=1
TARGET_REACQUIRE_MS = 2.0  # landmark re-acquisition, CPU ms per frame

# (row label, indent) in print order; the keys are the timer names used below.
STAGES = {
    "data_wait": ("data: waiting for the next frame (decoded; prepared when frontend.ahead)", 0),
    "frontend": ("frontend (main thread)", 0),
    "frontend/depth": ("depth registered to colour (*)", 1),
    "frontend/sim": ("SIM (shape index, eq. 8) (*)", 1),
    "frontend/pyramids": ("LK pyramids (*)", 1),
    "flow": ("flow: LK + TIM (eq. 10)", 0),
    "measure": ("depth read at features (eq. 6)", 0),
    "weighting": ("weighting (eqs. 11-14)", 0),
    "backend": ("backend: EKF (total)", 0),
    "backend/predict": ("predict (eqs. 3-4)", 1),
    "backend/linearize": ("linearise h (eqs. 6-7)", 1),
    "landmarks": ("landmarks: re-acquisition at re-selections (its LK call counted in flow too)", 0),
    "region": ("selection: region", 0),
    "select": ("selection: features (eq. 9)", 0),
    "record": ("run loop: per-frame recording (run.py)", 0),
    "write": ("writing outputs (trajectory, metrics, csv)", 0),
}
TOP_LEVEL = [k for k, (_, indent) in STAGES.items() if indent == 0]


class StageTimer:
    """Accumulated wall time and call counts per stage name; thread-safe (the loader decodes in a thread)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self._lock = threading.Lock()
        self._local = threading.local()  # this thread's stages being run, innermost last (for OpCounter)

    @property
    def running(self) -> list[str]:
        if not hasattr(self._local, "stages"):
            self._local.stages = []
        return self._local.stages

    def add(self, name: str, seconds: float) -> None:
        with self._lock:
            self.seconds[name] += seconds
            self.calls[name] += 1

    def wrap(self, name: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            self.running.append(name)
            try:
                return fn(*args, **kwargs)
            finally:
                self.running.pop()
                self.add(name, time.perf_counter() - t0)
                if self.running:  # nested: also under its caller's name (the landmarks' flow call: counted twice)
                    self.add(f"{self.running[-1]}/{name}", time.perf_counter() - t0)

        return timed


class OpCounter(TorchDispatchMode):
    """Counts the aten operators this thread dispatches, per innermost running stage of a StageTimer (a stage's
    count includes its sub-stages'; ops outside every stage count as "other")."""

    def __init__(self, timer: StageTimer) -> None:
        super().__init__()
        self.timer, self.counts = timer, defaultdict(int)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        running = self.timer.running
        for stage in running or ["other"]:
            self.counts[stage] += 1
        return func(*args, **(kwargs or {}))


class Timed:
    """Proxy of a pipeline component: calls are timed, attributes (``reset``, ``levels``, ...) pass through."""

    def __init__(self, obj, name: str, timer: StageTimer) -> None:
        self._obj, self._call = obj, timer.wrap(name, obj)

    def __call__(self, *args, **kwargs):
        return self._call(*args, **kwargs)

    def __getattr__(self, attr: str):
        return getattr(self._obj, attr)


class TimedSequence:
    """A sequence whose frame loading (decode + conversion) is timed; the rest passes through."""

    def __init__(self, seq, timer: StageTimer) -> None:
        self._seq, self._get = seq, timer.wrap("decode", seq.__getitem__)

    def __len__(self) -> int:
        return len(self._seq)

    def __getitem__(self, i: int):
        return self._get(i)

    def __getattr__(self, attr: str):
        return getattr(self._seq, attr)


@contextlib.contextmanager
def patched(module, name: str, timer: StageTimer, stage: str) -> Iterator[None]:
    """Time ``module.name`` (a module-level function the tracker calls) for the duration of the block."""
    original = getattr(module, name, None)
    if original is None:  # renamed upstream: that row stays empty rather than failing the benchmark
        yield
        return
    setattr(module, name, timer.wrap(stage, original))
    try:
        yield
    finally:
        setattr(module, name, original)


def instrument(tracker, timer: StageTimer) -> contextlib.ExitStack:
    """Wrap the tracker's stages with timing proxies; returns the context restoring the module functions."""
    backend = tracker.backend
    ekf = getattr(backend, "ekf", None)
    if ekf is not None:  # instance attributes shadow the methods; this tracker is thrown away afterwards
        ekf.predicted = timer.wrap("backend/predict", ekf.predicted)
        ekf.linearize_at = timer.wrap("backend/linearize", ekf.linearize_at)
    backend.step = timer.wrap("backend", backend.step)
    for owner, attr in ((tracker, "frontend"), (tracker, "flow"), (tracker, "weighting"), (tracker.reselect, "region"),
                        (tracker.reselect, "select")):  # fmt: skip
        setattr(owner, attr, Timed(getattr(owner, attr), attr, timer))
    if tracker.landmarks is not None:
        tracker.landmarks.reacquire = timer.wrap("landmarks", tracker.landmarks.reacquire)
    stack = contextlib.ExitStack()
    for method, stage in (("add", "record"), ("finish", "write")):
        original = getattr(run_module.Recorder, method)
        stack.callback(setattr, run_module.Recorder, method, original)
        setattr(run_module.Recorder, method, timer.wrap(stage, original))
    ahead = run_module._prepared_ahead  # the frames the tracker gets: decoded, and prepared when frontend.ahead

    def timed_frames(*args, **kwargs):
        frames = ahead(*args, **kwargs)
        while True:
            t0 = time.perf_counter()
            frame = next(frames, None)
            timer.add("data_wait", time.perf_counter() - t0)
            if frame is None:
                return
            yield frame

    stack.callback(setattr, run_module, "_prepared_ahead", ahead)
    run_module._prepared_ahead = timed_frames
    stack.enter_context(patched(tracker_module, "measure_points", timer, "measure"))
    stack.enter_context(patched(frontend_module, "depth_in_colour", timer, "frontend/depth"))
    for name in ("compute_sim", "shape_index", "sim_image"):  # whichever the front end calls
        stack.enter_context(patched(frontend_module, name, timer, "frontend/sim"))
    stack.enter_context(patched(frontend_module, "prepare_frame", timer, "frontend/pyramids"))
    return stack


def run(cfg: DictConfig, sequences: list, *, instrumented: bool = False, count_ops: bool = False) -> dict:
    """Track ``sequences`` (B in lockstep) with a fresh tracker as the CLI does (``run_tracker``, outputs into a
    temporary folder, no plots); wall time, frames, features and stage timings (and with count_ops the aten
    operators per stage, main thread: slower, so not timed together)."""
    tracker = build_tracker(cfg)
    timer = StageTimer()
    instrumented |= count_ops
    sequences = [TimedSequence(s, timer) for s in sequences] if instrumented else sequences
    stack = instrument(tracker, timer) if instrumented else contextlib.ExitStack()
    counter = OpCounter(timer)
    if count_ops:
        stack.enter_context(counter)
    steps = 0
    step = tracker.step

    def counted(frame):
        nonlocal steps
        steps += 1
        return step(frame)

    tracker.step = counted
    with stack, tempfile.TemporaryDirectory(prefix="bench_pipeline_") as out:
        start, cpu, main_cpu = time.perf_counter(), time.process_time(), time.thread_time()
        results = run_module.run_tracker(tracker, sequences, Path(out), plots=False)
        wall, cpu, main_cpu = time.perf_counter() - start, time.process_time() - cpu, time.thread_time() - main_cpu
    frames = sum(r["frames"] for r in results)
    return {
        "B": len(sequences),
        "steps": steps,
        "frames": frames,
        "wall_s": wall,
        "fps": frames / wall,
        "cpu_ms": 1e3 * cpu / frames,  # all threads of the process (loader included), per frame: robust to load
        "main_cpu_ms": 1e3 * main_cpu / frames,  # the tracker's thread; the rest ran in the loader / front-end threads
        "step_ms": 1e3 * wall / steps,
        "mean_features": statistics.fmean(r["mean_features"] for r in results),
        "reselections": sum(r["reselections"] for r in results),
        "stages": dict(timer.seconds),
        "calls": dict(timer.calls),
        "ops": dict(counter.counts) if count_ops else None,
    }


def reacquire_costs(cfg: DictConfig, seq, repeats: int) -> dict:
    """Landmark re-acquisition (``LandmarkMap.reacquire``, the tracker's main thread) with one LK call per keyframe
    slot (``per_slot``, before) and one batched call over all slots (after), alternating in this process: the median
    over ``repeats`` runs of each of CPU ms per call and per frame (thread time: robust to the load)."""
    out: dict = {True: defaultdict(list), False: defaultdict(list)}
    for _ in range(repeats):
        for per_slot in (True, False):
            tracker = build_tracker(cfg)
            lm = tracker.landmarks
            if lm is None:
                return {}
            lm.per_slot, spent, calls, real = per_slot, [0.0], [0], lm.reacquire

            def timed(*args, _real=real, _spent=spent, _calls=calls, **kwargs):
                t0 = time.thread_time()
                try:
                    return _real(*args, **kwargs)
                finally:
                    _spent[0] += time.thread_time() - t0
                    _calls[0] += 1

            lm.reacquire = timed
            with tempfile.TemporaryDirectory(prefix="bench_pipeline_") as folder:
                frames = sum(r["frames"] for r in run_module.run_tracker(tracker, [seq], Path(folder), plots=False))
            out[per_slot]["call_ms"].append(1e3 * spent[0] / max(calls[0], 1))
            out[per_slot]["frame_ms"].append(1e3 * spent[0] / frames)
            out[per_slot]["calls"].append(calls[0])
    return {k: {m: statistics.median(v) for m, v in d.items()} for k, d in out.items()}


def reacquire_report(cfg: DictConfig, seq, repeats: int) -> None:
    costs = reacquire_costs(cfg, seq, repeats)
    if not costs:
        print("landmark re-acquisition: landmarks disabled")
        return
    old, new = costs[True], costs[False]
    print(f"landmark re-acquisition (main-thread CPU, median of {repeats} runs each, {torch.get_num_threads()} thread(s), "
          f"{new['calls']:.0f} calls in {seq.name}): one LK call per keyframe slot {old['call_ms']:.1f} ms per call, "
          f"{old['frame_ms']:.2f} ms per frame; one batched call over all slots {new['call_ms']:.1f} ms per call, "
          f"**{new['frame_ms']:.2f} ms per frame** (batched / per slot = {new['call_ms'] / old['call_ms']:.2f}; target "
          f"<= {TARGET_REACQUIRE_MS:.0f} ms per frame: {'met' if new['frame_ms'] <= TARGET_REACQUIRE_MS else 'NOT met'})")  # fmt: skip


def lk_report(threads: int, repeats: int = 40) -> None:
    """The LK row: one forward LK pass of 300 points with the next frame's pyramid vs OpenCV's
    (``bench_lk.py --one-pass``, the same table)."""
    import argparse as _argparse

    import bench_lk
    import cv2

    cv2.setNumThreads(threads)
    data = bench_lk.load_pairs("sun3d_fragment1", 1, 300)
    args = dict(winSize=(21, 21), maxLevel=2, minEigThreshold=1e-4,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01))  # fmt: skip
    bench_lk.print_one_pass(data, args, _argparse.Namespace(levels=3, window=21, repeats=repeats, threads=threads))


def median_of(repeats: int, fn) -> dict:
    """The run of median wall time among ``repeats`` runs, with the spread of their fps."""
    runs = sorted((fn() for _ in range(repeats)), key=lambda r: r["wall_s"])
    med = dict(runs[len(runs) // 2])
    med["fps_range"] = (runs[-1]["fps"], runs[0]["fps"])
    return med


def peer_fps(seq) -> float:
    return _peers().open3d_rgbd_odometry(seq, progress=False)[1]


def _peers():
    """experiments/eval/peers.py, loaded by its path: a script run as ``python experiments/bench/<script>.py`` sees
    only its own folder, and the peers belong with the evaluation that uses them most."""
    import importlib.util

    path = REPO / "experiments" / "eval" / "peers.py"
    spec = importlib.util.spec_from_file_location("peers", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def opencv_klt_horn(seq, frames: int, features: int = 300) -> dict:
    """The OpenCV KLT + Horn RGB-D odometry on frames 0..frames-1 of seq (registered depth, colour intrinsics): per
    frame decode (``seq[i]``, as the CLI's loader), grey, forward and backward LK with the CLI's parameters (window 21,
    3 levels, 30 iterations, eps 0.01, min_eig 1e-4), forward-backward error <= 1 px (the TIM threshold), depth at the
    new points, Horn between the previous and the current 3D points, chained; goodFeaturesToTrack when fewer than half
    of ``features`` remain. Wall and CPU ms per frame, decode included (serial: no loader thread)."""
    import cv2
    import numpy as np

    from torchtrack.estimators.horn import horn

    fx, fy, cx, cy = (float(seq.K[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)
    args = dict(winSize=(21, 21), maxLevel=2, criteria=crit, minEigThreshold=1e-4)

    def lift(p, depth):  # (n, 1, 2) pixels -> (n, 3) metres and valid
        u = np.clip(np.rint(p[:, 0]).astype(int), 0, depth.shape[1] - 1)
        v = np.clip(np.rint(p[:, 1]).astype(int), 0, depth.shape[0] - 1)
        z = depth[v, u]
        return np.stack([(p[:, 0] - cx) * z / fx, (p[:, 1] - cy) * z / fy, z], -1), z > 0

    n = min(frames, len(seq))
    T, prev, pts, X = np.eye(4), None, np.zeros((0, 1, 2), np.float32), np.zeros((0, 3))
    start, cpu, decode = time.perf_counter(), time.process_time(), 0.0
    for i in range(n):
        t0 = time.perf_counter()
        f = seq[i]
        decode += time.perf_counter() - t0
        gray = cv2.cvtColor((f.rgb.permute(1, 2, 0).numpy() * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        depth = f.depth[0].numpy()
        if prev is not None and len(pts):
            nxt, st, _ = cv2.calcOpticalFlowPyrLK(prev, gray, pts, None, **args)
            back, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, nxt, None, **args)
            ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((back - pts)[:, 0], axis=-1) <= 1.0)
            Xn, has = lift(nxt[:, 0], depth)
            ok &= has
            fit = horn(
                torch.from_numpy(Xn[ok])[None],
                torch.from_numpy(X[ok])[None],
                torch.ones(1, int(ok.sum()), dtype=torch.bool),
            )
            T = T @ fit.T[0].numpy()  # T_world_prev @ T_prev_cur
            pts, X = nxt[ok], Xn[ok]
        if len(pts) < features // 2:
            pts = cv2.goodFeaturesToTrack(gray, features, 0.001, 5)
            X, has = lift(pts[:, 0], depth)
            pts, X = pts[has], X[has]
        prev = gray
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    return {"frames": n, "ms": 1e3 * wall / n, "cpu_ms": 1e3 * cpu / n, "decode_ms": 1e3 * decode / n}


def compose_config(root: Path | None, frames: int, overrides: list[str]) -> DictConfig:
    if root is None:
        data = ["data=synthetic", f"data.scene.frames={frames}"]
    else:
        data = ["data=tum", f"data.root='{root}'", f"data.max_frames={frames}"]
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF), job_name="bench_pipeline"):
        return compose("config", overrides=data + overrides)


def stage_table(runs: list[dict], ops: dict | None = None) -> str:
    """ms per step of each stage for each run, with its share of the wall time; 'other' closes the sum. ``ops``: a
    run with count_ops, whose aten operators per step (main thread) make the last column."""
    head = "| stage | " + " | ".join(f"B={r['B']} ms/step | %" for r in runs) + " |"
    head += f" B={ops['B']} aten ops/step |" if ops else ""
    lines = [head, "|---|" + "---:|---:|" * len(runs) + ("---:|" if ops else "")]

    def row(label: str, key: str | None, times: list[float]) -> str:
        cells = [f"{1e3 * t / r['steps']:.1f} | {100 * t / r['wall_s']:.0f}" if t is not None else "– | –"
                 for t, r in zip(times, runs, strict=True)]  # fmt: skip
        if ops:
            n = ops["ops"].get(key) if key else None
            cells.append(f"{n / ops['steps']:.0f}" if n is not None else "–")
        return f"| {label} | {' | '.join(cells)} |"

    for key, (label, indent) in STAGES.items():
        lines.append(row("&nbsp;&nbsp;" * indent + label, key, [r["stages"].get(key) for r in runs]))
    rest = [r["wall_s"] - sum(r["stages"].get(k, 0.0) for k in TOP_LEVEL) for r in runs]
    rest = [x + r["stages"].get("landmarks/flow", 0.0) for x, r in zip(rest, runs, strict=True)]  # counted twice
    lines.append(row("other (tracker step glue: state, eq. 16, re-selection)", "other", rest))
    if ops:
        ops["ops"]["total"] = sum(ops["ops"].get(k, 0) for k in [*TOP_LEVEL, "other"])
    lines.append(row("**wall**", "total", [r["wall_s"] for r in runs]))
    lines.append(
        row("decode in the loader thread (overlaps the above)", None, [r["stages"].get("decode", 0.0) for r in runs])
    )
    lines.append(
        "\n(*) in the front end's thread, overlapping the main thread, when ``frontend.ahead`` (the default); aten "
        "operators are counted on the main thread only."
    )
    return "\n".join(lines)


def worker(args, overrides: list[str]) -> int:
    """One of the parallel B=1 processes: warm up, say ready, wait for go, track its sequences one after another."""
    configure(args.threads)
    cfg = compose_config(args.root if args.root.is_dir() else None, args.frames, overrides)
    (seq,) = build_sequences(cfg.data)
    warm = compose_config(args.root if args.root.is_dir() else None, 3, overrides)
    run(warm, build_sequences(warm.data))
    print("ready", flush=True)
    sys.stdin.readline()
    start, cpu = time.perf_counter(), time.process_time()
    frames = sum(run(cfg, [seq])["frames"] for _ in range(args.worker))
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    print(json.dumps({"frames": frames, "wall_s": wall, "cpu_s": cpu}), flush=True)
    return 0


def parallel_processes(args, overrides: list[str], processes: int, per_process: int) -> dict:
    """``processes`` B=1 processes of ``per_process`` sequences each, started together after their warm-up."""
    cmd = [sys.executable, __file__, "--worker", str(per_process), "--root", str(args.root), "--frames",
           str(args.frames), "--threads", str(args.threads), *overrides]  # fmt: skip
    procs = [subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
             for _ in range(processes)]  # fmt: skip
    for p in procs:
        if p.stdout.readline().strip() != "ready":
            raise RuntimeError("bench_pipeline: a worker failed during its warm-up")
    start = time.perf_counter()
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    out = [json.loads(p.stdout.readline()) for p in procs]
    wall = time.perf_counter() - start
    for p in procs:
        p.wait()
    frames = sum(o["frames"] for o in out)
    return {
        "frames": frames,
        "wall_s": wall,
        "fps": frames / wall,
        "cpu_ms": 1e3 * sum(o["cpu_s"] for o in out) / frames,
    }


_FIRST_FRAME = """
import os, sys, time
import torchtrack.pipeline.tracker as T
step = T.Tracker.step
def first(self, frame):
    out = step(self, frame)
    print("FIRST_FRAME", time.time(), file=sys.stderr, flush=True)
    os._exit(0)
T.Tracker.step = first
sys.argv = ["torchtrack", *sys.argv[1:]]
from torchtrack.cli import main
main()
"""


def startup_seconds(repeats: int = 3) -> tuple[float, list[float]]:
    """Seconds from spawning the default demo (``python -m torchtrack.cli``, synthetic data, no plots) to the end of
    its first tracked frame; median and all runs. The process exits there (the first frame is what is measured)."""
    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory(prefix="bench_startup_") as out:
            t0 = time.time()
            p = subprocess.run([sys.executable, "-c", _FIRST_FRAME, f"hydra.run.dir={out}", "plots=false"],
                               capture_output=True, text=True, env=dict(os.environ, TQDM_DISABLE="1"))  # fmt: skip
            line = [ln for ln in p.stderr.splitlines() if ln.startswith("FIRST_FRAME")]
            if not line:
                raise RuntimeError(f"bench_pipeline: the demo did not reach its first frame:\n{p.stderr[-2000:]}")
            times.append(float(line[0].split()[1]) - t0)
    return statistics.median(times), times


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="a 640x480 sequence (synthetic when absent)")
    ap.add_argument("--frames", type=int, default=50, help="frames per sequence")
    ap.add_argument("--batch", type=int, default=8, help="B of the lockstep run (the same sequence B times)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of the B=1 runs and of the processes")
    ap.add_argument("--repeats", type=int, default=5, help="uninstrumented runs at B=1; the median is reported")
    ap.add_argument("--only", choices=("b1", "batch", "startup", "reacquire", "lk"), help="one part only")
    ap.add_argument("--no-peer", action="store_true", help="skip Open3D's RGB-D odometry")
    ap.add_argument("--worker", type=int, default=0, help=argparse.SUPPRESS)  # internal: a parallel B=1 process
    args = ap.parse_args([a for a in argv if a not in overrides])
    logging.basicConfig(level=logging.WARNING)
    if args.worker:
        return worker(args, overrides)
    configure(args.threads)  # as the CLI: without the allocator tuning, image-sized temporaries page-fault every frame

    root = args.root if args.root.is_dir() else None
    cfg = compose_config(root, args.frames, overrides)
    (seq,) = build_sequences(cfg.data)
    H, W = seq[0].rgb.shape[-2:]
    print(f"# bench_pipeline: sequence {seq.name} ({'real' if root else 'synthetic'}), {len(seq)} frames of {W}x{H}; "
          f"overrides: {overrides or 'none'}; torch {torch.__version__}, {args.threads} thread(s), {platform.machine()}, "
          f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start")  # fmt: skip

    warm = compose_config(root, 3, overrides)
    run(warm, build_sequences(warm.data))  # first-call costs (allocator, functorch) out of the way
    plain = None
    if args.only in (None, "b1", "batch"):
        plain = median_of(args.repeats, lambda: run(cfg, [seq]))
    if args.only in (None, "b1"):
        timed1 = run(cfg, [seq], instrumented=True)
        print(f"\n{stage_table([timed1], ops=run(cfg, [seq], count_ops=True))}\n")
        lo, hi = plain["fps_range"]
        verdict = "met" if plain["fps"] >= TARGET_FPS else "NOT met"
        print(f"B=1: **{plain['fps']:.1f} fps** (median of {args.repeats} runs, range {lo:.1f}-{hi:.1f}; "
              f"{1e3 / plain['fps']:.1f} ms per frame, CPU {plain['cpu_ms']:.1f} ms per frame in all threads, "
              f"{plain['main_cpu_ms']:.1f} in the main thread; target >= "
              f"{TARGET_FPS:.0f} fps: {verdict}); "
              f"{plain['mean_features']:.0f} features, {plain['reselections']} re-selections")  # fmt: skip
        klt = min((opencv_klt_horn(seq, args.frames) for _ in range(args.repeats)), key=lambda r: r["ms"])
        ours = 1e3 / plain["fps"]
        ratio = ours / klt["ms"]
        print(f"OpenCV KLT + Horn, same frames (best of {args.repeats}, decode included, serial): {klt['ms']:.1f} ms "
              f"per frame (CPU {klt['cpu_ms']:.1f}; decoding {klt['decode_ms']:.1f} of it, overlapped by the CLI's "
              f"loader thread); CLI / OpenCV = **{ratio:.2f}** wall, "
              f"{plain['cpu_ms'] / klt['cpu_ms']:.2f} CPU (all threads) (target <= {TARGET_KLT_RATIO}: "
              f"{'met' if ratio <= TARGET_KLT_RATIO else 'NOT met'})")  # fmt: skip
        if not args.no_peer:
            peer = peer_fps(seq)
            print(f"Open3D RGB-D odometry (peer), same frames: {peer:.1f} fps; ours / peer = {plain['fps'] / peer:.2f}")
    if args.only in (None, "b1", "reacquire"):
        reacquire_report(cfg, seq, 3)
    if args.only in (None, "lk") and root is not None:
        lk_report(args.threads)
    if args.only in (None, "batch"):
        batch_report(args, overrides, cfg, seq, plain)
    if args.only in (None, "startup"):
        med, times = startup_seconds()
        verdict = "met" if med <= TARGET_STARTUP_S else "NOT met"
        print(f"\nstart-up, spawn to the end of the default demo's first frame: **{med:.2f} s** (median of "
              f"{', '.join(f'{t:.2f}' for t in times)}; target <= {TARGET_STARTUP_S:.0f} s: {verdict})")  # fmt: skip
    print(f"# load average {os.getloadavg()[0]:.1f} at the end")
    return 0


def batch_report(args, overrides: list[str], cfg: DictConfig, seq, plain: dict) -> None:
    """Lockstep B in one process (1 and 2 torch threads) vs B=1 and vs two parallel B=1 processes."""
    b = args.batch
    rows = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        rows.append((f"B={b} lockstep, 1 process, {threads} thread(s)", median_of(3, lambda: run(cfg, [seq] * b))))
    torch.set_num_threads(args.threads)
    procs = parallel_processes(args, overrides, 2, b // 2)
    rows.append((f"{b} sequences as 2 parallel B=1 processes ({b // 2} each, {args.threads} thread each)", procs))
    print(
        "\n| run | frames | wall s | frames/s (aggregate) | / B=1 | / 2 processes | CPU ms per frame (all threads) "
        "| main thread |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in [("B=1, 1 process", plain), *rows]:
        main = f"{r['main_cpu_ms']:.1f}" if "main_cpu_ms" in r else "–"
        print(f"| {name} | {r['frames']} | {r['wall_s']:.2f} | **{r['fps']:.1f}** | {r['fps'] / plain['fps']:.2f} | "
              f"{r['fps'] / procs['fps']:.2f} | {r['cpu_ms']:.1f} | {main} |")  # fmt: skip
    best = max(r["fps"] for _, r in rows[:2])
    print(f"\nlockstep B={b} (best thread count): {best / plain['fps']:.2f}x B=1 (target >= {TARGET_BATCH:.0f}x: "
          f"{'met' if best >= TARGET_BATCH * plain['fps'] else 'NOT met'}; >= {TARGET_BATCH_25:.0f}x: "
          f"{'met' if best >= TARGET_BATCH_25 * plain['fps'] else 'NOT met'}), {best / procs['fps']:.2f}x two B=1 "
          f"processes (target >= 1: {'met' if best >= procs['fps'] else 'NOT met'}); B={b} runs: median of 3")  # fmt: skip
    timed = run(cfg, [seq] * b, instrumented=True)
    ops = run(cfg, [seq] * b, count_ops=True)
    print(f"\nstages at B={b} (1 instrumented run, {torch.get_num_threads()} thread):\n\n{stage_table([timed], ops)}")


if __name__ == "__main__":
    sys.exit(main())
