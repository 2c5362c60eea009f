"""Shape Index Map (SIM) of a depth image, paper §III-B, eq. (8).

``SI = 1/2 - (1/pi) * atan((k1 + k2) / (k1 - k2))`` with ``k1 >= k2`` the principal curvatures of the
depth surface, SI in [0, 1].

Sign convention (Dorai & Jain's): curvatures are taken with the surface normal pointing towards the
camera, so a surface bulging towards the camera has negative curvatures. Hence

    convex cap (sphere seen from outside)     -> 1.0     concave cup (inside of a bowl) -> 0.0
    convex ridge (cylinder seen from outside) -> 0.75    concave rut (inside of a pipe) -> 0.25
    saddle (k1 = -k2)                         -> 0.5

Curvatures are metric and exact for a pinhole camera. The depth surface is the parametric surface
``P(s, t) = Z(s, t) * (x, y, 1)`` with ``s = u / fx``, ``t = v / fy`` and ``(x, y) = (s - cx/fx, t - cy/fy)``
the pixel's normalised ray. With the inverse depth ``w = 1 / Z`` (subscripts are derivatives)
``P_s x P_t`` is parallel to ``q = (w_s, w_t, w - x w_s - y w_t)`` and the second fundamental form is
``(w_ss, w_st, w_tt) / (w |q|)``, which gives

    a = (w - x w_s, -y w_s, -w_s),   b = (-x w_t, w - y w_t, -w_t)       (w^2 P_s = a, w^2 P_t = b)
    K = w^4 (w_ss w_tt - w_st^2) / |q|^4
    H = w (|a|^2 w_tt - 2 a.b w_st + |b|^2 w_ss) / (2 |q|^3)

Planes are linear in ``w`` and so have exactly zero curvature; this is also why the smoothing acts on
inverse depth (a Gaussian keeps a linear function linear). ``SI = 1/2 - atan2(H, sqrt(H^2 - K)) / pi``
is eq. (8) without the division by ``k1 - k2`` (``k1 - k2 = 2 sqrt(H^2 - K)``, ``k1 + k2 = 2 H``).

Speed: the map is computed on every ``decimate``-th pixel (default 2; Kinect-class depth has no
finer detail) and upsampled back linearly, so it costs a few milliseconds per 640x480 frame.

Invalid pixels: the smoothing is a normalised convolution over valid pixels only (0-depth never
bleeds in). Masked are: pixels whose smoothing window has less than ``min_support`` valid weight
or reaches a depth discontinuity (a neighbour step above ``max_step`` times the depth per pixel);
grazing pixels (normal more than ``max_incidence`` from the viewing ray); near-planar pixels
(curvedness ``sqrt((k1^2 + k2^2) / 2)`` below ``min_curvature``, in 1/m), where SI is undefined. Masked pixels carry ``fill`` (0.5, the middle of the range: the smallest possible step
to any neighbour in the SIM image).

References:
    C. Dorai, A. K. Jain, "COSMOS - A representation scheme for 3D free-form objects", PAMI 1997.
    J. J. Koenderink, A. J. van Doorn, "Surface shape and curvature scales", IVC 1992.
"""

from __future__ import annotations

import inspect
import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.filters import filter2d_separable
from kornia.filters.kernels import get_pascal_kernel_1d
from torch import Tensor

from torchtrack import ops


class ShapeIndex(NamedTuple):
    """Shape index map of a depth batch (all (B, 1, H, W), the input's grid).

    Attributes:
        si: float32 shape index in [0, 1] (eq. (8)); ``fill`` where not ``valid``.
        valid: bool, SI defined: depth valid, away from depth edges and holes, not near-planar.
        curvedness: float32 ``sqrt((k1^2 + k2^2) / 2)`` in 1/m (nearest-upsampled when decimated); 0 where
            depth or support is missing. None when not asked for.
    """

    si: Tensor
    valid: Tensor
    curvedness: Tensor | None


class SIM(NamedTuple):
    """What the per-frame pipeline needs from the depth: SI, its mask and its 8-bit-like image."""

    si: Tensor  # (B, 1, H, W) float32 in [0, 1]
    valid: Tensor  # (B, 1, H, W) bool
    image: Tensor  # (B, 1, H, W) float32 in [0, 1], multiples of 1/255, for LK and Harris


def _check(depth: Tensor, K: Tensor) -> None:
    if depth.dim() != 4 or depth.shape[1] != 1:
        raise ValueError(f"shape_index: depth must be (B, 1, H, W), got {tuple(depth.shape)}")
    if K.shape != (depth.shape[0], 3, 3):
        raise ValueError(f"shape_index: K must be ({depth.shape[0]}, 3, 3), got {tuple(K.shape)}")


