"""Re-acquisition error with and without the pose-warped template (torchtrack/image/warp.py), exact ground truth.

Synthetic scene sequence (noise-free render, torchtrack.data.synthetic): keyframe = frame 0, current = frame g for
several gaps g. Landmarks: the strongest Harris corners of the keyframe (one per 20 px cell) with depth. Exact track:
the keyframe pixel back-projected with the exact depth, moved by the exact relative pose, projected. LK starts at the
projection under a predicted pose off by ``--pose-err-deg`` / ``--pose-err-m`` (the drift re-acquisition corrects).
Three trackers, the same LK settings (the flow config's), each with the TIM check at 1 px:
  full     today's re-acquisition: LK from the keyframe image into the current image (whole images)
  crop     the crop-based tracker with the unwarped template (translation only): the warp's baseline
  warp     the crop-based tracker with the template warped by the predicted pose's plane homography (normal from the
           keyframe's depth)
Reports per gap: tracked (TIM-passed) count, median / mean / 90th percentile error (px), share within 0.5 px and 1 px.

    python experiments/warp_reacquire.py [--gaps 5 10 20 30] [--seeds 0 1 2] [--crop 48] [--levels 2]
"""

from __future__ import annotations

import argparse
import json
import math

import torch

from torchtrack.config import FlowConfig, LandmarkConfig
from torchtrack.data.synthetic import SyntheticConfig, default_scene, render_frame, sequence_poses
from torchtrack.geometry import T_inv, backproject, project, se3_exp, transform_points
from torchtrack.image.corners import harris
from torchtrack.image.flow import combined_track, prepare_frame
from torchtrack.image.warp import track_warped, translation_homography, warped_landmark_tracks


def gray(rgb: torch.Tensor) -> torch.Tensor:
    return (0.299 * rgb[:, 0:1] + 0.587 * rgb[:, 1:2] + 0.114 * rgb[:, 2:3]).contiguous()


