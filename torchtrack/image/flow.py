"""The combined intensity + SIM feature tracker with template inverse matching (paper §III-C, eq. (10)).

Steps of §III-C, per feature: (I) track with pyramidal LK on a) intensity and b) the SIM image;
(II) track each result back and take the TIM error d_TIM = ||x - x'|| (eq. 10); (III) keep the tracker
with the smaller d_TIM; (IV) drop the feature when that d_TIM is above a threshold or the track failed
(left the image, degenerate window, no convergence). Dropping features without depth at the new
position is the caller's job.

Each frame is prepared once (:func:`prepare_frame`): intensity and SIM are stacked into one pyramid, so
the two forward passes run as one batched LK call, and so do the two backward passes; the frame's
pyramid is the next call's template. Steps III and IV (:func:`pick_tracks`) take the per-channel passes as a
function, so that the tests run them on OpenCV's ``calcOpticalFlowPyrLK`` as well (tests/opencv_flow.py).

Defaults are torchtrack's (the improvements on); the application's schema repeats them (``FlowConfig``), and
tests/test_defaults.py holds the two equal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Literal, NamedTuple

import torch
from torch import Tensor

from torchtrack.image.lk import lk_track_flat, tim_error
from torchtrack.image.pyramid import Pyramid, build_pyramid, layout

Mode = Literal["combined", "intensity", "sim"]
_CHANNELS = {"combined": (0, 1), "intensity": (0,), "sim": (1,)}


@dataclass
class FlowFrame:
    """One frame prepared for tracking, built once and used as next, then as prev.

    Attributes:
        images: the K tracked (B, 1, H, W) images: (intensity, SIM) or (intensity,).
        pyramid: LK pyramid of the K * B images stacked as (K * B, 1, H, W): image k * B + b is channel k of
            sequence b.
    """

    images: tuple[Tensor, ...]
    pyramid: Pyramid

    @property
    def batch(self) -> int:
        return self.images[0].shape[0]

    @property
    def has_sim(self) -> bool:
        return len(self.images) == 2


def prepare_frame(gray: Tensor, sim: Tensor | None = None, levels: int = 3, *, max_window: int = 31) -> FlowFrame:
    """Prepare a frame for the combined tracker: build the intensity and SIM pyramids once.

    Args:
        gray: (B, 1, H, W) intensity in [0, 1].
        sim: (B, 1, H, W) SIM image in [0, 1] (``shape_index.sim_image``), or None for intensity only.
        levels: pyramid levels L (OpenCV maxLevel = L - 1).
        max_window: the largest LK window the frame must support.
    """
    if gray.ndim != 4 or gray.shape[1] != 1:
        raise ValueError(f"prepare_frame: gray must be (B, 1, H, W), got {tuple(gray.shape)}")
    if sim is not None and sim.shape != gray.shape:
        raise ValueError(f"prepare_frame: sim must match gray {tuple(gray.shape)}, got {tuple(sim.shape)}")
    images = (gray.float(), sim.float()) if sim is not None else (gray.float(),)
    return FlowFrame(images, build_pyramid(images, levels, window=max_window))


def zero_frame(images: tuple[Tensor, ...], levels: int = 3, *, max_window: int = 31) -> FlowFrame:
    """:func:`prepare_frame` of K (B, 1, H, W) images that are all zeros, without building: the pyramid of zero images
    is zeros, laid out as :func:`~torchtrack.image.pyramid.build_pyramid` lays out K * B images (the frame's
    ``images`` are ``images`` themselves). A buffer to copy other frames' pyramids into, image by image."""
    b, c, h, w = images[0].shape
    b *= len(images)
    pad, sizes, heights, starts, row_start = layout(b, h, w, levels, max_window, images[0].device)
    with torch.inference_mode():
        buf = images[0].new_zeros(c, sum(heights) * b, w + 2 * pad, dtype=torch.float32)
        views = [buf[:, int(s0) : int(s0) + b * ht].view(c, b, ht, -1)[..., pad : pad + hl, pad : pad + wl].transpose(0, 1)
                 for s0, ht, (hl, wl) in zip(starts, heights, sizes, strict=True)]  # fmt: skip
    pyr = Pyramid(views, buf.view(-1), row_start, stride=w + 2 * pad, plane=buf[0].numel(), pad=pad)
    return FlowFrame(tuple(x.float() for x in images), pyr)


