"""Benchmark the pose estimators : Horn, ICP, CPD on 300 correspondences, batched B=8.

Runs ours (batched over B) next to Open3D's point-to-point ``registration_icp`` and pycpd's
``RigidRegistration`` (both looped over B) in one process on the same inputs, and prints ms per frame
(= per sequence per frame: batch time / B) and ratios. A second table measures accuracy under noise
and outliers (mean rotation error in degrees, translation error in mm, over the B sequences).

    python experiments/bench/bench_estimators.py            # B=8, N=300, float64 and float32, 1 thread
    python experiments/bench/bench_estimators.py --threads 2 --repeats 50 > bench.md
"""

from __future__ import annotations

import os

# One thread for every library (Open3D's OpenMP, numpy's BLAS, torch), set before they load: idle OpenMP/BLAS
# workers spin after each call and would steal the CPU from whichever method runs next in the round.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from torchtrack.estimators.cpd import cpd_rigid  # noqa: E402
from torchtrack.estimators.horn import horn  # noqa: E402
from torchtrack.estimators.icp import icp  # noqa: E402
from torchtrack.geometry import make_T, rotation_angle, so3_exp, transform_points  # noqa: E402


def make_problem(B, N, noise, outlier_frac, seed, dtype=torch.float64):
    """Object points (~10 cm at 1 m), an inter-frame motion (<= 6 deg, 2 cm), measured points with noise (m)
    and a fraction of features replaced by gross outliers (mis-tracked: displaced 5-20 cm)."""
    g = torch.Generator().manual_seed(seed)
    src = torch.randn(B, N, 3, generator=g, dtype=torch.float64) * 0.1 + torch.tensor(
        [0.0, 0.0, 1.0], dtype=torch.float64
    )
    axis = torch.randn(B, 3, generator=g, dtype=torch.float64)
    omega = (
        axis / axis.norm(dim=-1, keepdim=True) * math.radians(6) * torch.rand(B, 1, generator=g, dtype=torch.float64)
    )
    T = make_T(so3_exp(omega), (torch.rand(B, 3, generator=g, dtype=torch.float64) * 2 - 1) * 0.02)
    dst = transform_points(T, src) + noise * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    n_out = int(round(outlier_frac * N))
    if n_out:
        d = torch.randn(B, n_out, 3, generator=g, dtype=torch.float64)
        r = 0.05 + 0.15 * torch.rand(B, n_out, 1, generator=g, dtype=torch.float64)
        dst[:, :n_out] += d / d.norm(dim=-1, keepdim=True) * r
    return src.to(dtype), dst.to(dtype), T.to(dtype)


def open3d_icp(src, dst, T_init, max_corr_dist, max_iters, tol):
    import open3d as o3d

    reg = o3d.pipelines.registration
    crit = reg.ICPConvergenceCriteria(relative_fitness=tol, relative_rmse=tol, max_iteration=max_iters)
    out = []
    for b in range(src.shape[0]):
        s = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src[b]))
        d = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dst[b]))
        res = reg.registration_icp(s, d, max_corr_dist, T_init[b], reg.TransformationEstimationPointToPoint(), crit)
        out.append(np.asarray(res.transformation))
    return np.stack(out)


def pycpd_rigid(src, dst, max_iters, tol, w):
    """pycpd moves Y (source) onto X (target) with row vectors: TY = s Y @ R + t, so R_ours = R.T."""
    from pycpd import RigidRegistration

    out = []
    for b in range(src.shape[0]):
        reg = RigidRegistration(X=dst[b], Y=src[b], max_iterations=max_iters, tolerance=tol, w=w)
        _, (s, R, t) = reg.register()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = s * R.T, t
        out.append(T)
    return np.stack(out)


def errors(T_est, T_true):
    T_est = torch.as_tensor(T_est, dtype=torch.float64)
    T_true = T_true.to(torch.float64)
    rot = rotation_angle(T_est[:, :3, :3].transpose(-1, -2) @ T_true[:, :3, :3])
    trans = (T_est[:, :3, 3] - T_true[:, :3, 3]).norm(dim=-1)
    return math.degrees(rot.mean().item()), 1e3 * trans.mean().item()


def timed_round_robin(fns, repeats):
    """name -> (min, median) seconds; the methods take turns within each round so that load drifts hit all alike.
    The min is the least disturbed run (the figure ratios use on a shared machine); the median shows the spread."""
    for fn in fns.values():
        fn()  # warm-up
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: (float(np.min(ts)), float(np.median(ts))) for name, ts in times.items()}


