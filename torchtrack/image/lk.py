"""Batched pyramidal Lucas–Kanade (Bouguet) and template inverse matching, paper §III-C, eq. (10).

Translation LK, per point and pyramid level (coarse to fine, the result of a level seeding the next); the
per-level work (template, inverse-compositional and Newton iterations on windows of the packed pyramid) is in
:mod:`torchtrack.image.lk_window`, this module drives it over the levels: every level's templates in one call (they
depend on the start point only), and points degenerate at the finest level are not tracked at all.
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

The inner loop runs as the compiled operator ``torch.ops.torchtrack.lk_track`` (csrc/lk.cpp, one C++ loop per point
over all points; :mod:`torchtrack.ops` builds it and decides where it runs) and as the pure-torch functions below
(:func:`lk_track_reference`), the reference and the path on other devices. Tracks agree within tests/tolerances.py's
LK_OP_PX.

References: J.-Y. Bouguet, "Pyramidal Implementation of the Lucas Kanade Feature Tracker", Intel, 2000;
S. Baker, I. Matthews, "Lucas-Kanade 20 Years On", IJCV 2004; R. Liu et al., "Online Determination of
Track Loss Using Template Inverse Matching", VS 2008 (d_TIM, paper eq. (10)).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack import ops
from torchtrack.image.lk_window import Sampler, iterate, template, window_residual
from torchtrack.image.pyramid import Pyramid, build_pyramid

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


def lk_track_flat(
    prev: Pyramid,
    next: Pyramid,
    points: Tensor,
    image_index: Tensor,
    init: Tensor,
    *,
    window: int = 21,
    levels: int = 3,
    iters: int = 30,
    eps: float = 0.01,
    min_eig: float = 1.0e-4,
    ic_iters: int = 3,
    with_residual: bool = True,
    chunk: int = _CHUNK,
) -> tuple[Tensor, Tensor, Tensor]:
    """Pyramidal LK on a flat list of P points, each in its own image of the pyramids' batch: the compiled operator
    where it runs (:func:`torchtrack.ops.compiled`), else :func:`lk_track_reference`.

    Args:
        prev, next: pyramids of equal geometry (built with a window at least ``window``).
        points: (P, 2) level-0 positions in prev. image_index: (P,) int64 batch index of each point.
        init: (P, 2) initial guess of the positions in next.
        chunk: points tracked together at most by the reference (each point's track is independent of the others).

    Returns:
        points (P, 2) in next (the input where not tracked), status (P,) bool, residual (P,) (zeros unless
        with_residual).
    """
    if chunk < 1:
        raise ValueError(f"lk_track_flat: chunk must be >= 1, got {chunk}")
    kwargs = dict(window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters)
    if ops.compiled(points):
        return _track_op(prev, next, points, image_index, init, **kwargs, with_residual=with_residual)
    return lk_track_reference(prev, next, points, image_index, init, **kwargs, with_residual=with_residual, chunk=chunk)


def lk_track_reference(
    prev: Pyramid,
    next: Pyramid,
    points: Tensor,
    image_index: Tensor,
    init: Tensor,
    *,
    window: int = 21,
    levels: int = 3,
    iters: int = 30,
    eps: float = 0.01,
    min_eig: float = 1.0e-4,
    ic_iters: int = 3,
    with_residual: bool = True,
    chunk: int = _CHUNK,
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`lk_track_flat` in pure torch, in equal chunks of at most ``chunk`` points: the compiled operator's
    reference, and the path on devices other than the CPU."""
    if chunk < 1:
        raise ValueError(f"lk_track_flat: chunk must be >= 1, got {chunk}")
    kwargs = dict(window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters)
    if points.shape[0] <= chunk:
        return _track_chunk(prev, next, points, image_index, init, **kwargs, with_residual=with_residual)
    size = -(-points.shape[0] // -(-points.shape[0] // chunk))  # equal chunks of at most ``chunk`` points
    parts = [
        _track_chunk(prev, next, *(t[i : i + size] for t in (points, image_index, init)), **kwargs,
                     with_residual=with_residual)
        for i in range(0, points.shape[0], size)
    ]  # fmt: skip
    return tuple(torch.cat(x) for x in zip(*parts, strict=True))


class _OpTables:
    """The operator's tables of one pyramid, kept with it (``Pyramid.samplers``): base (L, B) int64 flat index of each
    level's and image's pixel (0, 0), sizes (L, 2) int64 level sizes (H_l, W_l)."""

    def __init__(self, pyr: Pyramid, levels: int):
        self.base = ((pyr.row_start[:levels] + pyr.pad) * pyr.stride + pyr.pad).contiguous()
        self.sizes = torch.tensor(
            [pyr.size(level) for level in range(levels)], dtype=torch.int64, device=pyr.flat.device
        )

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
    return torch.ops.torchtrack.lk_track(
        prev.flat.contiguous(), next.flat.contiguous(), base_prev, base_next, sizes, points.to(**f32),
        image_index.to(torch.int64).contiguous(), init.to(**f32), prev.stride, prev.plane, prev.pad, window, iters,
        ic_iters, eps, min_eig, with_residual,
    )  # fmt: skip


def _track_chunk(
    prev, next, points, image_index, init, *, window, levels, iters, eps, min_eig, ic_iters, with_residual
):
    """:func:`lk_track_flat` on one chunk of points."""
    with torch.inference_mode():
        s_prev, s_next = Sampler.of(prev, window), Sampler.of(next, window)
        h0, w0 = prev.size(0)
        inside = (points >= 0).all(-1) & (points[:, 0] <= w0 - 1) & (points[:, 1] <= h0 - 1)
        guess, status = init.clone(), inside.clone()
        sel = inside.nonzero().squeeze(1)
        tracked = torch.zeros_like(status)
        status[:] = False
        if sel.numel():
            x0, img = points[sel], image_index[sel]
            # The templates of all levels in one call (rows level-major): they depend on x0 only.
            scale = 0.5 ** torch.arange(levels, dtype=x0.dtype, device=x0.device)
            x_levels = (scale.view(-1, 1, 1) * x0).reshape(-1, 2)
            base = s_prev.base_table[:levels].index_select(1, img).reshape(-1)
            *tmpl, degenerate = template(s_prev, x_levels, base, min_eig)
            degenerate = degenerate.view(levels, -1)
            # A point degenerate at the finest level fails whatever the coarse levels find, so it is not tracked
            # at all (OpenCV tracks it through the coarse levels, then reports it as failed).
            fine = ~degenerate[0]
            tracked[sel[fine]] = True
        for level in reversed(range(levels) if sel.numel() else ()):
            track = (fine & ~degenerate[level]).nonzero().squeeze(1)  # degenerate at a coarse level: skip it (OpenCV)
            g, tg, h_inv, h_det = (t.index_select(0, track + level * sel.numel()) for t in tmpl)
            rows = sel[track]
            q, conv = iterate(
                s_next, level, guess[rows] * 0.5**level, g, tg, h_inv, h_det, s_next.base(level, img[track]),
                iters=iters, eps=eps, ic_iters=ic_iters,
            )  # fmt: skip
            guess[rows] = q / 0.5**level
            if level == 0:
                status[rows] = conv
        status &= (guess >= 0).all(-1) & (guess[:, 0] <= w0 - 1) & (guess[:, 1] <= h0 - 1)
        residual = points.new_zeros(points.shape[0])
        good = status.nonzero().squeeze(1)
        if with_residual and good.numel():
            residual[good] = window_residual(s_prev, s_next, points[good], guess[good], image_index[good])
        guess = torch.where(tracked[:, None], guess, points)
    return guess.clone(), status.clone(), residual.clone()


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
    window: int = 21,
    levels: int = 3,
    iters: int = 30,
    eps: float = 0.01,
    init: Tensor | None = None,
    valid: Tensor | None = None,
    min_eig: float = 1.0e-4,
    ic_iters: int = 3,
    with_residual: bool = True,
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
    dev = points.device
    image_index = torch.arange(b, device=dev).repeat_interleave(n)
    sel = valid.reshape(-1).nonzero().squeeze(1) if valid is not None else torch.arange(b * n, device=dev)
    out, status, residual = pts.clone(), torch.zeros(b * n, dtype=torch.bool, device=dev), pts.new_zeros(b * n)
    out[sel], status[sel], residual[sel] = lk_track_flat(
        prev_p, next_p, pts[sel], image_index[sel], guess[sel],
        window=window, levels=levels, iters=iters, eps=eps, min_eig=min_eig, ic_iters=ic_iters,
        with_residual=with_residual,
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
