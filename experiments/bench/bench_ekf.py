"""Benchmark of the filter stage (torchtrack.filter): Jacobians, update forms, per-frame step, iterated EKF.

Run: ``python experiments/bench/bench_ekf.py [--n 300] [--reps 40] [--json out.json]``

Timings use one thread (``torch.set_num_threads(1)``), run every variant interleaved in one process and
report the minimum and the median wall time per call (the machine may be shared: compare ratios).
The accuracy part runs a synthetic sequence with an abrupt motion reversal and noisy measurements,
with 1, 2 and 3 EKF iterations.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch

from torchtrack.filter import FusionEKF, Variances, ekf, measure_analytic, measure_single
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.frame import Observation
from torchtrack.geometry import T_inv, intrinsics_matrix, make_T, project, rotation_angle, so3_exp, transform_points

F64 = torch.float64


def timeit(fns: dict, reps: int, warmup: int = 3) -> dict:
    """Interleaved timing, after ``warmup`` calls each: {name: (min_ms, median_ms)}."""
    times = {k: [] for k in fns}
    for f in fns.values():
        for _ in range(warmup):
            f()
    for _ in range(reps):
        for k, f in fns.items():
            t = time.perf_counter()
            f()
            times[k].append((time.perf_counter() - t) * 1e3)
    return {k: (min(v), statistics.median(v)) for k, v in times.items()}


def problem(B: int, N: int, dtype=F64, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.cat([0.2 * torch.randn(B, 6, generator=g), 0.1 * torch.randn(B, 6, generator=g)], -1).to(dtype)
    x[:, 5] += 1.5
    X = (0.2 * torch.randn(B, N, 3, generator=g)).to(dtype)
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=dtype).expand(B, 3, 3).contiguous()
    T = make_T(so3_exp(0.02 * torch.randn(B, 3, generator=g)), 0.02 * torch.randn(B, 3, generator=g)).to(dtype)
    lin = measure_analytic(x, X, K, T)
    z = lin.h + 1e-3 * torch.randn(lin.h.shape, generator=g).to(dtype)
    var = torch.cat([torch.full((B, N, 3), 1e-4), torch.full((B, N, 2), 1.0)], -1).to(dtype)
    cov = torch.diag_embed(torch.tensor([1e-4] * 6 + [1e-2] * 6, dtype=dtype).expand(B, 12))
    return x, cov, X, K, T, lin, z, var


def bench_batch(B: int, N: int, reps: int) -> dict:
    """Timings at one batch size: Jacobians, update algebra (both forms), EKFBackend per-frame step."""
    x, cov, X, K, T, lin, z, var = problem(B, N)
    valid = torch.ones(B, N, dtype=torch.bool)

    def fixed(*_):  # isolates the update algebra from the Jacobian
        return lin

    res = timeit(
        {
            "jacobian jacfwd (autograd)": lambda: ekf.linearize(measure_single, x, (X,), (K, T), "forward"),
            "jacobian jacrev (autograd)": lambda: ekf.linearize(measure_single, x, (X,), (K, T), "reverse"),
            "jacobian analytic": lambda: measure_analytic(x, X, K, T),
            "update algebra, information form": lambda: ekf.update(x, cov, z, var, valid, linearizer=fixed),
            "update algebra, gain form eq. (15)": lambda: ekf.update(
                x, cov, z, var, valid, linearizer=fixed, form="gain"
            ),
        },
        max(3, reps // 4) if B == 4 else reps // 2,
    )
    dt = torch.full((B,), 1 / 30, dtype=F64)
    steps = {}
    obs = Observation(dt, X, z[..., :3], z[..., 3:], valid, K, T)
    fixed_var = Variances(var[..., 3], var[..., 0])
    for state in ("se3", "euler"):
        for jac in ("forward", "analytic"):
            backend = EKFBackend(FusionEKF(jacobian=jac, state=state, gate=None, refit=None, noise_scale=False))
            backend.reset(make_T(torch.eye(3, dtype=F64).expand(B, 3, 3), x[:, 3:6]), valid[:, 0])

            def step(backend=backend):
                backend.step(obs, fixed_var)

            steps[f"EKFBackend step (predict+update), state={state}, jacobian={jac}"] = step
    scaled = EKFBackend(FusionEKF(gate=None, refit=None, noise_scale=True))  # the default's online noise scale
    scaled.reset(make_T(torch.eye(3, dtype=F64).expand(B, 3, 3), x[:, 3:6]), valid[:, 0])
    steps["EKFBackend step (predict+update), state=se3, jacobian=analytic, with the online noise scale"] = lambda: (
        scaled.step(obs, fixed_var)
    )
    res.update(timeit(steps, reps))
    return res


def bench_speed(N: int, reps: int) -> dict:
    return {f"B={B}": bench_batch(B, N, reps) for B in (1, 4)}


def true_pose(t: torch.Tensor, B: int) -> torch.Tensor:
    """Rotation at 90 deg/s about a tilted axis that reverses at t = 0.5 s; translation at 0.3 m/s."""
    axis = torch.tensor([0.3, 1.0, 0.2], dtype=F64)
    axis = axis / axis.norm()
    rate = math.radians(90.0)
    angle = torch.where(t < 0.5, rate * t, rate * (1.0 - t))
    R = so3_exp(axis * angle[..., None])
    tr = torch.stack([0.3 * t, 0.0 * t, 1.2 + 0.0 * t], -1)
    return make_T(R, tr).expand(B, 4, 4)


def bench_iterations(B: int = 4, N: int = 300, frames: int = 30) -> dict:
    g = torch.Generator().manual_seed(0)
    X = 0.15 * torch.randn(B, N, 3, generator=g, dtype=F64)
    X = X - X.mean(1, keepdim=True)
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=F64).expand(B, 3, 3)
    noise_pix, noise_xyz = 0.5, 2e-3
    dt = 1 / 30
    meas = []
    for k in range(1, frames + 1):
        T = true_pose(torch.tensor(k * dt, dtype=F64), B)
        pd = transform_points(T, X)
        px = project(K, pd) + noise_pix * torch.randn(B, N, 2, generator=g, dtype=F64)
        meas.append((T, pd + noise_xyz * torch.randn(B, N, 3, generator=g, dtype=F64), px))
    out = {}
    valid = torch.ones(B, N, dtype=torch.bool)
    var = Variances(torch.full((B, N), noise_pix**2, dtype=F64), torch.full((B, N), noise_xyz**2, dtype=F64))
    T_cd = torch.eye(4, dtype=F64).expand(B, 4, 4)
    for it in (1, 2, 3):
        backend = EKFBackend(FusionEKF(iterations=it, jacobian="analytic", gate=None, refit=None, noise_scale=False))
        backend.reset(true_pose(torch.tensor(0.0, dtype=F64), B), valid[:, 0])
        rot, trans, t_step = [], [], []
        for T, pd, px in meas:
            t0 = time.perf_counter()
            est = backend.step(Observation(torch.full((B,), dt, dtype=F64), X, pd, px, valid, K, T_cd), var)
            t_step.append((time.perf_counter() - t0) * 1e3)
            E = T_inv(T) @ est.T_cam_obj
            rot.append(torch.rad2deg(rotation_angle(E[:, :3, :3])).mean().item())
            trans.append(E[:, :3, 3].norm(dim=-1).mean().item() * 1e3)
        jump = int(0.5 / dt)  # the frame right after the reversal
        out[f"iterations={it}"] = {
            "rot_err_deg_mean": statistics.mean(rot),
            "rot_err_deg_after_reversal": rot[jump],
            "trans_err_mm_mean": statistics.mean(trans),
            "trans_err_mm_after_reversal": trans[jump],
            "step_ms_median_B4": statistics.median(t_step),
        }
    return out


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help: the module docstring as written, and every option's default."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=HelpFormatter)
    ap.add_argument("--n", type=int, default=300, help="features per sequence")
    ap.add_argument("--reps", type=int, default=40, help="timed calls per variant")
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"torch {torch.__version__}, 1 thread, N={args.n}, float64 filter state; min / median ms per call")
    speed = bench_speed(args.n, args.reps)
    for b, res in speed.items():
        print(f"\n[{b}]")
        for k, (mn, md) in res.items():
            print(f"  {k:48s} {mn:8.3f} / {md:8.3f}")
        r = res["jacobian jacfwd (autograd)"][0] / res["jacobian analytic"][0]
        g = res["update algebra, gain form eq. (15)"][0] / res["update algebra, information form"][0]
        print(f"  ratio jacfwd/analytic {r:.1f}x, gain/information form {g:.0f}x (by min)")
    print("\n[iterated EKF: 90 deg/s rotation reversing at t=0.5 s, 0.5 px / 2 mm noise, B=4, N=300]")
    iters = bench_iterations(N=args.n)
    for k, v in iters.items():
        print("  " + k + ": " + ", ".join(f"{kk} {vv:.4f}" for kk, vv in v.items()))
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"speed": speed, "iterated": iters}, f, indent=2)


if __name__ == "__main__":
    main()