def ours(src, dst, valid, T_init, d_max, args, tag):
    """name -> callable returning T (B, 4, 4): our three methods with their default stopping rules, then the
    iterative ones for a fixed number of iterations (no stopping test)."""
    ki, kc = args.fixed_icp, args.fixed_cpd
    return {
        f"horn (ours{tag})": lambda: horn(src, dst, valid).T,
        f"icp (ours{tag})": lambda: icp(src, dst, valid, valid, T_init, max_iters=50, tol=1e-6, max_corr_dist=d_max).T,
        f"cpd (ours{tag}, scale)": lambda: cpd_rigid(src, dst, valid, valid, T_init, w=args.w, tol=1e-5, scale=True).T,
        f"cpd (ours{tag}, rigid)": lambda: cpd_rigid(src, dst, valid, valid, T_init, w=args.w, tol=1e-5).T,
        f"icp (ours{tag}) {ki} it": lambda: (
            icp(src, dst, valid, valid, T_init, max_iters=ki, tol=0, max_corr_dist=d_max).T
        ),
        f"cpd (ours{tag}, scale) {kc} it": lambda: (
            cpd_rigid(src, dst, valid, valid, T_init, w=args.w, max_iters=kc, tol=0, scale=True).T
        ),
    }


def references(src, dst, T_init, d_max, args):
    """The same for Open3D's ICP and pycpd (float64, looped over B)."""
    s_np, d_np, T_np = src.numpy(), dst.numpy(), T_init.numpy()
    ki, kc = args.fixed_icp, args.fixed_cpd
    return {
        "icp open3d": lambda: open3d_icp(s_np, d_np, T_np, d_max, 50, 1e-6),
        "cpd pycpd": lambda: pycpd_rigid(s_np, d_np, 100, args.pycpd_tol, args.w),
        f"icp open3d {ki} it": lambda: open3d_icp(s_np, d_np, T_np, d_max, ki, 0.0),
        f"cpd pycpd {kc} it": lambda: pycpd_rigid(s_np, d_np, kc, 0.0, args.w),
    }


def mean_iterations(src, dst, valid, T_init, d_max, args, tag):
    """Mean iterations to convergence of ours (the references do not report theirs)."""
    return {
        f"icp (ours{tag})": icp(src, dst, valid, valid, T_init, max_iters=50, tol=1e-6, max_corr_dist=d_max).iterations,
        f"cpd (ours{tag}, scale)": cpd_rigid(src, dst, valid, valid, T_init, w=args.w, scale=True).iterations,
        f"cpd (ours{tag}, rigid)": cpd_rigid(src, dst, valid, valid, T_init, w=args.w).iterations,
    }


