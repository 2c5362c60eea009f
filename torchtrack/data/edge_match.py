"""Edge maps of RGB-D frames and their masked normalised cross-correlation (NCC) over shifts, via FFT.

Building blocks of :mod:`torchtrack.data.alignment`: a depth-discontinuity map (relative depth gradient, holes
excluded by a support mask), the smoothed intensity gradient magnitude, masked NCC of one with the other at every
integer shift (Padfield's masked FFT correlation), and a pyramid level that resamples the depth edges by a
magnification-plus-shift map before correlating.

References: J. P. Lewis, "Fast normalized cross-correlation", Vision Interface 1995; D. Padfield, "Masked object
registration in the Fourier domain", IEEE TIP 2012.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from kornia.filters import gaussian_blur2d, spatial_gradient
from torch import Tensor

# ----------------------------------------------------------------------------------------------- edge maps


def _gaussian_blur(x: Tensor, sigma: float) -> Tensor:
    """(B, 1, H, W) -> Gaussian blur (kernel radius 3 sigma), replicate border."""
    k = 2 * max(1, math.ceil(3 * sigma)) + 1
    return gaussian_blur2d(x, (k, k), (sigma, sigma), border_type="replicate")


def _gradient_norm(x: Tensor) -> Tensor:
    """(B, 1, H, W) -> |grad x| by central differences (kornia's "diff" gradient), 0 on the border."""
    gx, gy = spatial_gradient(x, "diff").unbind(2)
    out = torch.zeros_like(x)
    out[..., 1:-1, 1:-1] = torch.sqrt(gx * gx + gy * gy)[..., 1:-1, 1:-1]
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


def parabola_offset(minus: float, centre: float, plus: float, limit: float = 0.5) -> float:
    """Offset of the vertex of the parabola through samples at -1, 0, +1 from the middle one, clamped to +-limit."""
    curv = minus - 2 * centre + plus
    if curv >= 0:  # not a maximum: keep the best sample
        return 0.0 if centre >= max(minus, plus) else (limit if plus > minus else -limit)
    return max(-limit, min(limit, 0.5 * (minus - plus) / curv))


# ----------------------------------------------------------------------------------------------- levels


def area_pool(gray: Tensor, depth: Tensor, r: int) -> tuple[Tensor, Tensor]:
    """Divide the resolution by r with r x r area averages; depth only where the whole block is measured."""
    if r == 1:
        return gray, depth
    full = -F.max_pool2d(-(depth > 0).to(depth.dtype), r)
    return F.avg_pool2d(gray, r), F.avg_pool2d(depth, r) * full


class EdgeLevel:
    """Edge maps of B frames on one level (1/r resolution), scoring pixel maps u_c = c + s (u_d - c) + t.

    gray, depth: (B, 1, h, w) already pooled by r (:func:`area_pool`); centre c and map shifts t are in
    full-resolution pixels, residual NCC shifts and border widths in level pixels.
    """

    def __init__(self, gray: Tensor, depth: Tensor, r: int, sigma: float, centre: tuple[float, float]) -> None:
        self.r = r
        edges, support = depth_edges(depth, sigma)
        self.depth_maps = torch.cat([edges, support], 1)  # B,2,h,w
        self.intensity = intensity_edges(gray, sigma)[:, 0]
        self.spectra = search_spectra(self.intensity)
        self.centre = ((centre[0] - (r - 1) / 2) / r, (centre[1] - (r - 1) / 2) / r)  # pixel centres of the blocks
        h, w = depth.shape[-2:]
        self.ys, self.xs = torch.meshgrid(
            torch.arange(h, dtype=depth.dtype, device=depth.device),
            torch.arange(w, dtype=depth.dtype, device=depth.device),
            indexing="ij",
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

    def spread(self) -> float:
        """Edge-weighted standard deviation of the depth edges' positions over all frames, as a fraction of the
        image side (the smaller of x and y); ~0.29 for edges spread uniformly, ~0.1 for one central object."""
        w = (self.depth_maps[:, 0] * self.depth_maps[:, 1]).sum(0)  # h,w
        n = w.sum().clamp_min(1e-12)
        sx = ((w * self.xs).sum() / n, (w * self.xs**2).sum() / n)
        sy = ((w * self.ys).sum() / n, (w * self.ys**2).sum() / n)
        h, wd = self.xs.shape
        return min(float(sx[1] - sx[0] ** 2) ** 0.5 / wd, float(sy[1] - sy[0] ** 2) ** 0.5 / h)

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


def surface_peak(S: Tensor) -> tuple[int, int, float]:
    """(2m+1, 2m+1) surface -> (ix, iy, value) of its maximum."""
    k = int(S.argmax())
    return k % S.shape[-1], k // S.shape[-1], float(S.flatten()[k])
