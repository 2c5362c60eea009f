"""The LK iteration on windows of a packed pyramid: sampling, template, inverse-compositional and Newton steps.

The pure-torch reference of the compiled operator's inner loop (csrc/lk.cpp); :mod:`torchtrack.image.lk` drives it
over pyramid levels and chunks of points. Per point and level:
- template, once: the w x w window of the previous image around the point (bilinear, as all windows), its
  Scharr gradients g and the gradient matrix H = g g^T (degenerate, as OpenCV, when its smallest eigenvalue
  is below min_eig); every level's in one call (they depend on the start point only);
- iterations: one integer (w+1)^2 patch of the next image per point, gathered by a single ``index_select``
  over rows of the packed pyramid buffer, interpolated by two lerps (all window pixels share one pair of
  bilinear weights), and the inverse-compositional step H^-1 g (T - J); from iteration ``ic_iters`` on, Newton
  steps on the same normal equations (module docstring of :mod:`torchtrack.image.lk`).
All points of all images form one flat list, compacted as points stop (per-point early stop); there is no Python loop
over points. Every tensor made here follows the pyramid's device.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.image.pyramid import Pyramid

_EXACT_F32 = 2**24  # float32 index arithmetic is exact below this


class Sampler:
    """Windows of one pyramid: (n, C, m, m) patches gathered with one 1-D index_select each.

    It keeps the pyramid's buffer and layout, not the pyramid: the pyramid keeps its samplers (``Pyramid.samplers``),
    and a reference back would make each frame's pyramid a reference cycle, freed only by Python's full garbage
    collection, which a process with many long-lived objects runs rarely (the long run's memory grew by the
    pyramids waiting for it: experiments/bench/bench_long_run.py).
    """

    def __init__(self, pyr: Pyramid, window: int):
        self.window, self.r, self.c = window, window // 2, pyr.channels
        self.flat, self.row_stride, self.plane, self.pad = pyr.flat, pyr.stride, pyr.plane, pyr.pad
        self.sizes = [pyr.size(level) for level in range(pyr.levels)]
        self.dtype = torch.float32 if pyr.flat.numel() < _EXACT_F32 else torch.float64
        self.device = pyr.flat.device
        self.stride = torch.tensor([1.0, float(pyr.stride)], dtype=self.dtype, device=self.device)
        self.base_table = ((pyr.row_start + pyr.pad) * pyr.stride + pyr.pad).to(
            self.device, self.dtype
        )  # L,B: level px (0, 0)
        self._rows: dict[int, tuple[Tensor, Tensor]] = {}

    @staticmethod
    def of(pyr: Pyramid, window: int) -> Sampler:
        """The sampler of a pyramid, built once and kept with it (the pyramid is used by two LK calls at least)."""
        if window not in pyr.samplers:
            pyr.samplers[window] = Sampler(pyr, window)
        return pyr.samplers[window]

    def rows(self, size: int) -> tuple[Tensor, Tensor]:
        """A sliding view (len, size) of the flat buffer (row i = flat[i : i + size]) and the (C * size,) int32
        offsets of the rows of a size x size patch whose centre pixel is at offset 0."""
        if size not in self._rows:
            s, h, flat = self.row_stride, (size - 1) // 2, self.flat
            rows = torch.arange(size, dtype=torch.int32, device=self.device) * s - h * (s + 1)
            chan = torch.arange(self.c, dtype=torch.int32, device=self.device)[:, None] * self.plane
            view = flat.as_strided((flat.numel() - size + 1, size), (1, 1))
            self._rows[size] = (view, (chan + rows[None, :]).reshape(-1))
        return self._rows[size]

    def bounds(self, level: int) -> tuple[Tensor, Tensor]:
        """Window centres q (level px) can be sampled, gradients included, iff lo <= floor(q) <= hi."""
        h, w = self.sizes[level]
        lo, hi = self.r + 1 - self.pad, self.pad - self.r - 3
        lo_hi = torch.tensor([[float(lo)] * 2, [w + hi, h + hi]], dtype=torch.float32, device=self.device)
        return lo_hi[0], lo_hi[1]  # (2,) each: a fast clamp

    def base(self, level: int, image_index: Tensor) -> Tensor:
        return self.base_table[level].index_select(0, image_index)

    def gather(self, start: Tensor, size: int) -> Tensor:
        """(n, C, size, size) patches centred at flat indices start (n,) (any dtype holding integers)."""
        view, offsets = self.rows(size)  # one index per patch row: 2x faster than one per pixel
        idx = (start.to(torch.int32).view(-1, 1) + offsets).view(-1)
        return view.index_select(0, idx).view(start.shape[0], self.c, size, size)

    def bilinear(self, q: Tensor, base: Tensor, extra: int) -> Tensor:
        """(n, C, w + 2 extra, w + 2 extra) windows bilinearly sampled at sub-pixel centres q (n, 2)."""
        n = q.shape[0]
        fl = q.floor()
        fr = q - fl
        patch = self.gather(torch.addmv(base, fl.to(self.dtype), self.stride), self.window + 1 + 2 * extra)
        jy = torch.lerp(patch[:, :, :-1], patch[:, :, 1:], fr[:, 1].view(n, 1, 1, 1))
        return torch.lerp(jy[..., :-1], jy[..., 1:], fr[:, 0].view(n, 1, 1, 1))


_GRAD_SCALE = 13.0 / 32.0  # _gradients returns Scharr derivatives (per pixel) divided by this
_ADJ = torch.tensor([3, 1, 2, 0], device="cpu")  # flat 2x2 [a, b, c, d] -> adjugate [d, -b, -c, a] (with _ADJ_SIGN)
_ADJ_SIGN = torch.tensor([1.0, -1.0, -1.0, 1.0], device="cpu")


def _gradients(patch: Tensor, out: Tensor) -> None:
    """Scharr derivatives [d/dx, d/dy] of patches (n, C, m, m) on their inner window, into out (n, 2, C, m-2, m-2);
    unscaled: [-3 0 3; -10 0 10; -3 0 3] / 13 (the per-pixel derivative is _GRAD_SCALE times this)."""
    dx = patch[..., 2:] - patch[..., :-2]
    dy = patch[..., 2:, :] - patch[..., :-2, :]
    torch.lerp(dx[..., 1:-1, :], dx[..., :-2, :] + dx[..., 2:, :], 3.0 / 13.0, out=out[:, 0])
    torch.lerp(dy[..., 1:-1], dy[..., :-2] + dy[..., 2:], 3.0 / 13.0, out=out[:, 1])


def _inverse_2x2(m: Tensor, scale: Tensor | float = 1.0) -> tuple[Tensor, Tensor]:
    """Inverses (n, 2, 2) of 2x2 matrices m (n, 2, 2), times scale, and their determinants (n,)."""
    n = m.shape[0]
    adj = m.reshape(n, 4).index_select(1, _ADJ.to(m.device)).mul_(_ADJ_SIGN.to(m.device))  # no copy on the CPU
    det = torch.linalg.vecdot(m[:, 0], adj[:, ::2])
    return adj.mul_((scale / det).view(n, 1)).view(n, 2, 2), det


def template(sampler: Sampler, x: Tensor, base: Tensor, min_eig: float):
    """Template data at sub-pixel points x (n, 2) (level pixels), once per point and level.

    Returns g (n, 2, C*K) unscaled gradients, tg = T @ g^T (n, 1, 2), h_inv (n, 2, 2) the inverse of the
    gradient matrix H = g @ g^T divided by _GRAD_SCALE (so that h_inv @ (tg - J @ g^T) is the LK step in
    pixels), det(H) (n,), and a degenerate mask (n,): smallest eigenvalue below min_eig in OpenCV's units.
    """
    patch = sampler.bilinear(x, base, extra=1)  # the window and a 1-pixel rim for the gradients
    n, c, m = patch.shape[:3]
    win = patch.new_empty(n, 3, c, m - 2, m - 2)  # [gx, gy, T]: one bmm gives the Hessian and g @ T
    _gradients(patch, win)
    win[:, 2] = patch[..., 1:-1, 1:-1]
    win = win.view(n, 3, -1)
    g = win[:, :2]
    a = torch.bmm(g, win.mT)  # n,2,3: [g g^T | g T]
    h = a[:, :, :2]
    a11, a12, a22 = h[:, 0, 0], h[:, 0, 1], h[:, 1, 1]
    lam = 0.5 * (a11 + a22 - torch.sqrt((a11 - a22) ** 2 + 4.0 * a12 * a12))
    # OpenCV's minEig: intensities on 0..255, 1/32-scaled Scharr (1/1024 on products), per window pixel.
    degenerate = lam * (_GRAD_SCALE**2 * 255.0**2 / 1024.0 / sampler.window**2) < min_eig
    h_inv, det = _inverse_2x2(h, 1.0 / _GRAD_SCALE)
    degenerate |= ~(det > 0.0)
    return g, a[:, :, 2].reshape(n, 1, 2), h_inv, det, degenerate


def _newton(r: Tensor, step: Tensor, g_t: Tensor, h_det: Tensor, jy: Tensor, patch: Tensor, fx: Tensor) -> Tensor:
    """Newton step on the normal equations R(q) = (T - J(q)) @ g^T = r (n, 1, 2), whose inverse-compositional
    step is ``step`` = r @ h_inv: M^-1 r with M = -dR/dq = g @ dJ/dq^T (n, 2, 2) (g_t = g^T), from the exact derivatives of
    the bilinear window: d/dx from the y-interpolated patch jy (n, C, w, w+1), d/dy from the raw patch
    (n, C, w+1, w+1). Where H^-1 M is far from the identity (det < 0.01; H = g @ g^T has determinant h_det)
    the step stays ``step``."""
    n = r.shape[0]
    djx = jy[..., 1:] - jy[..., :-1]
    dpy = patch[:, :, 1:] - patch[:, :, :-1]
    djy = torch.lerp(dpy[..., :-1], dpy[..., 1:], fx)
    m_t = torch.cat([torch.bmm(djx.view(n, 1, -1), g_t), torch.bmm(djy.view(n, 1, -1), g_t)], 1)  # M^T (unscaled)
    m_t_inv, det = _inverse_2x2(m_t)
    newton = torch.bmm(r, m_t_inv).view(n, 2)
    ok = det > (0.01 * _GRAD_SCALE) * h_det  # det(H^-1 M) > 0.01, with the gradients' scale
    return torch.where(ok.view(n, 1), newton, step)


def iterate(sampler, level, q, g, tg, h_inv, h_det, base, *, iters, eps, ic_iters):
    """LK iterations with per-point early stop for window centres q (P, 2) in level pixels.

    A point stops when its update is at most eps (converged), or, in the Newton phase, when its update
    is not at least halved (not converging), or after iters iterations. Windows are sampled inside the
    padded image; a point that leaves it stops (not converged). A stopped point stays in the batch, frozen,
    until half of the batch has stopped; then the batch is compacted (fewer tensor operations than compacting
    at every stop, for the same results).
    Returns the final centres (P, 2) and converged flags (P,).
    """
    lo, hi = sampler.bounds(level)
    q_out, conv_out = q.clone(), torch.zeros(q.shape[0], dtype=torch.bool, device=q.device)
    if q.shape[0] == 0:
        return q_out, conv_out
    ids = torch.arange(q.shape[0], device=q.device)
    live, conv_all = torch.ones_like(conv_out), torch.zeros_like(conv_out)
    size, stride, eps2, d2_prev, g_t = sampler.window + 1, sampler.stride, eps * eps, None, g.mT
    exact = sampler.dtype == q.dtype  # else float64 index arithmetic (buffers of 2^24 elements and more)
    for j in range(iters):
        n = q.shape[0]
        fl0 = q.floor()
        fl = fl0.clamp(lo, hi)
        f = (q - fl).view(n, 2, 1, 1, 1)  # fractions (x, y)
        patch = sampler.gather(torch.addmv(base, fl if exact else fl.to(base.dtype), stride), size)  # n,C,w+1,w+1
        jy = torch.lerp(patch[:, :, :-1], patch[:, :, 1:], f[:, 1])
        win = torch.lerp(jy[..., :-1], jy[..., 1:], f[:, 0])
        r = torch.baddbmm(tg, win.view(n, 1, -1), g_t, alpha=-1.0)  # (T - J) @ g^T
        delta = torch.bmm(r, h_inv).view(n, 2)  # inverse-compositional step (h_inv is symmetric)
        if j >= ic_iters:
            delta = _newton(r, delta, g_t, h_det, jy, patch, f[:, 0])
        q = torch.where(live.view(n, 1), q + delta, q)
        d2 = torch.linalg.vecdot(delta, delta)
        conv = d2 <= eps2
        stop = conv | (fl != fl0).any(-1)  # converged, or left the sampleable area
        if j > ic_iters:
            stop |= d2 > 0.25 * d2_prev  # Newton converges fast: a step not halved means no convergence
        d2_prev = d2
        stop &= live
        conv_all |= stop & conv
        live &= ~stop
        n_live = int(live.count_nonzero())
        if n_live == 0 or j == iters - 1:
            break
        if 2 * n_live <= n:
            q_out[ids] = q
            conv_out[ids] = conv_all
            keep = live.nonzero().squeeze(1)
            ids, q, base, d2_prev, h_det = ids[keep], q[keep], base[keep], d2[keep], h_det[keep]
            live, conv_all = torch.ones_like(keep, dtype=torch.bool), torch.zeros_like(keep, dtype=torch.bool)
            g, tg, h_inv = g.index_select(0, keep), tg.index_select(0, keep), h_inv.index_select(0, keep)
            g_t = g.mT
    q_out[ids] = q
    conv_out[ids] = conv_all
    return q_out, conv_out


def window_residual(s_prev: Sampler, s_next: Sampler, x0: Tensor, x1: Tensor, img: Tensor) -> Tensor:
    """Mean |J - T| over the final level-0 windows (the objective LK minimised), (P,)."""
    t = s_prev.bilinear(x0, s_prev.base(0, img), extra=0)
    j = s_next.bilinear(x1, s_next.base(0, img), extra=0)
    return (j - t).abs().flatten(1).mean(-1)