def repeat_frame(frame: FlowFrame, times: int) -> FlowFrame:
    """``frame`` seen as ``times`` copies of its batch B, without copying a pixel: image k * (times B) + t B + b of
    the result is image k * B + b of ``frame`` (the layout of a frame of batch times * B). The pyramid shares the
    frame's buffer with its row table repeated; the images are shape-only (NaN) placeholders, so the result serves
    as an LK pyramid only (the torch back end of :func:`combined_track`), e.g. the current frame as next for prev
    frames stacked from ``times`` keyframes (:class:`~torchtrack.pipeline.landmarks.LandmarkMap`)."""
    pyr, b, k = frame.pyramid, frame.batch, len(frame.images)
    ar = partial(torch.arange, device=pyr.row_start.device)
    idx = (ar(k)[:, None, None] * b + ar(b)[None, None, :]).expand(k, times, b).reshape(-1)
    nan = pyr.flat.new_full((), float("nan"))
    shape = lambda x: nan.expand(x.shape[0] * times, *x.shape[1:])  # noqa: E731
    rep = Pyramid([shape(x) for x in pyr.images], pyr.flat, pyr.row_start.index_select(1, idx), pyr.stride,
                  pyr.plane, pyr.pad)  # fmt: skip
    return FlowFrame(tuple(shape(x) for x in frame.images), rep)


class TrackResult(NamedTuple):
    """Per feature (all (B, N)): the combined tracker's output.

    points: (B, N, 2) position in the next frame from the winning tracker (input where not tracked).
    valid: kept: valid input, tracked, inside the image, d_TIM <= threshold.
    d_tim: d_TIM of the winner (eq. 10), +inf where not tracked. d_tim_int, d_tim_sim: of each tracker.
    winner: int64, 0 intensity, 1 SIM. status_int, status_sim: each tracker's forward and backward success.
    residual: the winner's forward LK residual, mean |I_next(x + d) - I_prev(x)| over the final level-0 window in
        image units ([0, 1]); 0 where that pass did not track, and zeros everywhere unless asked (``with_residual``).
    """

    points: Tensor
    valid: Tensor
    d_tim: Tensor
    d_tim_int: Tensor
    d_tim_sim: Tensor
    winner: Tensor
    status_int: Tensor
    status_sim: Tensor
    residual: Tensor


def _inside(points: Tensor, h: int, w: int) -> Tensor:
    return (points >= 0).all(-1) & (points[..., 0] <= w - 1) & (points[..., 1] <= h - 1)


def _track_lk(
    prev: FlowFrame, next: FlowFrame, points: Tensor, valid: Tensor, channels, lk_kwargs, with_residual, init=None
):
    """Forward and backward LK for each channel k in channels: (fwd points, status, d_tim, forward residual), each
    (K, B, N[, 2]). The forward pass starts at ``init`` (B, N, 2) (default: points), the backward pass at its result
    minus the same prior displacement."""
    b, n = points.shape[:2]
    k, dev = len(channels), points.device
    image = torch.tensor(channels, device=dev)[:, None, None] * b + torch.arange(b, device=dev)[None, :, None]  # K,B,1
    image = image.expand(k, b, n).reshape(-1)
    pts = points.float().expand(k, b, n, 2).reshape(-1, 2)
    sel = valid.expand(k, b, n).reshape(-1).nonzero().squeeze(1)
    fwd_pts, status = pts.clone(), torch.zeros(pts.shape[0], dtype=torch.bool, device=dev)
    x0, img = pts[sel], image[sel]
    guess = x0 if init is None else init.float().expand(k, b, n, 2).reshape(-1, 2)[sel]
    x1, ok, res = lk_track_flat(prev.pyramid, next.pyramid, x0, img, guess, with_residual=with_residual, **lk_kwargs)
    fwd_pts[sel] = x1
    residual = pts.new_zeros(pts.shape[0])
    if with_residual:
        residual[sel] = res
    good = ok.nonzero().squeeze(1)
    back_guess = x1[good] - (guess[good] - x0[good])
    back, ok_back, _ = lk_track_flat(  # template inverse matching: from the result back to prev
        next.pyramid, prev.pyramid, x1[good], img[good], back_guess, with_residual=False, **lk_kwargs
    )
    d_tim = pts.new_full((pts.shape[0],), float("inf"))
    rows = sel[good]
    d_tim[rows], status[rows] = tim_error(x0[good], back, ok[good], ok_back)  # eq. (10)
    return fwd_pts.view(k, b, n, 2), status.view(k, b, n), d_tim.view(k, b, n), residual.view(k, b, n)


