"""Spatio-textural feature selection, paper §III-B, eq. (9).

1. Cornerness of the intensity image and of the SIM image (Harris, :mod:`torchtrack.image.corners`).
2. Normalisation, per frame and per map, so that the two are comparable: with ``R+ = max(R, 0)`` on
   the eligible pixels (region of interest, valid depth, valid SIM when used, away from the border)
   and ``s`` the 90th percentile over the patches of the patch maxima of ``R+`` (patches with a
   positive maximum), ``rho = (R+ / s)^(1/4)`` and ``C = rho / (1 + rho)``. The fourth root makes the
   measure linear in image contrast (Harris grows as contrast^4, spanning 5 decades over a frame);
   dividing by a high percentile makes it invariant to each image's contrast (1/2 = as strong as the
   strong corners of this frame); the soft saturation keeps a few extreme corners of one map from
   outweighing the other map, without ties (a monotone map: each map keeps its own ranking). C is in
   [0, 1), 0 on flat areas and edges.
3. ``C = lam * C_int + (1 - lam) * C_SIM`` (eq. 9).
4. ``spread=True`` (the paper): a regular grid of patches over the image, one pixel of maximum C
   per patch (patches outside the region of interest give none). ``spread=False`` (ablation EKF-1):
   the global top-N by C after non-maximum suppression in a (2 nms_radius + 1)^2 window, N the
   number of patches of the grid (or ``max_features``).

``roi_fraction`` (improvement, default 0.5; None = the paper's fixed grid): when the bounding box of a frame's
eligible pixels covers less than this fraction of the image inside the border, its square patches shrink (down to
``min_patch``) so that the box holds as many patches as that fraction of the image holds at the configured size (0.5
at 640 x 480, 32 px: ~137). The paper splits the *region of interest* into patches; with a fixed image grid a small
object (a few % of the image) gets only a couple of dozen features, which is what limits the pose there. Larger
regions keep the configured size.

Only pixels with C > ``min_cornerness`` (default 0.05: a corner of about 5% of the contrast of the
frame's strong corners) are selected: a textureless patch gives no feature rather than an
untrackable one.

Defaults are torchtrack's (the improvements on); the application's schema repeats them (``SelectConfig``), and
tests/test_defaults.py holds the two equal.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.geometry import backproject, sample_depth
from torchtrack.image.corners import harris
from torchtrack.image.shape_index import SIM, ShapeIndex, compute_sim, sim_image


class Features(NamedTuple):
    """Selected features, padded to (B, N) and sorted by decreasing cornerness within each sequence.

    Attributes:
        pixels: (B, N, 2) float32 pixel coordinates (x, y) of the features (integers).
        points: (B, N, 3) camera coordinates, back-projection of the raw depth at the pixels.
        cornerness: (B, N) combined normalised cornerness C of eq. (9), in [0, 1).
        cornerness_int: (B, N) normalised intensity cornerness.
        cornerness_sim: (B, N) normalised SIM cornerness (0 when lam = 1: no SIM used).
        valid: (B, N) bool; invalid entries are all zeros.
    """

    pixels: Tensor
    points: Tensor
    cornerness: Tensor
    cornerness_int: Tensor
    cornerness_sim: Tensor
    valid: Tensor


class CornernessMaps(NamedTuple):
    """Per-pixel maps of the selector, each (B, 1, H, W).

    Attributes:
        C: combined cornerness of eq. (9) in [0, 1) on eligible pixels, -1 elsewhere.
        c_int, c_sim: normalised intensity and SIM cornerness (c_sim is 0 when lam = 1).
        eligible: float {0, 1}: in the region of interest, with depth, with a valid SIM when required,
            at least ``border`` pixels from the image edge.
    """

    C: Tensor
    c_int: Tensor
    c_sim: Tensor
    eligible: Tensor


def patch_shape(H: int, W: int, patch_size: int | tuple[int, int] = 32, grid: tuple[int, int] | None = None):
    """(ph, pw, gh, gw): patch rows/cols in pixels and the grid's rows/cols covering (H, W)."""
    if grid is not None:
        gh, gw = grid
        ph, pw = math.ceil(H / gh), math.ceil(W / gw)
    else:
        ph, pw = (patch_size, patch_size) if isinstance(patch_size, int) else patch_size
    if ph < 1 or pw < 1:
        raise ValueError(f"select_features: patch size must be positive, got {(ph, pw)}")
    return ph, pw, math.ceil(H / ph), math.ceil(W / pw)


