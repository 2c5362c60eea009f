"""Per-feature quality cues: what a learned weighting sees of each tracked feature.

A frame's cues are one (B, N, C) float32 tensor whose last axis follows :data:`CUE_NAMES`. Cues are raw,
finite physical values (pixels, metres, frames); a model normalises them itself. Values that do not exist
for a feature (the SIM tracker did not run, a track failed) are capped at :data:`D_TIM_CAP` pixels, never inf.
Bump :data:`CUE_VERSION` whenever a name, its order or its meaning changes: caches and checkpoints carry it,
and a mismatch is an error.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

CUE_VERSION = 2  # 2: + depth_step, depth_holes, lk_min_eig, fb_error
D_TIM_CAP = 100.0  # px; stands for "did not track" in the d_TIM cues

CUE_NAMES: tuple[str, ...] = (
    "d_tim_int",  # px, d_TIM (eq. 10) of the intensity tracker; D_TIM_CAP where it did not run or failed
    "d_tim_sim",  # px, d_TIM of the SIM tracker; D_TIM_CAP where it did not run or failed
    "sim_won",  # 1 where the SIM tracker won (eq. 10, step III), else 0
    "lk_residual",  # mean |I_next(x + d) - I_prev(x)| over the final LK window of the winning tracker, image units
    "depth",  # z of the measured 3D point X_d, m (depth camera)
    "centroid_dist",  # ||X_d - centroid of the frame's valid X_d||, m (eq. 13's cue)
    "cornerness_int",  # normalised intensity Harris cornerness at selection (eq. 9)
    "cornerness_sim",  # normalised SIM Harris cornerness at selection (eq. 9)
    "sim_value",  # shape index (eq. 8) at the tracked pixel, [0, 1]
    "track_age",  # frames since the feature was selected (0 in its selection frame)
    "prev_reproj",  # px, the feature's reprojection residual (eq. 16) in the previous frame; 0 when new
    "u_norm",  # pixel x / image width, [0, 1]
    "v_norm",  # pixel y / image height, [0, 1]
    "depth_step",  # m, max - min of the valid depths in the DEPTH_WINDOW^2 window at the tracked pixel; 0 if none valid
    "depth_holes",  # fraction of that window without depth (0 or outside the image), [0, 1]
    "lk_min_eig",  # smallest eigenvalue of LK's gradient matrix over LK_WINDOW^2 px of the previous image, (1/px)^2
    "fb_error",  # px, the winner's forward-backward error d_TIM (eq. 10); D_TIM_CAP where not tracked
)
CUE_INDEX = {name: i for i, name in enumerate(CUE_NAMES)}


def stack_cues(**cues: Tensor) -> Tensor:
    """Stack named (B, N) cues into (B, N, C) float32 in :data:`CUE_NAMES` order; non-finite values -> D_TIM_CAP.

    Every name of CUE_NAMES must be given, and nothing else."""
    missing, extra = set(CUE_NAMES) - set(cues), set(cues) - set(CUE_NAMES)
    if missing or extra:
        raise ValueError(f"stack_cues: missing {sorted(missing)}, unknown {sorted(extra)}")
    out = torch.stack([cues[n].float() for n in CUE_NAMES], -1)
    return torch.nan_to_num(out, nan=D_TIM_CAP, posinf=D_TIM_CAP, neginf=-D_TIM_CAP)


def check_cue_names(names, version: int, where: str) -> None:
    """Raise a one-line error when ``names``/``version`` (from a cache or a checkpoint) differ from this code's."""
    names = tuple(names)
    if names != CUE_NAMES or int(version) != CUE_VERSION:
        i = next(
            (i for i, (a, b) in enumerate(zip(names, CUE_NAMES, strict=False)) if a != b),
            min(len(names), len(CUE_NAMES)),
        )
        theirs, ours = (n[i] if i < len(n) else "none" for n in (names, CUE_NAMES))
        raise ValueError(
            f"{where}: made with cue version {version} ({len(names)} cues); this torchtrack computes cue version "
            f"{CUE_VERSION} ({len(CUE_NAMES)} cues; column {i}: {theirs!r} there, {ours!r} here): re-record the "
            "cache or retrain the model"
        )


DEPTH_WINDOW = 5  # px, side of the window of depth_step and depth_holes
LK_WINDOW = 21  # px, the window of lk_min_eig: the default LK window (FlowConfig.window), fixed as part of the cue
_SCHARR = (
    torch.tensor([[-3.0, 0.0, 3.0], [-10.0, 0.0, 10.0], [-3.0, 0.0, 3.0]], device="cpu") / 32.0
)  # d/dx per px; .to(win) at use