def combined_track(
    prev: FlowFrame,
    next: FlowFrame,
    points: Tensor,
    valid: Tensor | None = None,
    *,
    mode: Mode = "combined",
    tim_threshold: float = 1.0,
    window: int = 21,
    levels: int = 3,
    iters: int = 30,
    eps: float = 0.01,
    min_eig: float = 1.0e-4,
    ic_iters: int = 3,
    policy: Literal["min_tim", "fallback"] = "fallback",
    with_residual: bool = False,
    init: Tensor | None = None,
) -> TrackResult:
    """Track features from prev to next with the combined intensity + SIM tracker (§III-C, eq. (10)).

    Args:
        prev, next: prepared frames (prepare_frame), with SIM unless mode == "intensity".
        points: (B, N, 2) pixel positions in prev. valid: (B, N) bool (default all).
        mode: "combined" (paper), "intensity" or "sim" (single trackers, e.g. Table II and EKF-2).
        tim_threshold: features with d_TIM above this (pixels) are dropped (step IV).
        window, levels, iters, eps, min_eig, ic_iters: LK parameters (see ``pyramidal_lk``).
        policy: "min_tim" (paper, step III): per feature the tracker with the smaller d_TIM; "fallback"
            (improvement, the default): the SIM tracker only where the intensity tracker failed step IV. On smooth SIM
            patches LK barely moves forward or backward, so a SIM track can have a tiny d_TIM and still be
            wrong; min_tim then prefers it over a correct intensity track.
        with_residual: also return the winner's forward LK residual (a cue for learned weighting; one more window
            sample per point, the tracks are unchanged); zeros otherwise.
        init: (B, N, 2) where each forward pass starts in next (default: points, as the paper); the backward pass
            starts at the forward result minus the same prior displacement, and d_TIM is still measured against
            points.

    Returns:
        TrackResult; d_tim_* and status_* of a tracker that did not run are +inf and False.
    """
    if mode not in _CHANNELS:
        raise ValueError(f"combined_track: mode must be one of {tuple(_CHANNELS)}, got {mode!r}")
    if points.ndim != 3 or points.shape[-1] != 2 or points.shape[0] != prev.batch:
        raise ValueError(f"combined_track: points must be (B={prev.batch}, N, 2), got {tuple(points.shape)}")
    if mode != "intensity" and not (prev.has_sim and next.has_sim):
        raise ValueError(f"combined_track: mode {mode!r} needs frames prepared with a SIM image")
    if window > prev.pyramid.max_window or levels > prev.pyramid.levels:
        raise ValueError(f"combined_track: frames support window <= {prev.pyramid.max_window}, levels <= "
                         f"{prev.pyramid.levels}; got {window}, {levels}")  # fmt: skip
    b, n = points.shape[:2]
    dev = points.device
    valid = torch.ones(b, n, dtype=torch.bool, device=dev) if valid is None else valid.bool()
    if valid.shape != (b, n):
        raise ValueError(f"combined_track: valid must be {(b, n)}, got {tuple(valid.shape)}")
    if init is not None and init.shape != points.shape:
        raise ValueError(f"combined_track: init must be {tuple(points.shape)}, got {tuple(init.shape)}")
    lk_kwargs = dict(window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters)
    track = partial(_track_lk, prev, next, points, lk_kwargs=lk_kwargs, with_residual=with_residual, init=init)
    return pick_tracks(track, points, valid, prev.images[0].shape[-2:], mode=mode, policy=policy,
                       tim_threshold=tim_threshold)  # fmt: skip