def roi_patch_size(
    eligible: Tensor, patch_size: int, roi_fraction: float, min_patch: int = 8, border: int = 0
) -> list[int]:
    """Per frame the square patch size (pixels) for the bounding box of the eligible pixels of ``eligible``
    (B, 1, H, W) bool: ``floor(patch_size * sqrt(box area / (roi_fraction * A)))`` clamped to
    ``[min_patch, patch_size]`` (``patch_size`` where nothing is eligible), A = (H - 2 border) (W - 2 border) the
    image inside the border."""
    B, _, H, W = eligible.shape
    inside = max(1, (H - 2 * border) * (W - 2 * border))
    rows, cols = eligible[:, 0].any(2), eligible[:, 0].any(1)  # B,H and B,W
    out = []
    for b in range(B):
        r, c = torch.nonzero(rows[b])[:, 0], torch.nonzero(cols[b])[:, 0]
        if r.numel() == 0:
            out.append(patch_size)
            continue
        area = float((r[-1] - r[0] + 1) * (c[-1] - c[0] + 1))
        size = math.floor(patch_size * math.sqrt(area / (roi_fraction * inside)))
        out.append(int(min(patch_size, max(min_patch, size))))
    return out


def _patches(x: Tensor, ph: int, pw: int, gh: int, gw: int, value: float) -> Tensor:
    """(B, C, H, W) -> (B, C, gh, ph, gw, pw), padded with ``value``."""
    B, C, H, W = x.shape
    if gh * ph != H or gw * pw != W:
        x = F.pad(x, (0, gw * pw - W, 0, gh * ph - H), value=value)
    return x.view(B, C, gh, ph, gw, pw)


def normalise_cornerness(
    R: Tensor, eligible: Tensor, ph: int, pw: int, gh: int, gw: int, quantile: float = 0.9
) -> Tensor:
    """Per-frame, per-channel normalisation of the module docstring: R (B, C, H, W) -> C in [0, 1)."""
    r = R.clamp_min(0.0).mul_(eligible)
    patch_max = _patches(r, ph, pw, gh, gw, 0.0).amax(dim=(3, 5)).flatten(2)  # B,C,P
    pos = patch_max > 0
    sorted_max = torch.where(pos, patch_max, torch.full_like(patch_max, float("inf"))).sort(dim=-1).values
    n = pos.sum(-1, keepdim=True)
    k = ((n - 1).clamp_min(0).to(R.dtype) * quantile).round().long()
    s = sorted_max.gather(-1, k)  # the quantile of the positive patch maxima
    s = torch.where(n > 0, s, torch.ones_like(s))[..., None]  # B,C,1,1
    # rho = (R+ / s)^(1/4), contrast-linear (Harris grows as contrast^4). Offsetting by 2^-100 and back
    # keeps 0 -> 0 exactly and avoids sqrt(0), a slow path of the vectorised CPU sqrt (~7x slower).
    rho = r.div_(s).add_(2.0**-100).sqrt_().sqrt_().sub_(2.0**-25)
    return rho / (rho + 1.0)


def _eligible(depth: Tensor, roi: Tensor | None, sim_valid: Tensor | None, border: int) -> Tensor:
    m = depth > 0
    if roi is not None:
        m &= roi
    if sim_valid is not None:
        m &= sim_valid
    if border > 0:
        for dim in (-1, -2):
            m.narrow(dim, 0, border).zero_()
            m.narrow(dim, m.shape[dim] - border, border).zero_()
    return m.to(depth.dtype)


