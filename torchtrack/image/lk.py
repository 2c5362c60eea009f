"""Batched pyramidal Lucas–Kanade (Bouguet) and template inverse matching, paper §III-C, eq. (10).

Translation LK, per point and pyramid level (coarse to fine, the result of a level seeding the next):
- template, once: the w x w window of the previous image around the point (bilinear, as all windows), its
  Scharr gradients g and the gradient matrix H = g g^T (degenerate, as OpenCV, when its smallest eigenvalue
  is below min_eig); every level's in one call (they depend on the start point only); points degenerate at the
  finest level are not tracked at all;
- iterations: one integer (w+1)^2 patch of the next image per point, gathered by a single ``index_select``
  over rows of the packed pyramid buffer, interpolated by two lerps (all window pixels share one pair of
  bilinear weights), and the inverse-compositional step H^-1 g (T - J).
All points of all images form one flat list, compacted as points stop (per-point early stop); there
is no Python loop over points, and images stacked in the batch (intensity and SIM) share every call. Lists longer
than ``chunk`` (1024) points are tracked in equal chunks, one after another: the same tracks within float error (other
shapes sum in other orders; tests/tolerances.py), at a lower cost per
point once the working set of one call no longer fits in the CPU's cache (B >= 4).

The difference from OpenCV's ``calcOpticalFlowPyrLK`` (same pyramid, gradients, window, criteria and
fixed point; tracks agree to about 0.0002 px on real frames) is in the stopping:
- from iteration ``ic_iters`` of a level on, a point takes Newton steps on the same normal equations
  R(q) = g (T - J(q)) = 0, with the exact Jacobian of the bilinear window: the fixed point is unchanged, but
  the points that slide slowly (where OpenCV's loop crawls to ``iters``) converge in a step or two, and a
  point whose Newton step is not at least halved is stopped as not converging. OpenCV reports such points as
  tracked after ``iters`` iterations; here ``status`` requires convergence (update <= eps) and an end point
  inside the image. ``ic_iters >= iters`` gives plain inverse-compositional iterations (no ping-pong rule).
On CPU the per-iteration cost is dominated by the number of tensor operations, not by arithmetic, so the
stopping rules matter as much as the sampling: they cut the iterations of a 300-point call from ~90 to ~20.

Two implementations of the same arithmetic (``backend``, ``FlowConfig.lk_backend``): ``"cpp"``, the compiled operator
``torch.ops.torchtrack.lk_track`` (csrc/lk.cpp, one C++ loop per point over all points, built on first use:
:mod:`torchtrack.image.lk_op`), and ``"torch"``, the pure-torch functions below, the reference and the fallback
(``"auto"``: the operator where it builds). Tracks agree within tests/tolerances.py's LK_OP_PX.

References: J.-Y. Bouguet, "Pyramidal Implementation of the Lucas Kanade Feature Tracker", Intel, 2000;
S. Baker, I. Matthews, "Lucas-Kanade 20 Years On", IJCV 2004; R. Liu et al., "Online Determination of
Track Loss Using Template Inverse Matching", VS 2008 (d_TIM, paper eq. (10)).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.config import FlowConfig
from torchtrack.image import lk_op
from torchtrack.image.pyramid import Pyramid, build_pyramid

_EXACT_F32 = 2**24  # float32 index arithmetic is exact below this
# Points tracked together at most: the tensors of more points (their windows, the templates of every level) leave the
# CPU's cache and the time per point grows (measured, combined tracker at B=8, 4800 points per pass: 1.4x the CPU time
# of chunks of 300 to 1024 points, which all cost the same; below that the per-operation overhead grows).
_CHUNK = 1024


class LKResult(NamedTuple):
    """Result of pyramidal LK.

    points: (B, N, 2) positions in the next image (pixels, x right, y down): where the track ran but failed, its
        last position; the input where it did not run (invalid, outside the image, degenerate window).
    status: (B, N) bool, tracked: valid input, inside the image, not degenerate, converged, ended inside the image.
    residual: (B, N) mean absolute intensity difference over the final window (0 where not tracked).
    """

    points: Tensor
    status: Tensor
    residual: Tensor


class _Sampler:
    """Windows of one pyramid: (n, C, m, m) patches gathered with one 1-D index_select each.

    It keeps the pyramid's buffer and layout, not the pyramid: the pyramid keeps its samplers (``Pyramid.samplers``),
    and a reference back would make each frame's pyramid a reference cycle, freed only by Python's full garbage
    collection, which a process with many long-lived objects runs rarely (the long run's memory grew by the
    pyramids waiting for it: experiments/bench_long_run.py).
    """

    def __init__(self, pyr: Pyramid, window: int):
        self.window, self.r, self.c = window, window // 2, pyr.channels
        self.flat, self.row_stride, self.plane, self.pad = pyr.flat, pyr.stride, pyr.plane, pyr.pad
        self.sizes = [pyr.size(level) for level in range(pyr.levels)]
        self.dtype = torch.float32 if pyr.flat.numel() < _EXACT_F32 else torch.float64
        self.stride = torch.tensor([1.0, float(pyr.stride)], dtype=self.dtype)
        self.base_table = ((pyr.row_start + pyr.pad) * pyr.stride + pyr.pad).to(self.dtype)  # L,B: level px (0, 0)
        self._rows: dict[int, tuple[Tensor, Tensor]] = {}

    @staticmethod
    def of(pyr: Pyramid, window: int) -> _Sampler:
        """The sampler of a pyramid, built once and kept with it (the pyramid is used by two LK calls at least)."""
        if window not in pyr.samplers:
            pyr.samplers[window] = _Sampler(pyr, window)
        return pyr.samplers[window]

    def rows(self, size: int) -> tuple[Tensor, Tensor]:
        """A sliding view (len, size) of the flat buffer (row i = flat[i : i + size]) and the (C * size,) int32
        offsets of the rows of a size x size patch whose centre pixel is at offset 0."""
        if size not in self._rows:
            s, h, flat = self.row_stride, (size - 1) // 2, self.flat
            rows = torch.arange(size, dtype=torch.int32) * s - h * (s + 1)
            chan = torch.arange(self.c, dtype=torch.int32)[:, None] * self.plane
            view = flat.as_strided((flat.numel() - size + 1, size), (1, 1))
            self._rows[size] = (view, (chan + rows[None, :]).reshape(-1))
        return self._rows[size]

    def bounds(self, level: int) -> tuple[Tensor, Tensor]:
        """Window centres q (level px) can be sampled, gradients included, iff lo <= floor(q) <= hi."""
        h, w = self.sizes[level]
        lo, hi = self.r + 1 - self.pad, self.pad - self.r - 3
        return torch.tensor([float(lo)] * 2), torch.tensor([w + hi, h + hi], dtype=torch.float32)  # (2,): fast clamp

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
_ADJ = torch.tensor([3, 1, 2, 0])  # flat 2x2 [a, b, c, d] -> adjugate [d, -b, -c, a] (with _ADJ_SIGN)
_ADJ_SIGN = torch.tensor([1.0, -1.0, -1.0, 1.0])


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
    adj = m.reshape(n, 4).index_select(1, _ADJ).mul_(_ADJ_SIGN)
    det = torch.linalg.vecdot(m[:, 0], adj[:, ::2])
    return adj.mul_((scale / det).view(n, 1)).view(n, 2, 2), det


def _template(sampler: _Sampler, x: Tensor, base: Tensor, min_eig: float):
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


def _iterate(sampler, level, q, g, tg, h_inv, h_det, base, *, iters, eps, ic_iters):
    """LK iterations with per-point early stop for window centres q (P, 2) in level pixels.

    A point stops when its update is at most eps (converged), or, in the Newton phase, when its update
    is not at least halved (not converging), or after iters iterations. Windows are sampled inside the
    padded image; a point that leaves it stops (not converged). A stopped point stays in the batch, frozen,
    until half of the batch has stopped; then the batch is compacted (fewer tensor operations than compacting
    at every stop, for the same results).
    Returns the final centres (P, 2) and converged flags (P,).
    """
    lo, hi = sampler.bounds(level)
    q_out, conv_out = q.clone(), torch.zeros(q.shape[0], dtype=torch.bool)
    if q.shape[0] == 0:
        return q_out, conv_out
    ids, live, conv_all = torch.arange(q.shape[0]), torch.ones_like(conv_out), torch.zeros_like(conv_out)
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


def lk_track_flat(
    prev: Pyramid,
    next: Pyramid,
    points: Tensor,
    image_index: Tensor,
    init: Tensor,
    *,
    window: int = FlowConfig.window,
    levels: int = FlowConfig.levels,
    iters: int = FlowConfig.iters,
    eps: float = FlowConfig.eps,
    min_eig: float = FlowConfig.min_eig,
    ic_iters: int = FlowConfig.ic_iters,
    with_residual: bool = True,
    chunk: int = _CHUNK,
    backend: str = FlowConfig.lk_backend,
) -> tuple[Tensor, Tensor, Tensor]:
    """Pyramidal LK on a flat list of P points, each in its own image of the pyramids' batch.

    Args:
        prev, next: pyramids of equal geometry (built with a window at least ``window``).
        points: (P, 2) level-0 positions in prev. image_index: (P,) int64 batch index of each point.
        init: (P, 2) initial guess of the positions in next.
        chunk: points tracked together at most (each point's track is independent of the others; torch backend).
        backend: "cpp" (the compiled operator, CPU tensors), "torch" (the reference) or "auto" (cpp where it builds;
            the reference for tensors on another device).

    Returns:
        points (P, 2) in next (the input where not tracked), status (P,) bool, residual (P,) (zeros unless
        with_residual).
    """
    if chunk < 1:
        raise ValueError(f"lk_track_flat: chunk must be >= 1, got {chunk}")
    kwargs = dict(window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters)
    if use_cpp(backend) and points.device.type == "cpu":  # the operator has a CPU kernel only
        return _track_op(prev, next, points, image_index, init, **kwargs, with_residual=with_residual)
    if points.shape[0] <= chunk:
        return _track_chunk(prev, next, points, image_index, init, **kwargs, with_residual=with_residual)
    size = -(-points.shape[0] // -(-points.shape[0] // chunk))  # equal chunks of at most ``chunk`` points
    parts = [
        _track_chunk(prev, next, *(t[i : i + size] for t in (points, image_index, init)), **kwargs,
                     with_residual=with_residual)
        for i in range(0, points.shape[0], size)
    ]  # fmt: skip
    return tuple(torch.cat(x) for x in zip(*parts, strict=True))


def use_cpp(backend: str) -> bool:
    """Whether ``backend`` ("auto", "cpp", "torch") runs the compiled operator; "cpp" raises where it cannot."""
    if backend not in ("auto", "cpp", "torch"):
        raise ValueError(f"lk: backend must be 'auto', 'cpp' or 'torch', got {backend!r}")
    if backend == "torch":
        return False
    if not lk_op.available() and backend == "cpp":
        raise RuntimeError(f"lk: backend 'cpp' asked, but the operator could not be built: {lk_op.error()}")
    return lk_op.available()


class _OpTables:
    """The operator's tables of one pyramid, kept with it (``Pyramid.samplers``): base (L, B) int64 flat index of each
    level's and image's pixel (0, 0), sizes (L, 2) int64 level sizes (H_l, W_l)."""

    def __init__(self, pyr: Pyramid, levels: int):
        self.base = ((pyr.row_start[:levels] + pyr.pad) * pyr.stride + pyr.pad).contiguous()
        self.sizes = torch.tensor([pyr.size(level) for level in range(levels)], dtype=torch.int64)

    @staticmethod
    def of(pyr: Pyramid, levels: int) -> _OpTables:
        if ("op", levels) not in pyr.samplers:
            pyr.samplers[("op", levels)] = _OpTables(pyr, levels)
        return pyr.samplers[("op", levels)]


def _track_op(prev, next, points, image_index, init, *, window, levels, iters, eps, min_eig, ic_iters, with_residual):
    """:func:`lk_track_flat` by the compiled operator (all points in one call)."""
    same = (prev.plane, prev.flat.numel()) == (next.plane, next.flat.numel()) or prev.channels == next.channels == 1
    if (prev.stride, prev.pad) != (next.stride, next.pad) or not same:  # one channel: buffers of any length
        raise ValueError("lk_track_flat: prev and next pyramids must have the same geometry")
    tables_prev, tables_next = _OpTables.of(prev, levels), _OpTables.of(next, levels)
    base_prev, base_next, sizes = tables_prev.base, tables_next.base, tables_prev.sizes
    f32 = dict(dtype=torch.float32, memory_format=torch.contiguous_format)
    return lk_op.lk_track(
        prev.flat.contiguous(), next.flat.contiguous(), base_prev, base_next, sizes, points.to(**f32),
        image_index.to(torch.int64).contiguous(), init.to(**f32), stride=prev.stride, plane=prev.plane,
        pad=prev.pad, window=window, iters=iters, ic_iters=ic_iters, eps=eps, min_eig=min_eig,
        with_residual=with_residual,
    )  # fmt: skip


def _track_chunk(
    prev, next, points, image_index, init, *, window, levels, iters, eps, min_eig, ic_iters, with_residual
):
    """:func:`lk_track_flat` on one chunk of points."""
    with torch.inference_mode():
        s_prev, s_next = _Sampler.of(prev, window), _Sampler.of(next, window)
        h0, w0 = prev.size(0)
        inside = (points >= 0).all(-1) & (points[:, 0] <= w0 - 1) & (points[:, 1] <= h0 - 1)
        guess, status = init.clone(), inside.clone()
        sel = inside.nonzero().squeeze(1)
        tracked = torch.zeros_like(status)
        status[:] = False
        if sel.numel():
            x0, img = points[sel], image_index[sel]
            # The templates of all levels in one call (rows level-major): they depend on x0 only.
            scale = 0.5 ** torch.arange(levels, dtype=x0.dtype)
            x_levels = (scale.view(-1, 1, 1) * x0).reshape(-1, 2)
            base = s_prev.base_table[:levels].index_select(1, img).reshape(-1)
            *template, degenerate = _template(s_prev, x_levels, base, min_eig)
            degenerate = degenerate.view(levels, -1)
            # A point degenerate at the finest level fails whatever the coarse levels find, so it is not tracked
            # at all (OpenCV tracks it through the coarse levels, then reports it as failed).
            fine = ~degenerate[0]
            tracked[sel[fine]] = True
        for level in reversed(range(levels) if sel.numel() else ()):
            track = (fine & ~degenerate[level]).nonzero().squeeze(1)  # degenerate at a coarse level: skip it (OpenCV)
            g, tg, h_inv, h_det = (t.index_select(0, track + level * sel.numel()) for t in template)
            rows = sel[track]
            q, conv = _iterate(
                s_next, level, guess[rows] * 0.5**level, g, tg, h_inv, h_det, s_next.base(level, img[track]),
                iters=iters, eps=eps, ic_iters=ic_iters,
            )  # fmt: skip
            guess[rows] = q / 0.5**level
            if level == 0:
                status[rows] = conv
        status &= (guess >= 0).all(-1) & (guess[:, 0] <= w0 - 1) & (guess[:, 1] <= h0 - 1)
        residual = torch.zeros(points.shape[0], dtype=points.dtype)
        good = status.nonzero().squeeze(1)
        if with_residual and good.numel():
            residual[good] = _residual(s_prev, s_next, points[good], guess[good], image_index[good])
        guess = torch.where(tracked[:, None], guess, points)
    return guess.clone(), status.clone(), residual.clone()


def _residual(s_prev: _Sampler, s_next: _Sampler, x0: Tensor, x1: Tensor, img: Tensor) -> Tensor:
    """Mean |J - T| over the final level-0 windows (the objective LK minimised), (P,)."""
    t = s_prev.bilinear(x0, s_prev.base(0, img), extra=0)
    j = s_next.bilinear(x1, s_next.base(0, img), extra=0)
    return (j - t).abs().flatten(1).mean(-1)


def _as_pyramid(x: Tensor | Pyramid, levels: int, window: int, name: str) -> Pyramid:
    if isinstance(x, Pyramid):
        if x.levels < levels or x.max_window < window:
            raise ValueError(
                f"pyramidal_lk: {name} pyramid has {x.levels} levels / window {x.max_window}, need {levels} / {window}"
            )
        return x
    return build_pyramid(x, levels, window=window)


def pyramidal_lk(
    prev: Tensor | Pyramid,
    next: Tensor | Pyramid,
    points: Tensor,
    *,
    window: int = FlowConfig.window,
    levels: int = FlowConfig.levels,
    iters: int = FlowConfig.iters,
    eps: float = FlowConfig.eps,
    init: Tensor | None = None,
    valid: Tensor | None = None,
    min_eig: float = FlowConfig.min_eig,
    ic_iters: int = FlowConfig.ic_iters,
    with_residual: bool = True,
    backend: str = FlowConfig.lk_backend,
) -> LKResult:
    """Track points from prev to next with pyramidal Lucas–Kanade (translation per window).

    Args:
        prev, next: (B, C, H, W) float images (channels tracked jointly) or their pyramids (build_pyramid),
            reusable across calls: build each frame's pyramid once.
        points: (B, N, 2) pixel positions in prev (x right, y down, pixel centres at integers).
        window: odd window width in pixels (OpenCV winSize). levels: pyramid levels L (OpenCV maxLevel = L - 1).
        iters, eps: per level, at most iters iterations; a point stops when its update is at most eps pixels.
        init: (B, N, 2) initial guess in next (default: points). valid: (B, N) bool, False entries are skipped.
        min_eig: threshold on the gradient matrix's smallest eigenvalue in OpenCV's units (minEigThreshold).
        ic_iters: inverse-compositional iterations per level before Newton steps (see the module docstring).
        with_residual: compute the residual (one more window sample per point); zeros otherwise.
        backend: "cpp" (compiled operator), "torch" (reference) or "auto" (cpp where it builds); see lk_track_flat.

    Returns:
        LKResult(points (B, N, 2), status (B, N), residual (B, N)).
    """
    if points.ndim != 3 or points.shape[-1] != 2:
        raise ValueError(f"pyramidal_lk: points must be (B, N, 2), got {tuple(points.shape)}")
    if window % 2 == 0 or window < 3 or levels < 1 or iters < 1:
        raise ValueError(
            f"pyramidal_lk: need odd window >= 3, levels >= 1, iters >= 1; got {window}, {levels}, {iters}"
        )
    prev_p, next_p = _as_pyramid(prev, levels, window, "prev"), _as_pyramid(next, levels, window, "next")
    b, n = points.shape[:2]
    if prev_p.batch != b or prev_p.images[0].shape != next_p.images[0].shape:
        raise ValueError(
            f"pyramidal_lk: images {tuple(prev_p.images[0].shape)} and {tuple(next_p.images[0].shape)} "
            f"do not match points {tuple(points.shape)}"
        )
    init = points if init is None else init
    if init.shape != points.shape:
        raise ValueError(f"pyramidal_lk: init must be {tuple(points.shape)}, got {tuple(init.shape)}")
    if valid is not None and valid.shape != (b, n):
        raise ValueError(f"pyramidal_lk: valid must be {(b, n)}, got {tuple(valid.shape)}")
    pts, guess = points.reshape(-1, 2).float(), init.reshape(-1, 2).float()
    image_index = torch.arange(b).repeat_interleave(n)
    sel = valid.reshape(-1).nonzero().squeeze(1) if valid is not None else torch.arange(b * n)
    out, status, residual = pts.clone(), torch.zeros(b * n, dtype=torch.bool), torch.zeros(b * n)
    out[sel], status[sel], residual[sel] = lk_track_flat(
        prev_p, next_p, pts[sel], image_index[sel], guess[sel],
        window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters,
        with_residual=with_residual, backend=backend,
    )  # fmt: skip
    return LKResult(out.view(b, n, 2).to(points.dtype), status.view(b, n), residual.view(b, n))


def forward_backward(
    prev: Tensor | Pyramid, next: Tensor | Pyramid, points: Tensor, **kwargs
) -> tuple[LKResult, Tensor, Tensor]:
    """Template inverse matching: track prev -> next, then the result back next -> prev (from no prior).

    Args:
        prev, next, points: as pyramidal_lk; kwargs are passed to both passes (init and valid only forward).
            Pass pyramids (build_pyramid) to build each image's pyramid once.

    Returns:
        (forward LKResult, back_points (B, N, 2) in prev, d_tim (B, N)): d_TIM = ||x - x'||, eq. (10), +inf
        where either pass failed.
    """
    levels, window = kwargs.get("levels", 3), kwargs.get("window", 21)
    prev_p, next_p = _as_pyramid(prev, levels, window, "prev"), _as_pyramid(next, levels, window, "next")
    fwd = pyramidal_lk(prev_p, next_p, points, **kwargs)
    kwargs.pop("init", None)
    kwargs.update(valid=fwd.status, with_residual=False)
    bwd = pyramidal_lk(next_p, prev_p, fwd.points, **kwargs)
    d_tim, _ = tim_error(points, bwd.points, fwd.status, bwd.status)
    return fwd, bwd.points, d_tim


def tim_error(points: Tensor, back_points: Tensor, ok_forward: Tensor, ok_backward: Tensor) -> tuple[Tensor, Tensor]:
    """Template inverse matching error, eq. (10): ``d_TIM = || x_{t-1} - x'_{t-1} ||`` between the start points
    (..., 2) and the points tracked forward and then back again (..., 2). The one definition shared by
    :func:`forward_backward` and both back ends of :func:`torchtrack.image.flow.combined_track`.

    Returns:
        (d_tim (...), status (...)): status is ``ok_forward & ok_backward`` (both passes tracked); d_tim is +inf
        where not, so that such a feature never wins the combined tracker's step III and fails its step IV.
    """
    status = ok_forward & ok_backward
    d_tim = torch.linalg.vector_norm(points - back_points, dim=-1)
    return torch.where(status, d_tim, torch.full_like(d_tim, float("inf"))), status