def bench_speed(args):
    """One table: ours in float64 and float32 and the references, all interleaved in the same rounds."""
    print(f"## Speed: B={args.B}, N={args.N} correspondences, 1 mm noise, init = identity (previous pose)\n")
    omp = ", ".join(f"{v}={os.environ[v]}" for v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"))
    print(f"torch {torch.__version__}, torch.set_num_threads({args.threads}), {omp}, {platform.machine()}, "
          f"{os.cpu_count()} cores; {args.repeats} rounds, all methods interleaved within each round")  # fmt: skip
    print("ICP: max_iters 50, tol 1e-6 (relative change of the mse), max_corr_dist 0.1 m; Open3D: max_iteration 50,")
    print("     relative_fitness = relative_rmse = 1e-6 (absolute changes in Open3D's code)")
    print(f"CPD: w={args.w}, max_iters 100, tol 1e-5 nats/point; pycpd: max_iterations 100, tolerance {args.pycpd_tol}")
    print("'k it' rows: exactly k iterations on both sides (no stopping test). References: float64, looped over B.")
    print("ms/frame = batch time / B: min over the rounds (median in brackets); ratios use the min.\n")
    src, dst, T = make_problem(args.B, args.N, 0.001, 0.0, seed=0)
    valid = torch.ones(args.B, args.N, dtype=torch.bool)
    T_init = torch.eye(4, dtype=torch.float64).expand(args.B, 4, 4).clone()
    fns, iters = {}, {}
    for dtype, tag in ((torch.float64, ""), (torch.float32, " f32")):
        x, y, T0 = src.to(dtype), dst.to(dtype), T_init.to(dtype)
        fns |= ours(x, y, valid, T0, 0.1, args, tag)
        iters |= mean_iterations(x, y, valid, T0, 0.1, args, tag)
    fns |= references(src, dst, T_init, 0.1, args)
    secs = timed_round_robin(fns, args.repeats)
    print("| method | ms/frame min (median) | mean iterations | rot err (deg) | trans err (mm) |")
    print("|---|---:|---:|---:|---:|")
    ms = {}
    for name, fn in fns.items():
        ms[name] = 1e3 * secs[name][0] / args.B
        er, et = errors(fn(), T)
        it = f"{iters[name].double().mean():.1f}" if name in iters else name.split()[-2] if name.endswith(" it") else ""
        print(f"| {name} | {ms[name]:.3f} ({1e3 * secs[name][1] / args.B:.3f}) | {it} | {er:.4f} | {et:.3f} |")
    ki, kc = args.fixed_icp, args.fixed_cpd
    print("\nratios, reference ms / ours ms (> 1: ours faster):\n")
    print("| reference | ours | ratio (ours float64) | ratio (ours float32) |\n|---|---|---:|---:|")
    for ref, o in [
        ("icp open3d", "icp (ours{})"),
        ("cpd pycpd", "cpd (ours{}, scale)"),
        ("cpd pycpd", "cpd (ours{}, rigid)"),
        (f"icp open3d {ki} it", f"icp (ours{{}}) {ki} it"),
        (f"cpd pycpd {kc} it", f"cpd (ours{{}}, scale) {kc} it"),
    ]:
        print(f"| {ref} | {o.format('')} | {ms[ref] / ms[o.format('')]:.2f} | {ms[ref] / ms[o.format(' f32')]:.2f} |")
    print()


def bench_accuracy(args):
    print(f"## Accuracy (float64): B={args.B}, N={args.N}, 6 deg / 2 cm motions from identity, mean over B\n")
    print("Rotation error, and translation error of T_cam_obj (object ~1 m away). Outliers: that fraction of the")
    print("measured points displaced 5-20 cm. CPD w = outlier weight; ours rigid, pycpd always estimates a scale.\n")
    print("| noise (mm) | outliers | horn | icp (d_max 0.1) | icp open3d | cpd w=0 | cpd w=0.2 | pycpd w=0.2 |")
    print("|---:|---:|---|---|---|---|---|---|")
    for noise, frac in [(0.0, 0.0), (1.0, 0.0), (5.0, 0.0), (1.0, 0.1), (1.0, 0.3)]:
        src, dst, T = make_problem(args.B, args.N, noise * 1e-3, frac, seed=1)
        valid = torch.ones(args.B, args.N, dtype=torch.bool)
        T_init = torch.eye(4, dtype=torch.float64).expand(args.B, 4, 4).clone()
        s_np, d_np = src.numpy(), dst.numpy()
        Ts = [
            horn(src, dst, valid).T,
            icp(src, dst, valid, valid, T_init, max_corr_dist=0.1).T,
            open3d_icp(s_np, d_np, T_init.numpy(), 0.1, 50, 1e-6),
            cpd_rigid(src, dst, valid, valid, T_init, w=0.0).T,
            cpd_rigid(src, dst, valid, valid, T_init, w=0.2).T,
            pycpd_rigid(s_np, d_np, 100, args.pycpd_tol, 0.2),
        ]
        cells = " | ".join("{:.3f} deg {:.2f} mm".format(*errors(T_est, T)) for T_est in Ts)
        print(f"| {noise:g} | {frac:.0%} | {cells} |")


def main():
    p = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--B", type=int, default=8, help="point sets per batch")
    p.add_argument("--N", type=int, default=300, help="points per set")
    p.add_argument("--repeats", type=int, default=20, help="timed calls per row")
    p.add_argument("--threads", type=int, default=1, help="torch.set_num_threads (1: reproducible on a loaded box)")
    p.add_argument("--w", type=float, default=0.0, help="CPD outlier weight in the speed table")
    p.add_argument("--pycpd-tol", type=float, default=1e-3, help="pycpd's absolute tolerance on Q (its default)")
    p.add_argument("--fixed-icp", type=int, default=10, help="iterations of the fixed-work ICP rows")
    p.add_argument("--fixed-cpd", type=int, default=30, help="iterations of the fixed-work CPD rows")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    bench_speed(args)
    bench_accuracy(args)


if __name__ == "__main__":
    main()