def _patch_maxima(C: Tensor, ph: int, pw: int, gh: int, gw: int) -> tuple[Tensor, Tensor]:
    """One pixel of maximum C per patch: (pixels (B, P, 2) float, value (B, P)); C (B, 1, H, W)."""
    B = C.shape[0]
    p = _patches(C, ph, pw, gh, gw, -1.0)[:, 0].permute(0, 1, 3, 2, 4).reshape(B, gh * gw, ph * pw)
    value, idx = p.max(dim=-1)
    P = torch.arange(gh * gw, device=C.device)
    x = (P % gw) * pw + idx % pw
    y = (P // gw) * ph + idx // pw
    return torch.stack([x, y], dim=-1).to(C.dtype), value


def _local_maxima(C: Tensor, radius: int, n: int) -> tuple[Tensor, Tensor]:
    """Global top-n of C (B, 1, H, W) after non-maximum suppression: (pixels (B, n, 2), value (B, n))."""
    B, _, H, W = C.shape
    m = C
    for _ in range(radius):
        p = F.pad(m, (1, 1), value=-1.0)
        m = torch.maximum(torch.maximum(p[..., :-2], p[..., 2:]), m)
    for _ in range(radius):
        p = F.pad(m, (0, 0, 1, 1), value=-1.0)
        m = torch.maximum(torch.maximum(p[..., :-2, :], p[..., 2:, :]), m)
    score = torch.where(C >= m, C, torch.full_like(C, -1.0)).reshape(B, H * W)
    value, idx = score.topk(min(n, H * W), dim=-1)
    return torch.stack([idx % W, idx // W], dim=-1).to(C.dtype), value


def _gather_map(x: Tensor, pixels: Tensor) -> Tensor:
    """x (B, 1, H, W) at integer pixels (B, N, 2) -> (B, N)."""
    B, _, H, W = x.shape
    idx = (pixels[..., 1].long() * W + pixels[..., 0].long()).clamp(0, H * W - 1)
    return x.reshape(B, H * W).gather(1, idx)


def cornerness_maps(
    gray: Tensor,
    depth: Tensor,
    K: Tensor,
    *,
    roi: Tensor | None,
    sim: SIM | ShapeIndex | None,
    lam: float,
    patches: tuple[int, int, int, int],
    border: int,
    require_sim: bool = False,
    corner_kwargs: dict | None = None,
    sim_kwargs: dict | None = None,
) -> CornernessMaps:
    """Steps 1-3 of the module docstring (arguments as :func:`select_features`; ``patches`` from :func:`patch_shape`)."""
    if lam == 1.0:
        sim = None  # pure intensity: the SIM is neither needed nor required
    elif sim is None:
        sim = compute_sim(depth, K, **(sim_kwargs or {}))
    gray = gray.float()
    if sim is not None:
        sim_img = sim.image if isinstance(sim, SIM) else sim_image(sim)
        images = torch.cat([gray, sim_img], dim=1)
    else:
        images = gray
    eligible = _eligible(depth, roi, sim.valid if (sim is not None and require_sim) else None, border)
    R = harris(images, **(corner_kwargs or {}))  # B,1|2,H,W
    Cn = normalise_cornerness(R, eligible, *patches)
    c_int = Cn[:, :1]
    c_sim = Cn[:, 1:] if sim is not None else torch.zeros_like(c_int)
    C = torch.add(c_int * lam, c_sim, alpha=1.0 - lam) if sim is not None else c_int * lam  # eq. (9)
    C = C.mul_(eligible).add_(eligible).sub_(1.0)  # -1 where not eligible
    return CornernessMaps(C=C, c_int=c_int, c_sim=c_sim, eligible=eligible)


def select_features(
    gray: Tensor,
    depth: Tensor,
    K: Tensor,
    *,
    roi: Tensor | None = None,
    sim: SIM | ShapeIndex | None = None,
    lam: float = 0.5,
    patch_size: int | tuple[int, int] = 32,
    grid: tuple[int, int] | None = None,
    spread: bool = True,
    max_features: int | None = None,
    border: int = 12,
    nms_radius: int = 2,
    min_cornerness: float = 0.05,
    require_sim: bool = False,
    corner_kwargs: dict | None = None,
    sim_kwargs: dict | None = None,
    cpu_chunk: int | None = 1,
    roi_fraction: float | None = 0.5,
    min_patch: int = 8,
) -> Features:
    """Spatio-textural feature selection (eq. 9); method and normalisation in the module docstring.

    Args:
        gray: (B, 1, H, W) intensity in [0, 1].
        depth: (B, 1, H, W) metres in the same pixel grid, 0 = none. Features only where depth > 0.
        K: (B, 3, 3) intrinsics of that grid (for the back-projection and the SIM).
        roi: (B, 1, H, W) bool region of interest (e.g. :func:`torchtrack.image.object_model.object_mask`);
            None = whole frame.
        sim: the frame's SIM (``compute_sim`` or ``shape_index`` output); computed here when None and lam < 1.
        lam: lambda of eq. (9): 1 = intensity only (the SIM is then neither computed nor required).
        patch_size: patch (rows, cols) in pixels, or one int for square patches (32: a 15 x 20 grid,
            300 patches, on 640 x 480).
        grid: (rows, cols) of the patch grid instead of ``patch_size``.
        spread: one feature per patch (paper); False = global top-N with NMS (ablation EKF-1).
        max_features: keep at most this many (the highest C); default: the number of patches.
        border: features are at least this many pixels from the image edge (LK window).
        nms_radius: non-maximum suppression radius (pixels) when ``spread`` is False.
        min_cornerness: a feature needs C above this (module docstring).
        require_sim: with lam < 1, only pixels with a valid SIM are eligible (the paper's choice;
            False lets planar areas compete with C_SIM = 0).
        corner_kwargs: keyword arguments of :func:`torchtrack.image.corners.harris`.
        sim_kwargs: keyword arguments of :func:`torchtrack.image.shape_index.shape_index` (when computed here).
        cpu_chunk: on CPU, frames go through the per-pixel maps this many at a time (None = all at once).
            A whole batch of full-frame temporaries overflows the caches and, with glibc's default malloc,
            is page-faulted afresh on every call; per-frame chunks are faster. Results agree within float error (other
            shapes sum in other orders; tests/tolerances.py).
        roi_fraction: improvement (None = paper): shrink the square patches of a frame whose eligible pixels' bounding
            box covers less than this fraction of the image inside ``border``, down to ``min_patch`` (module docstring;
            :func:`roi_patch_size`).
            Needs an int ``patch_size`` and no ``grid``; frames are then selected one at a time.

    Returns:
        Features, N = the largest number of selected features over the batch (or ``max_features``).
    """
    if gray.dim() != 4 or gray.shape[1] != 1 or depth.shape != gray.shape:
        raise ValueError(
            f"select_features: gray and depth must be (B, 1, H, W), got {tuple(gray.shape)}, {tuple(depth.shape)}"
        )
    B, _, H, W = gray.shape
    if K.shape != (B, 3, 3):
        raise ValueError(f"select_features: K must be ({B}, 3, 3), got {tuple(K.shape)}")
    if roi is not None and roi.shape != gray.shape:
        raise ValueError(f"select_features: roi must be {tuple(gray.shape)}, got {tuple(roi.shape)}")
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"select_features: lam must be in [0, 1], got {lam}")
    ph, pw, gh, gw = patch_shape(H, W, patch_size, grid)
    if 2 * border >= min(H, W):
        raise ValueError(f"select_features: border {border} leaves no pixel of a {H}x{W} image")

    sizes = None
    if roi_fraction is not None:
        if grid is not None or not isinstance(patch_size, int):
            raise ValueError(
                "select_features: roi_fraction needs an int patch_size and no grid (roi_fraction=None: the fixed grid)"
            )
        if not 0.0 < roi_fraction <= 1.0 or min_patch < 1:
            raise ValueError(
                f"select_features: need 0 < roi_fraction <= 1 and min_patch >= 1, got {roi_fraction}, {min_patch}"
            )
        eligible = _eligible(depth, roi, None, border) > 0
        sizes = roi_patch_size(eligible, patch_size, roi_fraction, min_patch, border)
        cpu_chunk = 1  # frames may differ in patch size
    n_max = gh * gw if max_features is None else max_features
    if sizes is not None and max_features is None:
        n_max = max(math.ceil(H / p) * math.ceil(W / p) for p in sizes)
    step = B if (cpu_chunk is None or (gray.device.type != "cpu" and sizes is None)) else max(1, cpu_chunk)
    parts = []
    for s in range(0, B, step):  # chunks of frames on CPU (see cpu_chunk); one pass on other devices
        sl = slice(s, s + step)
        patches = (ph, pw, gh, gw) if sizes is None else patch_shape(H, W, sizes[s])
        maps = cornerness_maps(
            gray[sl], depth[sl], K[sl], roi=None if roi is None else roi[sl],
            sim=None if sim is None else type(sim)(*(t[sl] for t in sim)), lam=lam, patches=patches,
            border=border, require_sim=require_sim, corner_kwargs=corner_kwargs, sim_kwargs=sim_kwargs,
        )  # fmt: skip
        ph, pw, gh, gw = patches
        if spread:
            pixels, value = _patch_maxima(maps.C, ph, pw, gh, gw)
        else:
            pixels, value = _local_maxima(maps.C, nms_radius, n_max)
        parts.append((pixels, value, _gather_map(maps.c_int, pixels), _gather_map(maps.c_sim, pixels)))
    if sizes is not None:  # frames with different grids: pad the candidates to the largest count (value -1: none)
        P = max(p[0].shape[1] for p in parts)
        parts = [(_pad(a, P, 0.0), _pad(v, P, -1.0), _pad(ci, P, 0.0), _pad(cs, P, 0.0)) for a, v, ci, cs in parts]
    candidates = [torch.cat(x) for x in zip(*parts, strict=True)]
    return _finish(*candidates, depth, K, n_max, min_cornerness)


def _pad(x: Tensor, n: int, value: float) -> Tensor:
    """Pad dim 1 of x (B, P, ...) to n with ``value``."""
    if x.shape[1] == n:
        return x
    return torch.cat([x, x.new_full((x.shape[0], n - x.shape[1], *x.shape[2:]), value)], dim=1)


def _finish(
    pixels: Tensor,
    value: Tensor,
    c_int: Tensor,
    c_sim: Tensor,
    depth: Tensor,
    K: Tensor,
    n_max: int,
    min_c: float,
) -> Features:
    """Candidates (B, P, ...) -> Features: sort by (valid, C) descending, pad to the batch's largest count,
    back-project."""
    valid = value > max(min_c, 0.0)
    order = torch.where(valid, value, torch.full_like(value, -1.0)).argsort(dim=-1, descending=True, stable=True)
    N = max(1, min(n_max, int(valid.sum(-1).max())))
    order = order[:, :N]
    pixels = pixels.gather(1, order[..., None].expand(-1, -1, 2))
    value, valid = value.gather(1, order), valid.gather(1, order)
    vf = valid.to(pixels.dtype)
    pixels = pixels * vf[..., None]
    z = sample_depth(depth, pixels) * vf
    points = backproject(K.to(pixels), pixels, z) * vf[..., None]
    return Features(
        pixels=pixels,
        points=points,
        cornerness=value.clamp_min(0.0) * vf,
        cornerness_int=c_int.gather(1, order) * vf,
        cornerness_sim=c_sim.gather(1, order) * vf,
        valid=valid,
    )