def corners(g: torch.Tensor, depth: torch.Tensor, cell: int = 20, border: int = 40) -> torch.Tensor:
    """(1, C, 2) the strongest Harris response per cell with depth, away from the border."""
    r = harris(g)[0, 0] if harris(g).dim() == 4 else harris(g)[0]
    r = torch.where(depth[0, 0] > 0, r, torch.full_like(r, -float("inf")))
    H, W = r.shape
    r = r[border : H - border, border : W - border]
    h, w = (r.shape[0] // cell) * cell, (r.shape[1] // cell) * cell
    blocks = r[:h, :w].reshape(h // cell, cell, w // cell, cell).permute(0, 2, 1, 3).reshape(-1, cell * cell)
    val, idx = blocks.max(1)
    by, bx = torch.meshgrid(torch.arange(h // cell), torch.arange(w // cell), indexing="ij")
    x = bx.reshape(-1) * cell + idx % cell + border
    y = by.reshape(-1) * cell + idx // cell + border
    keep = val > val[torch.isfinite(val)].quantile(0.5)
    return torch.stack([x, y], -1)[keep][None].float()


def run(
    gap: int,
    seed: int,
    pose_err_deg: float,
    pose_err_m: float,
    crop: int = LandmarkConfig.warp_crop,
    levels: int | None = None,
) -> dict:
    cfg = SyntheticConfig(frames=gap + 1, seed=seed, mode="scene", noise="none", trans_step_m=0.015, rot_step_deg=1.5)
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    kf, cur = render_frame(scene, poses.T_world_cam[0]), render_frame(scene, poses.T_world_cam[gap])
    K = scene.K.double()[None]
    g_kf, g_cur = gray(kf.rgb[None]), gray(cur.rgb[None])
    d_kf, d_cur = kf.depth[None], cur.depth[None]
    px = corners(g_kf, d_kf)
    z = d_kf[0, 0, px[0, :, 1].long(), px[0, :, 0].long()][None].double()
    X_kf = backproject(K, px.double(), z)
    T_cur_kf = T_inv(poses.T_world_cam[gap].double()) @ poses.T_world_cam[0].double()
    truth = project(K, transform_points(T_cur_kf[None], X_kf))
    gen = torch.Generator().manual_seed(1000 + seed)
    err = torch.cat(
        [pose_err_m * torch.randn(3, generator=gen), math.radians(pose_err_deg) * torch.randn(3, generator=gen)]
    )
    T_pred = se3_exp(err.double()) @ T_cur_kf
    pred = project(K, transform_points(T_pred[None], X_kf))
    H, W = d_cur.shape[-2:]
    visible = (pred[..., 0] > 45) & (pred[..., 0] < W - 46) & (pred[..., 1] > 45) & (pred[..., 1] < H - 46)
    X_cur = transform_points(T_cur_kf[None], X_kf)
    d_true = d_cur[0, 0].double()[
        truth[0, :, 1].round().long().clamp(0, H - 1), truth[0, :, 0].round().long().clamp(0, W - 1)
    ]
    visible &= (truth[..., 0] > 0) & (truth[..., 0] < W - 1) & ((d_true - X_cur[0, :, 2]).abs() < 0.02)[None]
    out = {}
    fl = FlowConfig()
    kw = dict(window=fl.window, levels=fl.levels, iters=fl.iters, eps=fl.eps, min_eig=fl.min_eig, ic_iters=fl.ic_iters)
    full_kw, kw = dict(kw), dict(kw, crop=crop, levels=levels or fl.levels)
    fr = combined_track(prepare_frame(g_kf, None, fl.levels), prepare_frame(g_cur, None, fl.levels), px, visible,
                        mode="intensity", init=pred.float(), **full_kw)  # fmt: skip
    out["full"] = (fr.points.double(), fr.valid)
    Hc = translation_homography(px.double(), pred)
    r = track_warped(g_kf.double(), g_cur.double(), Hc, px.double(), visible, pred, **kw)
    out["crop"] = (r.pixels, r.status & (r.d_tim <= fl.tim_threshold))
    T_world_kf = poses.T_world_cam[0].double()[None]
    world = transform_points(T_world_kf, X_kf)  # the landmarks (depth registered: colour = depth camera)
    r = warped_landmark_tracks(g_kf, d_kf, g_cur, K, torch.eye(4, dtype=torch.float64)[None], T_world_kf,
                               T_world_kf @ T_inv(T_pred)[None], world, px, pred[:, :, None], visible, **kw)  # fmt: skip
    r = r._replace(pixels=r.pixels[:, :, 0], status=r.status[:, :, 0], d_tim=r.d_tim[:, :, 0])
    out["warp"] = (r.pixels, r.status & (r.d_tim <= fl.tim_threshold))
    res = {"candidates": int(visible.sum())}
    for name, (p, ok) in out.items():
        e = (p - truth).norm(dim=-1)[ok]
        res[name] = e.tolist()
    return res


def summary(errors: list[float], candidates: int) -> str:
    e = torch.tensor(errors, dtype=torch.float64)
    if len(e) == 0:
        return "0 tracked"
    return (f"{len(e):4d}/{candidates:4d} tracked, median {e.median():.3f}, mean {e.mean():.3f}, "
            f"p90 {e.quantile(0.9):.3f} px, <=0.5px {100 * (e <= 0.5).double().mean():.0f}%, "
            f"<=1px {100 * (e <= 1).double().mean():.0f}%")  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--gaps", type=int, nargs="+", default=[5, 10, 20, 30])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--pose-err-deg", type=float, default=1.0)
    p.add_argument("--pose-err-m", type=float, default=0.01)
    p.add_argument("--json", help="write the per-gap errors here")
    p.add_argument("--crop", type=int, default=LandmarkConfig.warp_crop, help="side of the warped crops (px)")
    p.add_argument("--levels", type=int, help="pyramid levels of the crop trackers (default: the flow config's)")
    a = p.parse_args()
    torch.set_num_threads(1)
    table = {}
    for gap in a.gaps:
        agg = {"candidates": 0, "full": [], "crop": [], "warp": []}
        for seed in a.seeds:
            r = run(gap, seed, a.pose_err_deg, a.pose_err_m, a.crop, a.levels)
            agg["candidates"] += r["candidates"]
            for k in ("full", "crop", "warp"):
                agg[k] += r[k]
        table[gap] = agg
        for k in ("full", "crop", "warp"):
            print(f"gap {gap:3d} {k:5s}: {summary(agg[k], agg['candidates'])}", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump(table, f)


if __name__ == "__main__":
    main()