class WindowCues(NamedTuple):
    """Image-window cues of tracked features, each (B, N): see :data:`CUE_NAMES`."""

    depth_step: Tensor
    depth_holes: Tensor
    lk_min_eig: Tensor


def _windows(image: Tensor, points: Tensor, size: int, fill: float) -> Tensor:
    """(B, 1, H, W) image, (B, N, 2) pixels -> (B, N, size, size) windows centred on the nearest pixel; ``fill``
    outside the image."""
    B, _, H, W = image.shape
    r = size // 2
    padded = F.pad(image[:, 0], (r, r, r, r), value=fill)  # B,H+2r,W+2r
    c = torch.nan_to_num(points, nan=-1e6).round().long()
    u = c[..., 0].clamp(-r - 1, W + r) + r  # a point far outside reads only fill
    v = c[..., 1].clamp(-r - 1, H + r) + r
    off = torch.arange(-r, r + 1, device=image.device)
    rows = (v[..., None] + off).clamp(0, H + 2 * r - 1)  # B,N,s
    cols = (u[..., None] + off).clamp(0, W + 2 * r - 1)
    inside_r = (v[..., None] + off >= 0) & (v[..., None] + off < H + 2 * r)
    inside_c = (u[..., None] + off >= 0) & (u[..., None] + off < W + 2 * r)
    b = torch.arange(B, device=image.device)[:, None, None, None]
    win = padded[b, rows[..., :, None], cols[..., None, :]]  # B,N,s,s
    return torch.where(inside_r[..., :, None] & inside_c[..., None, :], win, torch.full_like(win, fill))


def depth_window_cues(depth: Tensor, points: Tensor) -> tuple[Tensor, Tensor]:
    """depth (B, 1, H, W) metres (0 = none), points (B, N, 2) pixels -> (depth_step, depth_holes), each (B, N):
    the spread max - min of the valid depths in the DEPTH_WINDOW x DEPTH_WINDOW window at the nearest pixel
    (0 without a valid depth) and the fraction of that window without depth (outside the image counts)."""
    win = _windows(depth, points, DEPTH_WINDOW, 0.0).flatten(-2)  # B,N,25
    ok = win > 0
    hi = win.masked_fill(~ok, float("-inf")).amax(-1)
    lo = win.masked_fill(~ok, float("inf")).amin(-1)
    step = torch.where(ok.any(-1), hi - lo, torch.zeros_like(hi))
    return step, 1.0 - ok.to(depth.dtype).mean(-1)


def min_eigenvalue(gray: Tensor, points: Tensor, window: int) -> Tensor:
    """gray (B, 1, H, W) intensities, points (B, N, 2) -> (B, N) smallest eigenvalue of LK's gradient matrix
    ``G = mean over the window x window pixels at the nearest pixel of [gx^2, gx gy; gx gy, gy^2]`` with Scharr
    derivatives per pixel (kernel / 32, as the LK tracker's), the image replicated by zeros outside.
    Closed form: ``(a + c) / 2 - sqrt(((a - c) / 2)^2 + b^2)``. Reference: Shi & Tomasi, "Good features to
    track" (CVPR 1994); OpenCV's ``minEigThreshold`` is this value on 0..255 intensities."""
    win = _windows(gray, points, window + 2, 0.0)  # B,N,w+2,w+2: the window and a rim for the derivatives
    B, N, m, _ = win.shape
    k = _SCHARR.to(win)
    g = F.conv2d(win.reshape(B * N, 1, m, m), torch.stack([k, k.T])[:, None])  # correlation: d/dx, d/dy
    gx, gy = g[:, 0].reshape(B, N, -1), g[:, 1].reshape(B, N, -1)
    a, b, c = (gx * gx).mean(-1), (gx * gy).mean(-1), (gy * gy).mean(-1)
    return ((a + c) / 2 - torch.sqrt(((a - c) / 2).square() + b.square())).clamp_min(0.0)


def window_cues(depth: Tensor, points: Tensor, gray_prev: Tensor, points_prev: Tensor, window: int = LK_WINDOW) -> dict:
    """The window cues as :func:`stack_cues` keywords: depth_step and depth_holes of ``depth`` (B, 1, H, W) at the
    tracked ``points`` (B, N, 2); lk_min_eig of ``gray_prev`` (B, 1, H, W) at ``points_prev`` (B, N, 2), where LK
    took its template, over ``window`` (a cue's meaning is part of a checkpoint's: it does not follow flow.window)."""
    step, holes = depth_window_cues(depth, points)
    return WindowCues(step, holes, min_eigenvalue(gray_prev, points_prev, window))._asdict()
