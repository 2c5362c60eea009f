"""Depth-to-colour registration by edge alignment, for depth that is not registered to colour.

Some sequences (Microsoft 7-Scenes) store depth in the depth camera's own pixel grid. With the two cameras a few
centimetres apart, looking the same way, the map from depth pixels to colour pixels is, up to a parallax of a few
pixels, a magnification about the principal point plus a shift (different focal lengths, offset optical axes):

    u_c = c + s (u_d - c) + t        (u: pixel (x, y), c: a reference point, s: scale, t = (dx, dy): shift at c)

With T_color_depth = identity this is exactly a depth intrinsics matrix: back-projecting u_d through
K_depth = (fx / s, fy / s, cx_d, cy_d) and projecting through the colour K gives u_c when
cx_d = c_x + (cx - c_x - dx) / s (the same for y); for s = 1 and c = (cx, cy), cx_d = cx - dx. The tracker's
front end then registers depth with :func:`torchtrack.geometry.warp_depth` (see :func:`depth_intrinsics`).

Estimation (:func:`estimate_depth_shift`): a depth-discontinuity map is matched to the intensity gradient
magnitude by masked normalised cross-correlation (NCC) over integer shifts, via FFT, averaged over a few frames,
coarse to fine: on a coarse level over a grid of scales and the whole shift window, on a finer level around the
best, with parabolic sub-pixel refinement. The map is applied only when it clearly raises the edge NCC.

Limits: the map ignores parallax. With Kinect v1's ~2.5 cm colour-IR baseline a point at depth z is displaced by
about 525 * 0.025 / z px (13 px at 1 m, 4 px at 3 m), so the fitted shift holds for the scene's typical depth and
is off by a few pixels for much nearer or farther surfaces; modelling it needs T_color_depth with the baseline.

Edge maps and the masked NCC live in :mod:`torchtrack.data.edge_match`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
from kornia.color import rgb_to_grayscale
from torch import Tensor

from torchtrack.data.edge_match import EdgeLevel, area_pool, parabola_offset, surface_peak
from torchtrack.data.errors import DataError

log = logging.getLogger(__name__)

MIN_APPLIED_SHIFT_PX = 2.0  # depth_alignment="auto" leaves a map that moves no pixel by this much alone


class ShiftEstimate(NamedTuple):
    """Depth-to-colour pixel map u_c = centre + scale (u_d - centre) + (dx, dy), from edge alignment.

    Attributes:
        dx, dy: shift in pixels at ``centre`` (everywhere when scale = 1): colour pixel = depth pixel + shift.
        scale: magnification s (colour focal / depth focal); 1 when fitted as a pure shift.
        score: frame-averaged edge NCC at zero residual shift after applying the map, in [-1, 1].
        score_at_zero: the same for the identity map (the depth as given).
        confident: the map clearly registers better than the identity (rule in :func:`estimate_depth_shift`).
        centre: (x, y) reference point in pixels.
        frames: number of frames averaged.
        frames_agreeing: frames whose own NCC peak lies within ``agree_px`` of the averaged one.
        size: (H, W) of the images it was estimated on ((0, 0) for a map given by hand).
    """

    dx: float
    dy: float
    scale: float
    score: float
    score_at_zero: float
    confident: bool
    centre: tuple[float, float]
    frames: int
    frames_agreeing: int
    size: tuple[int, int]

    def max_displacement(self) -> float:
        """Largest pixel displacement |u_c - u_d| the map makes over the image (at a corner; at centre for size 0)."""
        H, W = self.size
        cx, cy = self.centre
        return max(
            math.hypot((self.scale - 1) * (x - cx) + self.dx, (self.scale - 1) * (y - cy) + self.dy)
            for x in ((0, W - 1) if W else (cx,))
            for y in ((0, H - 1) if H else (cy,))
        )


def _as_batch(x: Tensor | Sequence[Tensor], name: str) -> Tensor:
    if isinstance(x, Tensor):
        x = x[None] if x.dim() == 3 else x
    else:
        x = torch.stack([torch.as_tensor(f) for f in x])
    if x.dim() != 4 or x.shape[1] != 1:
        raise ValueError(f"estimate_depth_shift: {name} must be (1, H, W), (B, 1, H, W) or a list of (1, H, W)")
    return x.float()


def estimate_depth_shift(
    gray: Tensor | Sequence[Tensor],
    depth: Tensor | Sequence[Tensor],
    *,
    max_shift: int = 40,
    scale_range: tuple[float, float] | None = (0.85, 1.15),
    centre: tuple[float, float] | None = None,
    min_gain: float = 0.15,
    min_score: float = 0.15,
    min_scale_gain: float = 0.1,
    min_spread: float = 0.18,
    agree_px: float = 2.0,
    sigma: float = 1.0,
) -> ShiftEstimate:
    """Estimate the depth-to-colour pixel map u_c = centre + s (u_d - centre) + (dx, dy) from edge alignment.

    Args:
        gray: (1, H, W), (B, 1, H, W) or a list of (1, H, W) intensity in [0, 1] (colour camera); B frames,
            best spread over a sequence.
        depth: the same layout, metres in the depth camera's pixel grid, 0 = no measurement.
        max_shift: largest |dx|, |dy| searched, in pixels.
        scale_range: (min, max) magnification searched; None fits a constant shift (s = 1).
        centre: reference point (x, y) of the map; the image centre when None (pass K's (cx, cy)).
        min_scale_gain: a scale other than 1 is kept only when its coarse NCC peak beats the best pure shift's by
            this relative margin (content such as shading can bias the edges by a pixel, which a free scale would
            absorb when the depth edges cover little of the image).
        min_spread: the scale is fitted only when the depth edges spread over the image: their edge-weighted
            position standard deviation is >= min_spread of the image side in x and in y (uniform: 0.29; the
            scale of one compact contour, e.g. a single object, is confounded with its texture).
        min_gain, min_score, agree_px: confidence rule, below.
        sigma: Gaussian smoothing of both edge maps, in pixels of the working resolution.

    Coarse to fine, on area-averaged images (fine level ~240 px high: 1/2 resolution at 640 x 480; coarse level
    half that): on the coarse level every scale of a 0.025 grid and every shift in the window is scored by the
    frame-averaged masked NCC (:func:`~torchtrack.data.edge_match.masked_ncc`), and the best scale is refined by a parabola through its
    neighbours; on the fine level shifts within +-3 fine pixels of the coarse one are scored again at that scale,
    and the peak is refined by parabolas in x and y.

    ``confident`` holds when all of these do: the map raises the frame-averaged edge NCC at zero shift by a
    relative gain, ``score - score_at_zero >= min_gain * score`` (registered depth: gain ~0); the edges then
    actually correlate, ``score >= min_score`` (scenes whose depth discontinuities are all holes, or hold a few
    edges only, score ~0.05); the peak is not on the border of the shift window or the scale range; and at
    least half of the frames put their own NCC peak within ``agree_px`` pixels of the averaged peak.

    Returns a :class:`ShiftEstimate` (full-resolution pixels).
    """
    g, d = _as_batch(gray, "gray"), _as_batch(depth, "depth")
    if g.shape != d.shape:
        raise ValueError(f"estimate_depth_shift: gray {tuple(g.shape)} and depth {tuple(d.shape)} differ in shape")
    B, _, H, W = d.shape
    if not 4 <= max_shift <= min(H, W) // 4:
        raise ValueError(f"estimate_depth_shift: max_shift={max_shift} must be in [4, {min(H, W) // 4}] for {H}x{W}")
    if scale_range is not None and not 0 < scale_range[0] < scale_range[1]:
        raise ValueError(f"estimate_depth_shift: scale_range must be (min, max) with 0 < min < max, got {scale_range}")
    c = ((W - 1) / 2, (H - 1) / 2) if centre is None else (float(centre[0]), float(centre[1]))
    rf = max(1, round(min(H, W) / 240))  # fine level ~240 px high, coarse level half that
    g_f, d_f = area_pool(g, d, rf)
    hi, lo = EdgeLevel(g_f, d_f, rf, sigma, c), EdgeLevel(*area_pool(g_f, d_f, 2), 2 * rf, sigma, c)
    m = max_shift // (2 * rf)
    scales = [1.0]
    if scale_range is not None and hi.spread() >= min_spread:
        n = max(2, round((scale_range[1] - scale_range[0]) / 0.025)) + 1
        scales = torch.linspace(*scale_range, n, device="cpu").tolist()  # host: a list of trial scales
    s, t0, on_border = _coarse_search(lo, scales, m, min_scale_gain)
    t, n_agree = _fine_shift(hi, s, t0, agree_px)
    score, score0 = hi.ncc_at_zero(s, t, 2 * m), hi.ncc_at_zero(1.0, (0.0, 0.0), 2 * m)
    gain = score - score0 >= min_gain * score and score >= min_score
    confident = gain and not on_border and 2 * n_agree >= B
    return ShiftEstimate(t[0], t[1], s, score, score0, bool(confident), c, B, n_agree, (H, W))


def _coarse_search(lo: EdgeLevel, scales: list[float], m: int, min_scale_gain: float) -> tuple[float, tuple, bool]:
    """Every scale, every shift in [-m, m]^2 on the coarse level -> (scale, shift (full-res px), peak on border).

    A scale other than 1 is kept only when its peak beats the pure shift's by ``min_scale_gain`` (relative);
    the best scale is refined by a parabola through its neighbours.
    """
    peaks = [surface_peak(lo.ncc(s, (0.0, 0.0), m).mean(0)) for s in scales]
    j = max(range(len(scales)), key=lambda i: peaks[i][2])
    one = min(range(len(scales)), key=lambda i: abs(scales[i] - 1.0))
    if abs(scales[one] - 1.0) < 1e-6 and peaks[j][2] < (1 + min_scale_gain) * peaks[one][2]:
        j, scales, peaks = 0, [1.0], [peaks[one]]  # Occam: a pure shift explains the edges about as well
    ix, iy, _ = peaks[j]
    on_border = not (0 < ix < 2 * m and 0 < iy < 2 * m) or (len(scales) > 1 and j in (0, len(scales) - 1))
    s = scales[j]
    if len(scales) > 1 and not on_border:
        s += (scales[1] - scales[0]) * parabola_offset(peaks[j - 1][2], peaks[j][2], peaks[j + 1][2])
    return s, (lo.r * (ix - m), lo.r * (iy - m)), on_border


def _fine_shift(hi: EdgeLevel, s: float, t0: tuple, agree_px: float, mf: int = 3) -> tuple[tuple[float, float], int]:
    """Residual shifts within +-mf fine pixels of t0 at scale s, parabolas in x and y -> (shift, frames agreeing)."""
    surf = hi.ncc(s, t0, mf)  # B,2mf+1,2mf+1
    S = surf.mean(0)
    ix, iy, _ = surface_peak(S)
    dx, dy = float(ix - mf), float(iy - mf)
    if 0 < ix < 2 * mf and 0 < iy < 2 * mf:
        dx += parabola_offset(float(S[iy, ix - 1]), float(S[iy, ix]), float(S[iy, ix + 1]))
        dy += parabola_offset(float(S[iy - 1, ix]), float(S[iy, ix]), float(S[iy + 1, ix]))
    own = surf.flatten(1).argmax(1)  # each frame's own peak
    near = ((own % (2 * mf + 1) - ix).abs() * hi.r <= agree_px) & ((own // (2 * mf + 1) - iy).abs() * hi.r <= agree_px)
    return (t0[0] + hi.r * dx, t0[1] + hi.r * dy), int(near.sum())


def _map_params(K: Tensor, est, where: str) -> tuple[float, float, float, float, float]:
    """(dx, dy, s, c_x, c_y) of a ShiftEstimate, or of (dx, dy[, scale]) about K's principal point."""
    if isinstance(est, ShiftEstimate):
        dx, dy, s, (c_x, c_y) = est.dx, est.dy, est.scale, est.centre
    elif len(est) in (2, 3):
        dx, dy, s = float(est[0]), float(est[1]), float(est[2]) if len(est) == 3 else 1.0
        c_x, c_y = float(K[..., 0, 2].flatten()[0]), float(K[..., 1, 2].flatten()[0])
    else:
        raise ValueError(f"{where}: need a ShiftEstimate, (dx, dy) or (dx, dy, scale), got {est!r}")
    if s <= 0:
        raise ValueError(f"{where}: scale must be positive, got {s}")
    return dx, dy, s, c_x, c_y


def depth_intrinsics(K: Tensor, est: ShiftEstimate | tuple[float, ...]) -> Tensor:
    """Depth intrinsics (..., 3, 3) that, with T_color_depth = I, realise a pixel map, from colour K (..., 3, 3).

    ``est``: a :class:`ShiftEstimate`, or (dx, dy) (a constant shift: colour pixel = depth pixel + (dx, dy)), or
    (dx, dy, scale) about K's principal point. From u_c = c + s (u_d - c) + t = cx + s (u_d - cx_d):
    fx_d = fx / s, cx_d = c_x + (cx - c_x - dx) / s (y alike); for s = 1 and c = (cx, cy), cx_d = cx - dx.
    """
    dx, dy, s, c_x, c_y = _map_params(K, est, "depth_intrinsics")
    K_d = K.clone()
    K_d[..., 0, 0], K_d[..., 1, 1] = K[..., 0, 0] / s, K[..., 1, 1] / s
    K_d[..., 0, 2] = c_x + (K[..., 0, 2] - c_x - dx) / s
    K_d[..., 1, 2] = c_y + (K[..., 1, 2] - c_y - dy) / s
    return K_d


def colour_intrinsics(K_depth: Tensor, est: ShiftEstimate | tuple[float, ...]) -> Tensor:
    """Colour intrinsics (..., 3, 3) that, with T_color_depth = I, realise a pixel map, from K_depth (..., 3, 3).

    The inverse of :func:`depth_intrinsics` (for when the given intrinsics are the depth camera's, as 7-Scenes'
    nominal Kinect values): fx_c = s fx_d, cx_c = c_x + s (cx_d - c_x) + dx (y alike); (dx, dy[, scale]) are
    about K_depth's principal point.
    """
    dx, dy, s, c_x, c_y = _map_params(K_depth, est, "colour_intrinsics")
    K_c = K_depth.clone()
    K_c[..., 0, 0], K_c[..., 1, 1] = K_depth[..., 0, 0] * s, K_depth[..., 1, 1] * s
    K_c[..., 0, 2] = c_x + s * (K_depth[..., 0, 2] - c_x) + dx
    K_c[..., 1, 2] = c_y + s * (K_depth[..., 1, 2] - c_y) + dy
    return K_c


def estimate_sequence_shift(
    load: Callable[[int], tuple[Tensor, Tensor]], length: int, K: Tensor, *, frames: int = 5, **kwargs
) -> ShiftEstimate | None:
    """:func:`estimate_depth_shift` on ``frames`` frames spread evenly over a sequence, centred on K's (cx, cy).

    ``load(i)`` -> (rgb (3, H, W) in [0, 1], depth (1, H, W) metres) of frame i of ``length``; K: (3, 3) colour
    intrinsics. Returns None when the images are too small for the search window (min side < 4 max_shift).
    """
    idx = sorted({int(i) for i in np.linspace(0, length - 1, min(frames, length)).round()})
    rgb, depth = zip(*(load(i) for i in idx), strict=True)
    H, W = depth[0].shape[-2:]
    if min(H, W) < 4 * kwargs.get("max_shift", 40):
        return None
    gray = [rgb_to_grayscale(c) for c in rgb]  # as FrameBatch.gray
    return estimate_depth_shift(gray, list(depth), centre=(float(K[0, 2]), float(K[1, 2])), **kwargs)


def resolve_depth_alignment(
    mode: str | Sequence[float], K: Tensor, load: Callable[[int], tuple[Tensor, Tensor]], length: int, name: str = ""
) -> tuple[ShiftEstimate | None, bool]:
    """A sequence's ``depth_alignment`` option -> (estimate or None, apply it).

    mode: "none" -> (None, False); "auto" -> :func:`estimate_sequence_shift`, applied when confident and moving
    some pixel by >= MIN_APPLIED_SHIFT_PX (None when the images are too small or a frame cannot be read: the read
    error is raised again where the frame is used); (dx, dy) or (dx, dy, scale) -> that map, applied.
    K: (3, 3) colour intrinsics; load(i) -> (rgb (3, H, W), depth (1, H, W)); name: for messages.
    """
    if isinstance(mode, str):
        if mode not in ("auto", "none"):
            raise ValueError(f"{name}: depth_alignment must be 'auto', 'none' or (dx, dy[, scale]), got {mode!r}")
        if mode == "none":
            return None, False
        try:
            est = estimate_sequence_shift(load, length, K)
        except DataError as e:
            log.warning("%s: depth alignment skipped: %s", name, e)
            return None, False
        if est is None:
            log.info("%s: depth alignment skipped: images too small to estimate", name)
            return None, False
        apply = est.confident and est.max_displacement() >= MIN_APPLIED_SHIFT_PX
    else:
        v = tuple(float(x) for x in mode)
        if len(v) not in (2, 3) or (len(v) == 3 and v[2] <= 0):
            raise ValueError(f"{name}: depth_alignment must be (dx, dy) or (dx, dy, scale > 0), got {mode!r}")
        c = (float(K[0, 2]), float(K[1, 2]))
        est, apply = (
            ShiftEstimate(*v[:2], v[2] if len(v) == 3 else 1.0, math.nan, math.nan, True, c, 0, 0, (0, 0)),
            True,
        )
    log.info(
        "%s: depth-to-colour map colour = c + %.4f (depth - c) + (%+.2f, %+.2f) px, c = (%.1f, %.1f); edge NCC "
        "%.3f -> %.3f over %d frames, confident %s: %s",
        name, est.scale, est.dx, est.dy, *est.centre, est.score_at_zero, est.score, est.frames, est.confident,
        "applied as depth intrinsics" if apply else "not applied (depth used as registered)",
    )  # fmt: skip
    return est, apply
