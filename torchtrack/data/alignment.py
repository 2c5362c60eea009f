"""Depth-to-colour registration by edge alignment, for depth that is not registered to colour.

Some sequences (Microsoft 7-Scenes) store depth in the depth camera's own pixel grid. With the two cameras a few
centimetres apart, looking the same way, the map from depth pixels to colour pixels is, up to a parallax of a few
pixels, a magnification about the principal point plus a shift (different focal lengths, offset optical axes):

    u_c = c + s (u_d - c) + t        (u: pixel (x, y), c: a reference point, s: scale, t = (dx, dy): shift at c)

With T_color_depth = identity this is exactly a depth intrinsics matrix: back-projecting u_d through
K_depth = (fx / s, fy / s, cx_d, cy_d) and projecting through the colour K gives u_c when
cx_d = c_x + (cx - c_x - dx) / s (the same for y); for s = 1 and c = (cx, cy), cx_d = cx - dx. The tracker's
front end then registers depth with :func:`torchtrack.geometry.warp_depth` (see :func:`depth_intrinsics`).

Estimation: a depth-discontinuity map (relative depth gradient, holes excluded by a support mask) is matched to
the smoothed intensity gradient magnitude by masked normalised cross-correlation (NCC) over integer shifts, via
FFT, in a grid of tiles; each tile's NCC surface is averaged over the frames, its peak refined to sub-pixel by a
parabola. The map (s, t) is fitted to the tile shifts by least squares (iteratively dropping outlier tiles) and
accepted only when warping the depth edges by it clearly raises their NCC with the intensity edges at zero shift.

References: J. P. Lewis, "Fast normalized cross-correlation", Vision Interface 1995; D. Padfield, "Masked object
registration in the Fourier domain", IEEE TIP 2012 (masked NCC via FFT).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

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


# ----------------------------------------------------------------------------------------------- edge maps


def _gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """(B, 1, H, W) -> separable Gaussian blur, replicate border."""
    r = max(1, math.ceil(3 * sigma))
    t = torch.arange(-r, r + 1, dtype=x.dtype, device=x.device)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1))


def _gradient_norm(x: Tensor) -> Tensor:
    """(B, 1, H, W) -> |grad x| by central differences, 0 on the border."""
    out = torch.zeros_like(x)
    gx = 0.5 * (x[..., 1:-1, 2:] - x[..., 1:-1, :-2])
    gy = 0.5 * (x[..., 2:, 1:-1] - x[..., :-2, 1:-1])
    out[..., 1:-1, 1:-1] = torch.sqrt(gx * gx + gy * gy)
    return out


def intensity_edges(gray: Tensor, sigma: float = 1.5) -> Tensor:
    """Gradient magnitude of the Gaussian-smoothed intensity: gray (B, 1, H, W) in [0, 1] -> (B, 1, H, W)."""
    return _gradient_norm(_gaussian_blur(gray, sigma))


def depth_edges(depth: Tensor, sigma: float = 1.5, low: float = 0.02, high: float = 0.06) -> tuple[Tensor, Tensor]:
    """Depth-discontinuity map and its support: depth (B, 1, H, W) metres, 0 = none.

    The edge strength is the relative depth gradient |grad z| / z (a 10 cm step reads alike at 1 m and at 4 m
    after dividing by z... up to the step's relative size), ramped from 0 at ``low`` to 1 at ``high`` per pixel:
    Kinect disparity quantisation makes relative steps of ~1% on slanted surfaces, true discontinuities
    are far larger. Smoothed like the intensity edges. Holes carry no edge: a pixel is supported only when its
    3x3 neighbourhood is fully measured (Kinect holes lie on the shadow side of occlusion boundaries, so
    their borders are not colour edges at the same place).

    Returns (edges (B, 1, H, W), support (B, 1, H, W) float in {0, 1}).
    """
    valid = (depth > 0).to(depth.dtype)
    support = -F.max_pool2d(-valid, 3, stride=1, padding=1)  # 3x3 erosion
    rel = _gradient_norm(depth) / depth.clamp_min(1e-6)
    edges = _gaussian_blur(((rel - low) / (high - low)).clamp(0.0, 1.0) * support, sigma)
    return edges, support


# ----------------------------------------------------------------------------------------------- masked NCC


def search_spectra(search: Tensor) -> Tensor:
    """(N, h, w) search images -> (N, 2, h, w // 2 + 1) spectra of search and search^2, for :func:`masked_ncc`."""
    return torch.fft.rfft2(torch.stack([search, search * search], dim=1))


def masked_ncc(template: Tensor, mask: Tensor, search: Tensor, max_shift: int) -> Tensor:
    """Masked NCC of a template with a search image at every integer shift, via FFT.

    template, mask: (N, h, w); mask in {0, 1} and zero within ``max_shift`` = m of the border (so that the FFT's
    circular correlation never wraps). search: (N, h, w), or its :func:`search_spectra` (N, 2, h, w // 2 + 1).
    Returns (N, 2m+1, 2m+1): entry [n, m + dy, m + dx] is the NCC over the mask of template(p) with
    search(p + (dx, dy)); 0 where either side has no variance.
    """
    h, w = template.shape[-2:]
    m = max_shift
    X = search_spectra(search) if search.dim() == 3 else search
    n = mask.sum(dim=(-2, -1), keepdim=True).clamp_min(1.0)
    t = (template - (template * mask).sum(dim=(-2, -1), keepdim=True) / n) * mask  # zero mean on the mask
    A = torch.fft.rfft2(torch.stack([t, mask], dim=1)).conj()  # N,2,h,w//2+1
    c = torch.fft.irfft2(torch.stack([A[:, 0] * X[:, 0], A[:, 1] * X[:, 0], A[:, 1] * X[:, 1]], dim=1), s=(h, w))
    iy = torch.arange(-m, m + 1, device=c.device) % h
    ix = torch.arange(-m, m + 1, device=c.device) % w
    c = c[:, :, iy][:, :, :, ix]  # N,3,2m+1,2m+1: sum t*S_s, sum M*S_s, sum M*S_s^2
    var_s = (c[:, 2] - c[:, 1] ** 2 / n.view(-1, 1, 1)).clamp_min(0.0)
    var_t = (t * t).sum(dim=(-2, -1)).view(-1, 1, 1)
    denom = torch.sqrt(var_t * var_s)
    return torch.where(denom > 1e-12, c[:, 0] / denom.clamp_min(1e-12), torch.zeros_like(denom))


def _parabola_offset(minus: float, centre: float, plus: float, limit: float = 0.5) -> float:
    """Offset of the vertex of the parabola through samples at -1, 0, +1 from the middle one, clamped to +-limit."""
    curv = minus - 2 * centre + plus
    if curv >= 0:  # not a maximum: keep the best sample
        return 0.0 if centre >= max(minus, plus) else (limit if plus > minus else -limit)
    return max(-limit, min(limit, 0.5 * (minus - plus) / curv))


# ----------------------------------------------------------------------------------------------- the map


def _as_batch(x: Tensor | Sequence[Tensor], name: str) -> Tensor:
    if isinstance(x, Tensor):
        x = x[None] if x.dim() == 3 else x
    else:
        x = torch.stack([torch.as_tensor(f) for f in x])
    if x.dim() != 4 or x.shape[1] != 1:
        raise ValueError(f"estimate_depth_shift: {name} must be (1, H, W), (B, 1, H, W) or a list of (1, H, W)")
    return x.float()


def _pool2(gray: Tensor, depth: Tensor) -> tuple[Tensor, Tensor]:
    """Halve the resolution by 2x2 area averages; depth only where the whole block is measured (no hole leaks)."""
    full = -F.max_pool2d(-(depth > 0).to(depth.dtype), 2)
    return F.avg_pool2d(gray, 2), F.avg_pool2d(depth, 2) * full


class _Level:
    """Edge maps of B frames at 1/r of the full resolution (gray, depth: (B, 1, h, w) already pooled by r)."""

    def __init__(self, gray: Tensor, depth: Tensor, r: int, sigma: float, centre: tuple[float, float]) -> None:
        self.r = r
        edges, support = depth_edges(depth, sigma)
        self.depth_maps = torch.cat([edges, support], 1)  # B,2,h,w
        self.intensity = intensity_edges(gray, sigma)[:, 0]
        self.spectra = search_spectra(self.intensity)
        self.centre = ((centre[0] - (r - 1) / 2) / r, (centre[1] - (r - 1) / 2) / r)  # pixel centres of the blocks
        h, w = depth.shape[-2:]
        self.ys, self.xs = torch.meshgrid(
            torch.arange(h, dtype=depth.dtype), torch.arange(w, dtype=depth.dtype), indexing="ij"
        )

    def _warped(self, s: float, t: tuple[float, float], m: int) -> tuple[Tensor, Tensor]:
        """Depth edges and support resampled into the colour grid by the map (s, t in full-resolution pixels):
        out(u) = in(centre + (u - centre - t) / s), bilinear; support kept where fully supported; border m cleared."""
        (c_x, c_y), (h, w) = self.centre, self.xs.shape
        u = c_x + (self.xs - c_x - t[0] / self.r) / s
        v = c_y + (self.ys - c_y - t[1] / self.r) / s
        grid = torch.stack([2 * u / (w - 1) - 1, 2 * v / (h - 1) - 1], -1)
        x = self.depth_maps
        x = F.grid_sample(x, grid.expand(len(x), h, w, 2), mode="bilinear", padding_mode="zeros", align_corners=True)
        D, M = x[:, 0], (x[:, 1] > 0.999).to(x.dtype)
        M[:, :m], M[:, h - m :], M[:, :, :m], M[:, :, w - m :] = 0, 0, 0, 0
        return D, M

    def ncc(self, s: float, t: tuple[float, float], m: int) -> Tensor:
        """(B, 2m+1, 2m+1) NCC surfaces of the depth edges after the map (s, t), residual shifts in level px."""
        return masked_ncc(*self._warped(s, t, m), self.spectra, m)

    def ncc_at_zero(self, s: float, t: tuple[float, float], m: int) -> float:
        """Frame-averaged NCC of the mapped depth edges with the intensity edges at the same pixel."""
        D, M = self._warped(s, t, m)
        n = M.sum((-2, -1), keepdim=True).clamp_min(1.0)
        a = (D - (D * M).sum((-2, -1), keepdim=True) / n) * M
        b = (self.intensity - (self.intensity * M).sum((-2, -1), keepdim=True) / n) * M
        ncc = (a * b).sum((-2, -1)) / ((a * a).sum((-2, -1)) * (b * b).sum((-2, -1))).sqrt().clamp_min(1e-12)
        return float(ncc.mean())


def _peak(S: Tensor) -> tuple[int, int, float]:
    """(2m+1, 2m+1) surface -> (ix, iy, value) of its maximum."""
    k = int(S.argmax())
    return k % S.shape[-1], k // S.shape[-1], float(S.flatten()[k])


def estimate_depth_shift(
    gray: Tensor | Sequence[Tensor],
    depth: Tensor | Sequence[Tensor],
    *,
    max_shift: int = 40,
    scale_range: tuple[float, float] | None = (0.85, 1.15),
    centre: tuple[float, float] | None = None,
    min_gain: float = 0.15,
    min_scale_gain: float = 0.1,
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
        min_gain, agree_px: confidence rule, below.
        sigma: Gaussian smoothing of both edge maps, in pixels of the working resolution.

    Coarse to fine: at 1/4 resolution every scale of a 0.025 grid and every shift in the window is scored by the
    frame-averaged masked NCC (:func:`masked_ncc`), and the best scale is refined by a parabola through its
    neighbours; at 1/2 resolution shifts within +-6 px of the coarse one are scored again at that scale, and the
    peak is refined by parabolas in x and y.

    ``confident`` holds when all three do: the map raises the frame-averaged edge NCC at zero shift by a relative
    gain, ``score - score_at_zero >= min_gain * score`` with ``score > 0`` (registered depth: gain ~0); the peak
    is not on the border of the shift window or the scale range; and at least half of the frames put their own
    NCC peak within ``agree_px`` pixels of the averaged peak.

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
    # coarse: 1/4 resolution, scales on a grid, the whole shift window; parabola in s through the best three
    g2, d2 = _pool2(g, d)
    lo, m, step = _Level(*_pool2(g2, d2), 4, sigma, c), max_shift // 4, 0.025
    n_s = 0 if scale_range is None else max(2, round((scale_range[1] - scale_range[0]) / step))
    scales = torch.linspace(scale_range[0], scale_range[1], n_s + 1).tolist() if n_s else [1.0]
    peaks = [_peak(lo.ncc(s, (0.0, 0.0), m).mean(0)) for s in scales]
    j = max(range(len(scales)), key=lambda i: peaks[i][2])
    one = min(range(len(scales)), key=lambda i: abs(scales[i] - 1.0))
    if abs(scales[one] - 1.0) < 1e-6 and peaks[j][2] < (1 + min_scale_gain) * peaks[one][2]:
        j, n_s, scales, peaks = 0, 0, [1.0], [peaks[one]]  # Occam: a pure shift explains the edges about as well
    t0 = (4.0 * (peaks[j][0] - m), 4.0 * (peaks[j][1] - m))
    on_border = not (0 < peaks[j][0] < 2 * m and 0 < peaks[j][1] < 2 * m) or (n_s and j in (0, n_s))
    s = scales[j]
    if n_s and not on_border:
        s += (scales[1] - scales[0]) * _parabola_offset(peaks[j - 1][2], peaks[j][2], peaks[j + 1][2])
    # fine: 1/2 resolution, residual shifts within +-6 px of the coarse shift, parabolas in x and y
    hi, mf = _Level(g2, d2, 2, sigma, c), 3
    surf = hi.ncc(s, t0, mf)  # B,2mf+1,2mf+1
    ix, iy, _ = _peak(surf.mean(0))
    S = surf.mean(0)
    dx, dy = float(ix - mf), float(iy - mf)
    if 0 < ix < 2 * mf and 0 < iy < 2 * mf:
        dx += _parabola_offset(float(S[iy, ix - 1]), float(S[iy, ix]), float(S[iy, ix + 1]))
        dy += _parabola_offset(float(S[iy - 1, ix]), float(S[iy, ix]), float(S[iy + 1, ix]))
    t = (t0[0] + 2 * dx, t0[1] + 2 * dy)
    own = surf.flatten(1).argmax(1)  # each frame's own peak
    agree = ((own % (2 * mf + 1) - ix).abs() * 2 <= agree_px) & ((own // (2 * mf + 1) - iy).abs() * 2 <= agree_px)
    score, score0 = hi.ncc_at_zero(s, t, 2 * m), hi.ncc_at_zero(1.0, (0.0, 0.0), 2 * m)
    confident = score > 0 and score - score0 >= min_gain * score and not on_border and 2 * int(agree.sum()) >= B
    return ShiftEstimate(t[0], t[1], s, score, score0, bool(confident), c, B, int(agree.sum()), (H, W))


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
    gray = [0.299 * c[0:1] + 0.587 * c[1:2] + 0.114 * c[2:3] for c in rgb]  # as FrameBatch.gray
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
