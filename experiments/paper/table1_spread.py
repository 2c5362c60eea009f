"""Paper Table I: 3D spread of the tracked points vs pose error, on an artificial motion of a real model.

    python experiments/paper/table1_spread.py --out runs/paper/table1          # visp_castle_simu frame 0, 20 trials
    python experiments/paper/table1_spread.py --sequence sun3d_fragment1 --features 100 --out /tmp/t1

As in the paper (§III-B, on its Face sequence): the point-cloud model (PCM) of a real frame is taken (the
object by depth: the pixels with depth in [near, far], automatic by default), a smooth artificial motion is defined, the exact
2D pixels (eq. 7) and 3D points (eq. 6) of subsets of the PCM are generated with Gaussian noise and fed to
the fusion EKF (:class:`torchtrack.filter.backend.EKFBackend`, fixed variances = the noise), and the per-axis
pose errors (:func:`torchtrack.metrics.per_axis_errors`, mrad and mm, frames after the first) are reported
against the subsets' 3D spread ``|| sigma_XYZ ||`` (the norm of the per-axis standard deviations, mm).

Subsets of growing spread: N points drawn at random among the PCM points within the q-quantile of the
distance to the PCM centroid, for growing q (``--fractions``); every (q, trial) is one sequence of the
EKF's batch. Writes ``OUT/table1_spread.{md,json,png}``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.frame import Observation
from torchtrack.filter.fusion import FusionEKF
from torchtrack.filter.weighting import Variances
from torchtrack.geometry import euler_to_matrix, make_T, project, transform_points
from torchtrack.image.object_model import feature_spread, object_mask, point_cloud_model
from torchtrack.metrics import per_axis_errors

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
AXES = ("Rot-x", "Rot-y", "Rot-z", "Tr-x", "Tr-y", "Tr-z")


class Model(NamedTuple):
    """points_obj (P, 3) float64 PCM in the object frame (model camera axes, origin at the centroid);
    centroid (3,) its position in the camera; K (3, 3) float64."""

    points_obj: Tensor
    centroid: Tensor
    K: Tensor


def load_model(root: Path, frame: int = 0, near: float | None = None, far: float | None = None) -> Model:
    """The PCM of one frame: the object by depth (:func:`~torchtrack.image.object_model.object_mask`, [near, far]
    in metres, automatic where None) back-projected (:func:`~torchtrack.image.object_model.point_cloud_model`)."""
    from torchtrack.data.tum import TumSequence

    seq = TumSequence(root, max_frames=frame + 1)
    f = seq[frame]
    depth, K = f.depth[None].double(), seq.K.double()[None]  # 1,1,H,W and 1,3,3
    mask = object_mask(depth, near=near, far=far)
    pcm = point_cloud_model(f.rgb[None].double(), depth, K, mask)
    cloud = pcm.points_colors[0, pcm.valid[0], :3]
    if len(cloud) < 10:
        raise ValueError(f"{root} frame {frame}: fewer than 10 object pixels with depth in [{near}, {far}] m")
    centroid = cloud.mean(0)
    return Model(cloud - centroid, centroid, K[0])


def spread(points: Tensor) -> Tensor:
    """|| sigma_XYZ || (m) of (..., N, 3) points -> (...): :func:`~torchtrack.image.object_model.feature_spread`."""
    return feature_spread(points.reshape(-1, *points.shape[-2:])).reshape(points.shape[:-2])


def spread_subsets(points_obj: Tensor, n: int, fractions: list[float], trials: int, gen: torch.Generator) -> Tensor:
    """Indices (G * trials, n): for each fraction q, ``trials`` random n-subsets of the points within the
    q-quantile of the distance to the centroid (G = len(fractions), group-major)."""
    dist = points_obj.norm(dim=-1)
    out = []
    for q in fractions:
        pool = (dist <= torch.quantile(dist, q)).nonzero().squeeze(1)
        if len(pool) < n:
            raise ValueError(f"fraction {q}: only {len(pool)} points for subsets of {n}")
        out += [pool[torch.randperm(len(pool), generator=gen)[:n]] for _ in range(trials)]
    return torch.stack(out)


def artificial_motion(frames: int, fps: float, rot_amp: float, trans_amp: float, centroid: Tensor) -> Tensor:
    """Smooth object motion T_cam_obj (F, 4, 4) float64 starting at (I, centroid): per-axis sinusoids of
    different phases and periods (Euler angles up to ``rot_amp`` rad, translation up to ``trans_amp`` m)."""
    t = torch.arange(frames, dtype=torch.float64)[:, None] / fps  # F,1 seconds
    w = torch.tensor([1.0, 1.3, 0.7], dtype=torch.float64) * 2 * math.pi / (frames / fps)  # one period per sequence
    phase = torch.sin(w * t)  # F,3, 0 at t = 0
    angles = rot_amp * phase
    trans = centroid + trans_amp * torch.sin(w.flip(0) * t)
    return make_T(euler_to_matrix(angles), trans)


def measurements(T_gt: Tensor, X: Tensor, K: Tensor, sigma_pix: float, sigma_xyz: float, gen: torch.Generator):
    """Exact eq. (6)/(7) measurements plus Gaussian noise. T_gt (F, 4, 4), X (B, N, 3) ->
    (points_d (F, B, N, 3), pixels (F, B, N, 2))."""
    Xd = transform_points(T_gt[:, None], X[None])  # F,B,N,3
    pix = project(K, Xd)
    Xd = Xd + sigma_xyz * torch.randn(Xd.shape, generator=gen, dtype=Xd.dtype)
    pix = pix + sigma_pix * torch.randn(pix.shape, generator=gen, dtype=pix.dtype)
    return Xd, pix


def track(X: Tensor, points_d: Tensor, pixels: Tensor, K: Tensor, T0: Tensor, fps: float, sigma2_pix: float,
          sigma2_xyz: float, **ekf_kwargs) -> Tensor:  # fmt: skip
    """The fusion EKF (:class:`~torchtrack.filter.backend.EKFBackend`, the paper's: no gate, no refit) over the
    frames with fixed variances (the first frame initialises): returns T_cam_obj (F, B, 4, 4)."""
    F_, B, N, _ = points_d.shape
    backend = EKFBackend(
        FusionEKF(**{"state": "euler", **ekf_kwargs}, gate=None, refit=None, noise_scale=False)
    )  # eq. (2), the variances as given
    backend.reset(T0.expand(B, 4, 4), torch.ones(B, dtype=torch.bool, device=X.device))
    valid = torch.ones(B, N, dtype=torch.bool, device=X.device)
    var = Variances(torch.full((B, N), sigma2_pix, dtype=X.dtype, device=X.device), torch.full((B, N), sigma2_xyz, dtype=X.dtype, device=X.device))  # fmt: skip
    Kb, T_cd = K.expand(B, 3, 3), torch.eye(4, dtype=X.dtype, device=X.device).expand(B, 4, 4)
    poses = [backend.state.T_cam_obj]
    dt = torch.full((B,), 1.0 / fps, dtype=torch.float64, device=X.device)
    for f in range(1, F_):
        poses.append(backend.step(Observation(dt, X, points_d[f], pixels[f], valid, Kb, T_cd), var).T_cam_obj)
    return torch.stack(poses)


def run(model: Model, args: argparse.Namespace) -> dict:
    """Table I's numbers: per fraction group, mean spread (mm) and mean per-axis errors (mrad, mm) over trials."""
    gen = torch.Generator().manual_seed(args.seed)
    idx = spread_subsets(model.points_obj, args.features, args.fractions, args.trials, gen)
    X = model.points_obj[idx]  # B,N,3
    T_gt = artificial_motion(args.frames, args.fps, math.radians(args.rot_amp_deg), args.trans_amp, model.centroid)
    points_d, pixels = measurements(T_gt, X, model.K, args.sigma_pix, args.sigma_xyz, gen)
    T_est = track(X, points_d, pixels, model.K, T_gt[0], args.fps,
                  sigma2_pix=args.sigma_pix**2, sigma2_xyz=args.sigma_xyz**2)  # fmt: skip
    rows = []
    for g, q in enumerate(args.fractions):
        sl = slice(g * args.trials, (g + 1) * args.trials)
        errs = []
        for b in range(sl.start, sl.stop):
            e = per_axis_errors(T_est[1:, b], T_gt[1:])
            errs.append(np.concatenate([np.deg2rad(e.rot_mean_deg.numpy()) * 1e3, e.trans_mean_m.numpy() * 1e3]))
        errs = np.stack(errs)
        rows.append({"fraction": q, "spread_mm": float(spread(X[sl]).mean()) * 1e3,
                     "errors": errs.mean(0).tolist(), "errors_std": errs.std(0).tolist()})  # fmt: skip
    return {"rows": rows, "settings": {k: v for k, v in vars(args).items() if k not in ("out", "data")}}


def markdown(result: dict) -> str:
    s = result["settings"]
    head = (f"PCM of `{s['sequence']}` frame {s['frame']}; {s['features']} points per subset, {s['trials']} random "
            f"subsets per row, {s['frames']} frames of artificial motion (Euler amplitude {s['rot_amp_deg']} deg, "
            f"translation {1e3 * s['trans_amp']:.0f} mm), noise {s['sigma_pix']} px and {1e3 * s['sigma_xyz']:.1f} mm. "
            "Rotation errors in mrad, translation errors in mm.\n\n")  # fmt: skip
    lines = ["| Point spread σ_XYZ (mm) | " + " | ".join(AXES) + " |", "|" + "---|" * (len(AXES) + 1)]
    for r in result["rows"]:
        lines.append(f"| {r['spread_mm']:.2f} | " + " | ".join(f"{v:.2f}" for v in r["errors"]) + " |")
    return head + "\n".join(lines) + "\n"


def plot(result: dict, path: Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9, 3.5), layout="constrained")
    x = [r["spread_mm"] for r in result["rows"]]
    for k, (title, unit) in enumerate((("rotation", "mrad"), ("translation", "mm"))):
        ax = fig.add_subplot(1, 2, k + 1)
        for a in range(3):
            ax.plot(x, [r["errors"][3 * k + a] for r in result["rows"]], "o-", label=AXES[3 * k + a])
        ax.set(xlabel="point spread σ_XYZ [mm]", ylabel=f"{title} error [{unit}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100)


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument("--data", type=Path, default=DATA, help="folder of TUM-layout sequence folders")
    p.add_argument("--sequence", default="visp_castle_simu", help="the model's sequence")
    p.add_argument("--frame", type=int, default=0, help="the model's frame")
    p.add_argument("--near", type=float, default=None, help="object by depth, metres (None: automatic)")
    p.add_argument("--far", type=float, default=None, help="object by depth, metres (None: automatic)")
    p.add_argument("--features", type=int, default=50, help="points per subset")
    p.add_argument("--fractions", default="0.2,0.4,0.7,1.0", help="distance quantiles of the subsets' pools")
    p.add_argument("--trials", type=int, default=20, help="random subsets per spread")
    p.add_argument("--frames", type=int, default=60, help="frames of the artificial motion")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the artificial motion")
    p.add_argument("--rot-amp-deg", type=float, default=10.0, help="rotation amplitude (degrees)")
    p.add_argument("--trans-amp", type=float, default=0.03, help="metres")
    p.add_argument("--sigma-pix", type=float, default=0.5, help="pixel noise (px)")
    p.add_argument("--sigma-xyz", type=float, default=0.002, help="metres")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--threads", type=int, default=None, help="torch threads (None: torch's default)")
    p.add_argument("--out", type=Path, default=Path("outputs/table1"), help="output folder")
    args = p.parse_args(argv)
    args.fractions = [float(f) for f in args.fractions.split(",")]
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    model = load_model(args.data / args.sequence, args.frame, args.near, args.far)
    result = run(model, args)
    result["settings"]["pcm_points"] = len(model.points_obj)
    result["settings"]["pcm_spread_mm"] = float(spread(model.points_obj)) * 1e3
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table1_spread.json").write_text(json.dumps(result, indent=2) + "\n")
    (args.out / "table1_spread.md").write_text(markdown(result))
    plot(result, args.out / "table1_spread.png")
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
