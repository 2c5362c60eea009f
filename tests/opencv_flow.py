"""The combined tracker on OpenCV's LK: an external oracle for the torch and compiled LK of torchtrack.image.flow.

``combined_track_opencv`` runs the same passes as :func:`torchtrack.image.flow.combined_track` with
``cv2.calcOpticalFlowPyrLK`` on the 8-bit images (the same window, levels, criteria and minimum eigenvalue), and the
same steps III and IV (:func:`torchtrack.image.flow.pick_tracks`).
"""

from __future__ import annotations

from functools import partial

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.image.flow import FlowFrame, TrackResult, pick_tracks
from torchtrack.image.lk import tim_error


def inside(points: Tensor, h: int, w: int) -> Tensor:
    return (points >= 0).all(-1) & (points[..., 0] <= w - 1) & (points[..., 1] <= h - 1)


def u8(frame: FlowFrame, k: int, b: int) -> np.ndarray:
    """Channel k of sequence b as an (H, W) uint8 image."""
    return (frame.images[k][b, 0] * 255.0).round().clamp(0, 255).to(torch.uint8).cpu().numpy()


def track_opencv(
    prev: FlowFrame, next: FlowFrame, points: Tensor, valid: Tensor, channels, lk_kwargs, with_residual, init=None
):
    """The same with cv2.calcOpticalFlowPyrLK on uint8 images, looped over channels and sequences. The residual is
    OpenCV's ``err`` of the forward pass (mean absolute difference over the window, 0..255 units) divided by 255, the
    torch LK's image units; ``with_residual`` does not change the work (OpenCV always computes it). OpenCV
    runs on the host: the results are moved to the points' device."""
    dev, points, valid = points.device, points.cpu(), valid.cpu()
    init = None if init is None else init.cpu()
    b, n = points.shape[:2]
    h, w = prev.images[0].shape[-2:]
    win = lk_kwargs["window"]
    args = dict(
        winSize=(win, win),
        maxLevel=lk_kwargs["levels"] - 1,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, lk_kwargs["iters"], lk_kwargs["eps"]),
        minEigThreshold=lk_kwargs["min_eig"],
    )
    fwd_pts = points.float().expand(len(channels), b, n, 2).clone()
    status = torch.zeros(len(channels), b, n, dtype=torch.bool, device="cpu")
    d_tim = torch.full((len(channels), b, n), float("inf"), device="cpu")
    residual = torch.zeros(len(channels), b, n, device="cpu")
    for i, k in enumerate(channels):
        for s in range(b):
            sel = valid[s].nonzero().squeeze(1)
            if sel.numel() == 0:
                continue
            x0 = points[s, sel].float().numpy().reshape(-1, 1, 2)
            a, c = u8(prev, k, s), u8(next, k, s)
            if init is None:
                x1, st1, err = cv2.calcOpticalFlowPyrLK(a, c, x0, None, **args)
                back, st2, _ = cv2.calcOpticalFlowPyrLK(c, a, x1, None, **args)
            else:  # both passes start from the prior displacement (forward) and its reverse (backward)
                prior = init[s, sel].float().numpy().reshape(-1, 1, 2) - x0
                flag = dict(flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
                x1, st1, err = cv2.calcOpticalFlowPyrLK(a, c, x0, x0 + prior, **args, **flag)
                back, st2, _ = cv2.calcOpticalFlowPyrLK(c, a, x1, x1 - prior, **args, **flag)
            x1t, backt = torch.from_numpy(x1.reshape(-1, 2)), torch.from_numpy(back.reshape(-1, 2))
            ok_fwd = torch.from_numpy(st1[:, 0] == 1) & inside(x1t, h, w)
            ok_bwd = torch.from_numpy(st2[:, 0] == 1) & inside(backt, h, w)
            d, ok = tim_error(torch.from_numpy(x0.reshape(-1, 2)), backt, ok_fwd, ok_bwd)  # eq. (10)
            fwd_pts[i, s, sel], status[i, s, sel], d_tim[i, s, sel] = x1t, ok, d
            if with_residual:
                residual[i, s, sel] = torch.where(ok, torch.from_numpy(err.reshape(-1)) / 255.0, 0.0)
    return fwd_pts.to(dev), status.to(dev), d_tim.to(dev), residual.to(dev)


def combined_track_opencv(
    prev: FlowFrame,
    next: FlowFrame,
    points: Tensor,
    valid: Tensor | None = None,
    *,
    mode: str = "combined",
    tim_threshold: float = 1.0,
    window: int = 21,
    levels: int = 3,
    iters: int = 30,
    eps: float = 0.01,
    min_eig: float = 1.0e-4,
    policy: str = "fallback",
    with_residual: bool = False,
    init: Tensor | None = None,
) -> TrackResult:
    """:func:`torchtrack.image.flow.combined_track` with OpenCV's LK for every pass."""
    valid = torch.ones(points.shape[:2], dtype=torch.bool, device=points.device) if valid is None else valid.bool()
    lk_kwargs = dict(window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig)
    track = partial(track_opencv, prev, next, points, lk_kwargs=lk_kwargs, with_residual=with_residual, init=init)
    return pick_tracks(track, points, valid, prev.images[0].shape[-2:], mode=mode, policy=policy,
                       tim_threshold=tim_threshold)  # fmt: skip