def _binomial(x: Tensor, passes: int) -> Tensor:
    """Blur (B, C, h, w) by ``passes`` [1, 2, 1] / 4 filters along each axis (variance passes / 2), zero padding:
    pairs of passes as one [1, 4, 6, 4, 1] / 16 filter (Pascal kernels, kornia's separable correlation)."""
    for taps in [5] * (passes // 2) + [3] * (passes % 2):
        k = get_pascal_kernel_1d(taps, norm=True, device=x.device, dtype=x.dtype)[None]
        x = filter2d_separable(x, k, k, border_type="constant")
    return x


def _grow(mask: Tensor, radius: int) -> Tensor:
    """Dilate a float {0, 1} mask (..., h, w) by a (2 radius + 1)^2 square: box sums by cumulative sums."""
    if radius <= 0:
        return mask
    k = 2 * radius + 1
    c = F.pad(mask, (radius + 1, radius)).cumsum(-1)
    m = c[..., k:] - c[..., :-k]
    c = F.pad(m, (0, 0, radius + 1, radius)).cumsum(-2)
    return ((c[..., k:, :] - c[..., :-k, :]) > 0.5).to(mask.dtype)


def _depth_edges(z: Tensor, has: Tensor, max_step: float) -> Tensor:
    """Float {0, 1} (..., h, w): pixels with a valid 4-neighbour more than ``max_step * depth`` away."""
    dx = (z[..., 1:] - z[..., :-1]).abs() - max_step * torch.minimum(z[..., 1:], z[..., :-1])
    jx = (dx > 0).to(z.dtype) * has[..., 1:] * has[..., :-1]
    dy = (z[..., 1:, :] - z[..., :-1, :]).abs() - max_step * torch.minimum(z[..., 1:, :], z[..., :-1, :])
    jy = (dy > 0).to(z.dtype) * has[..., 1:, :] * has[..., :-1, :]
    jx, jy = F.pad(jx, (0, 1)), F.pad(jy, (0, 0, 0, 1))
    e = torch.maximum(jx, F.pad(jx, (1, 0))[..., :-1])
    return torch.maximum(e, torch.maximum(jy, F.pad(jy, (0, 0, 1, 0))[..., :-1, :]))


def _upsample(x: Tensor, d: int, H: int, W: int) -> Tensor:
    """Linear upsampling of samples taken at pixels (d i, d j) to the (H, W) grid (edge-clamped).

    A NaN sample makes every pixel that mixes it NaN; a pixel on a sample takes only that sample. Each axis writes
    its d phases into one output (no concatenated neighbour copies; lerp(a, a, t) = a at the clamped edge).
    """
    if d == 1:
        return x
    for axis in (-1, -2):
        n = x.shape[axis]
        # the phases of the interleaved output: ..., h, w, d (columns) or ..., h, d, W (rows)
        out = x.new_empty(*x.shape, d) if axis == -1 else x.new_empty(*x.shape[:-1], d, x.shape[-1])
        phases = out.unbind(-1) if axis == -1 else out.unbind(-2)
        phases[0].copy_(x)
        for k in range(1, d):
            dst = phases[k]
            torch.lerp(x.narrow(axis, 0, n - 1), x.narrow(axis, 1, n - 1), k / d, out=dst.narrow(axis, 0, n - 1))
            dst.narrow(axis, n - 1, 1).copy_(x.narrow(axis, n - 1, 1))
        x = out.reshape(*x.shape[:-1], -1) if axis == -1 else out.reshape(*x.shape[:-2], -1, x.shape[-1])
    return x[..., :H, :W]


def _curvatures(ws: Tensor, K: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Mean curvature H (1/m), Gaussian curvature K (1/m^2) and the cosine of the angle between the
    viewing ray and the normal, from smoothed inverse depth (B, h, w) on its grid with K (B, 3, 3)."""
    B, h, w = ws.shape
    p = F.pad(ws.unsqueeze(1), (1, 1, 1, 1), mode="replicate")[:, 0]
    c = p[:, 1:-1, 1:-1]
    l, r, up, dn = p[:, 1:-1, :-2], p[:, 1:-1, 2:], p[:, :-2, 1:-1], p[:, 2:, 1:-1]
    fx, fy = K[:, 0, 0].view(B, 1, 1), K[:, 1, 1].view(B, 1, 1)
    cx, cy = K[:, 0, 2].view(B, 1, 1), K[:, 1, 2].view(B, 1, 1)
    w_s, w_t = 0.5 * fx * (r - l), 0.5 * fy * (dn - up)  # d/ds = fx d/du
    c2x = 2 * c
    w_ss, w_tt = fx * fx * (r + l - c2x), fy * fy * (dn + up - c2x)
    w_st = 0.25 * fx * fy * (p[:, 2:, 2:] - p[:, 2:, :-2] - p[:, :-2, 2:] + p[:, :-2, :-2])
    x = (torch.arange(w, dtype=ws.dtype, device=ws.device).view(1, 1, w) - cx) / fx
    y = (torch.arange(h, dtype=ws.dtype, device=ws.device).view(1, h, 1) - cy) / fy
    xs, ys, xt, yt = x * w_s, y * w_s, x * w_t, y * w_t
    ax, by = c - xs, c - yt
    ws2, wt2 = w_s * w_s, w_t * w_t
    q2 = ws2 + wt2 + (ax - yt) ** 2
    aa = ax * ax + ys * ys + ws2
    bb = xt * xt + by * by + wt2
    ab = w_s * w_t - ax * xt - ys * by
    q = q2.sqrt()
    mean_c = c * (aa * w_tt - 2.0 * ab * w_st + bb * w_ss) / (2.0 * q2 * q)
    c2 = c * c
    gauss_c = c2 * c2 * (w_ss * w_tt - w_st * w_st) / (q2 * q2)
    cos_incidence = c / (q * (1.0 + x * x + y * y).sqrt())  # q . (x, y, 1) = w
    return mean_c, gauss_c, cos_incidence


def shape_index(
    depth: Tensor,
    K: Tensor,
    *,
    smooth_sigma: float = 4.0,
    min_curvature: float = 5.0,
    max_step: float = 0.05,
    min_support: float = 0.9999,
    max_incidence: float = 60.0,
    decimate: int = 2,
    fill: float = 0.5,
    curvedness: bool = True,
) -> ShapeIndex:
    """Shape index map of a depth batch, eq. (8). Conventions in the module docstring.

    Args:
        depth: (B, 1, H, W) metres, 0 = no measurement.
        K: (B, 3, 3) intrinsics of the depth image.
        smooth_sigma: Gaussian sigma (input pixels) of the normalised smoothing of inverse depth
            (a binomial filter of about this sigma); 0 = none.
        min_curvature: curvedness in 1/m below which a pixel is near-planar and masked
            (5 /m: flatter than a sphere of 0.2 m radius; with the default smoothing, the noise of
            Kinect-class depth on walls and floors stays mostly below it).
        max_step: a neighbour depth step above ``max_step * depth`` per input pixel is a
            discontinuity; pixels whose smoothing window reaches one are masked.
        min_support: masked where the smoothing window's valid weight is below this fraction. Nearly 1:
            a one-sided window shifts the estimate and fakes curvature on steep or curved surfaces.
        max_incidence: masked where the angle (degrees) between viewing ray and normal is larger
            (grazing surfaces: depth there is unreliable and the SI estimate breaks down).
        decimate: compute on every ``decimate``-th pixel and upsample linearly (1 = full resolution).
        fill: SI given to masked pixels.
        curvedness: also return the curvedness map (False: None, one full-resolution copy less).

    Returns:
        ShapeIndex(si, valid, curvedness), each (B, 1, H, W).
    """
    _check(depth, K)
    if decimate < 1:
        raise ValueError(f"shape_index: decimate must be >= 1, got {decimate}")
    B, _, H, W = depth.shape
    d = decimate
    z = depth[:, 0, ::d, ::d].float().contiguous()  # B,h,w samples at input pixels (d i, d j)
    Kd = K.to(z).clone()
    Kd[:, :2] /= d
    has_b = z > 0
    has = has_b.to(z.dtype)
    w = has / (z + (1.0 - has))  # inverse depth, 0 where missing

    passes = round(2.0 * (smooth_sigma / d) ** 2)
    support, ws = _binomial(torch.stack([has, w], dim=1), passes).unbind(1) if passes else (has, w)
    ws = ws / support.clamp_min(1e-6)  # >= 0
    ws.masked_fill_(ws <= 0, 1.0)  # 1 where nothing is known (masked anyway): no 0/0 and no sqrt(0) below
    edges = _grow(_depth_edges(z, has, max_step * d), passes + 1)  # the whole smoothing window
    ok = torch.zeros_like(has_b)  # boolean masks; False on the outer ring: the derivative stencils need both neighbours
    inner = (slice(None), slice(1, -1), slice(1, -1))
    ok[inner] = has_b[inner] & (support[inner] >= min_support) & (edges[inner] < 0.5)

    mean_c, gauss_c, cos_inc = _curvatures(ws, Kd)
    # (sqrt of exact 0 is a slow path of the vectorised CPU sqrt: clamp at 1e-30 instead)
    disc = (mean_c * mean_c - gauss_c).clamp_min(1e-30).sqrt()  # (k1 - k2) / 2
    si = 0.5 - torch.atan2(mean_c, disc) / math.pi  # eq. (8)
    curv = (2.0 * mean_c * mean_c - gauss_c).clamp_min(1e-30).sqrt()
    si_ok = ok & (curv >= min_curvature) & (cos_inc >= math.cos(math.radians(max_incidence)))
    curv = curv * ok if curvedness else None  # 0 where depth or support is missing
    si = torch.where(si_ok, si, math.nan)  # NaN marks masked samples through the upsampling

    si = _upsample(si, d, H, W)  # a pixel between samples is valid when all the samples it mixes are
    if curv is not None and d > 1:
        h, w = curv.shape[-2:]
        curv = curv[:, :, None, :, None].expand(B, h, d, w, d).reshape(B, h * d, w * d)[:, :H, :W]  # nearest
    valid = si == si  # not NaN
    curv = curv.unsqueeze(1) if curv is not None else None
    return ShapeIndex(si=si.nan_to_num(fill).unsqueeze(1), valid=valid.unsqueeze(1), curvedness=curv)


def sim_image(sim: ShapeIndex | Tensor, valid: Tensor | None = None, *, fill: float = 0.5) -> Tensor:
    """SIM as an 8-bit-like image for LK and Harris: (B, 1, H, W) float32 in [0, 1], multiples of 1/255.

    Args:
        sim: a ShapeIndex, or an SI tensor (B, 1, H, W) in [0, 1] (then ``valid`` may be given).
        valid: (B, 1, H, W) bool; pixels outside it get ``fill`` (quantised as well).
    """
    if isinstance(sim, ShapeIndex):
        si, valid = sim.si, sim.valid
    else:
        si = sim
    if si.dim() != 4 or si.shape[1] != 1:
        raise ValueError(f"sim_image: SI must be (B, 1, H, W), got {tuple(si.shape)}")
    if valid is not None:
        si = (si - fill) * valid + fill
    return (si.clamp(0.0, 1.0) * 255.0).round() / 255.0


# shape_index's keyword defaults (one place), for the operator's positional arguments
_SIM_DEFAULTS = {k: p.default for k, p in inspect.signature(shape_index).parameters.items() if p.kind == p.KEYWORD_ONLY}


def compute_sim(depth: Tensor, K: Tensor, **kwargs) -> SIM:
    """One call for the per-frame pipeline: ``shape_index(depth, K, **kwargs)`` and its ``sim_image``, as the compiled
    operator ``torch.ops.torchtrack.shape_index_map`` (csrc/sim.cpp, the same stages in one pass each) where it runs
    (:func:`torchtrack.ops.compiled`), else as :func:`compute_sim_reference`."""
    _check(depth, K)
    if not ops.compiled(depth):
        return compute_sim_reference(depth, K, **kwargs)
    if set(kwargs) - set(_SIM_DEFAULTS) | ({"curvedness"} & set(kwargs)):
        raise TypeError(f"compute_sim: unexpected arguments {sorted(kwargs)}")
    p = {**_SIM_DEFAULTS, **kwargs}
    si, valid, image = torch.ops.torchtrack.shape_index_map(
        depth.float().contiguous(), K.float().contiguous(), p["smooth_sigma"], p["min_curvature"], p["max_step"],
        p["min_support"], p["max_incidence"], p["decimate"], p["fill"],
    )  # fmt: skip
    return SIM(si=si, valid=valid, image=image)


def compute_sim_reference(depth: Tensor, K: Tensor, **kwargs) -> SIM:
    """:func:`compute_sim` by the functions above: the operator's reference, and the path on other devices.
    A batch is computed one image at a time (the same values within float error: other shapes sum in other orders;
    tests/tolerances.py): the temporaries of one 640x480 image stay in the CPU's
    cache, those of eight do not (measured at B=8: 52 ms instead of 75 ms per step)."""
    _check(depth, K)
    if depth.shape[0] > 1:
        parts = [compute_sim_reference(depth[i : i + 1], K[i : i + 1], **kwargs) for i in range(depth.shape[0])]
        return SIM(*(torch.cat(x) for x in zip(*parts, strict=True)))
    s = shape_index(depth, K, **kwargs, curvedness=False)
    image = (s.si * 255.0).round_().div_(255.0)  # SI and fill are in [0, 1]: sim_image without its clamp
    return SIM(si=s.si, valid=s.valid, image=image)


class ShapeIndexMap:
    """Holds the SIM parameters; ``__call__(depth, K) -> SIM`` delegates to ``compute_sim``."""

    def __init__(
        self,
        smooth_sigma: float = 4.0,
        min_curvature: float = 5.0,
        max_step: float = 0.05,
        min_support: float = 0.9999,
        max_incidence: float = 60.0,
        decimate: int = 2,
        fill: float = 0.5,
    ) -> None:
        self.kwargs = dict(
            smooth_sigma=smooth_sigma,
            min_curvature=min_curvature,
            max_step=max_step,
            min_support=min_support,
            max_incidence=max_incidence,
            decimate=decimate,
            fill=fill,
        )

    def __call__(self, depth: Tensor, K: Tensor) -> SIM:
        return compute_sim(depth, K, **self.kwargs)