def pick_tracks(
    track: Callable[..., tuple[Tensor, Tensor, Tensor, Tensor]],
    points: Tensor,
    valid: Tensor,
    size: tuple[int, int],
    *,
    mode: Mode = "combined",
    policy: Literal["min_tim", "fallback"] = "fallback",
    tim_threshold: float = 1.0,
) -> TrackResult:
    """Steps III and IV of §III-C over the passes ``track(valid=, channels=)``: for each channel k (0 intensity, 1 SIM)
    of ``channels``, the forward and backward passes of the features in ``valid`` (B, N), returned as (forward points
    (K, B, N, 2), status (K, B, N), d_TIM (K, B, N), forward residual (K, B, N)). ``points`` (B, N, 2) are the
    features in prev, ``size`` (H, W) the images'. :func:`combined_track` passes its LK; the tests OpenCV's."""
    if policy not in ("min_tim", "fallback"):
        raise ValueError(f"combined_track: policy must be 'min_tim' or 'fallback', got {policy!r}")
    channels = _CHANNELS[mode]
    b, n = points.shape[:2]
    dev = points.device
    if policy == "fallback" and len(channels) == 2:
        # the SIM tracker runs only where the intensity tracker failed step IV (its d_TIM elsewhere: inf)
        first = track(valid=valid, channels=channels[:1])
        failed = valid & ~(first[2][0] <= tim_threshold)
        second = track(valid=failed, channels=channels[1:])
        fwd, status, d_tim, residual = (torch.cat([a, b]) for a, b in zip(first, second, strict=True))
    else:
        fwd, status, d_tim, residual = track(valid=valid, channels=channels)
    pick = (d_tim[-1] < d_tim[0]).long()  # step III: the tracker with the smaller d_TIM (ties: intensity)
    best = d_tim.gather(0, pick[None])[0]
    chosen = fwd.gather(0, pick[None, ..., None].expand(1, b, n, 2))[0]
    winner = torch.tensor(channels, device=dev)[pick]
    residual = residual.gather(0, pick[None])[0]
    keep = valid & torch.isfinite(best) & (best <= tim_threshold) & _inside(chosen, *size)  # step IV
    full = {c: (d_tim[i], status[i]) for i, c in enumerate(channels)}
    none = (torch.full((b, n), float("inf"), device=dev), torch.zeros(b, n, dtype=torch.bool, device=dev))
    (d_int, st_int), (d_sim, st_sim) = full.get(0, none), full.get(1, none)
    points_out = torch.where(keep[..., None], chosen, points.float()).to(points.dtype)
    return TrackResult(points_out, keep, best, d_int, d_sim, winner, st_int, st_sim, residual)


class CombinedTracker:
    """Holds the combined tracker's parameters; ``__call__(prev, next, points, valid, with_residual=False)`` delegates
    to :func:`combined_track` and ``prepare(gray, sim)`` to :func:`prepare_frame`."""

    pyramids_only = True  # reads the frames' pyramids alone: a repeat_frame (placeholder images) serves as a frame

    def __init__(
        self,
        mode: Mode = "combined",
        tim_threshold: float = 1.0,
        window: int = 21,
        levels: int = 3,
        iters: int = 30,
        eps: float = 0.01,
        min_eig: float = 1.0e-4,
        ic_iters: int = 3,
        policy: Literal["min_tim", "fallback"] = "fallback",
    ) -> None:
        for key, value, allowed in (("mode", mode, tuple(_CHANNELS)), ("policy", policy, ("min_tim", "fallback"))):
            if value not in allowed:
                raise ValueError(f"flow.{key} must be one of {', '.join(allowed)}, got {value!r}")
        self.levels = levels
        self.kwargs = dict(
            mode=mode, tim_threshold=tim_threshold, window=window, levels=levels, iters=iters, eps=eps,
            min_eig=min_eig, ic_iters=ic_iters, policy=policy,
        )  # fmt: skip

    def prepare(self, gray: Tensor, sim: Tensor | None = None) -> FlowFrame:
        return prepare_frame(gray, sim, self.levels)

    def __call__(
        self,
        prev: FlowFrame,
        next: FlowFrame,
        points: Tensor,
        valid: Tensor | None = None,
        with_residual: bool = False,
        init: Tensor | None = None,
    ) -> TrackResult:
        return combined_track(prev, next, points, valid, **self.kwargs, with_residual=with_residual, init=init)
