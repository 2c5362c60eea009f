"""Procedural surface textures and shading, evaluated at ray hits in primitive-local coordinates.

Every colour is a function of the hit point in the primitive's own frame (and of the normal in its
rigid group's frame), so texture and shading move rigidly with the surface: a point seen in two
frames has exactly the same colour in both. Edges are linear ramps ``EDGE_M`` metres wide (about a
pixel at 1.5 m), which keeps the images free of aliasing and Lucas-Kanade-friendly.

Tensors are structure-of-arrays, one contiguous (n,) tensor per coordinate or channel: on CPU this
is several times faster than (n, 3) layouts for long chains of element-wise operations.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict

import torch
import torch.nn.functional as F
from torch import Tensor

from torchtrack.data.synthetic.scene import Primitive, Scene, TextureParams

EDGE_M = 0.003
ATLAS_TEXEL_M = 0.004  # planes' textures are baked once per scene at this resolution, or one pixel at
ATLAS_TEXEL_PX_AT_M = 2.0  # this distance (metres) for low-resolution cameras, whichever is coarser

Vec3 = tuple[Tensor | float, Tensor | float, Tensor | float]


def surface_uv_normal(prim: Primitive, p: tuple[Tensor, Tensor, Tensor]) -> tuple[tuple[Tensor, Tensor], Vec3]:
    """Local hit points p = (x, y, z), each (n,) -> surface coordinates (u, v) in metres and local unit normal.

    Planes use (x, y). Boxes and spheres are cube-mapped: the two coordinates orthogonal to the dominant
    axis of p / half-size, shifted per face so that the six faces differ. Cylinders use (arc length, z)
    on the side and (x, y) on the caps.
    """
    x, y, z = p
    s = prim.size
    if prim.kind == "plane":
        return (x, y), (0.0, 0.0, 1.0)
    if prim.kind == "cylinder":
        r, hh = s
        rho = torch.sqrt(x * x + y * y)
        cap = ((z.abs() - hh).abs() < (rho - r).abs()).float()
        zsign = torch.sign(z)
        u = torch.lerp(r * torch.atan2(y, x), x + 7.3 * zsign, cap)  # caps shifted off the side's coordinates
        v = torch.lerp(z, y + 7.3 * zsign, cap)
        inv = (1 - cap) / rho.clamp_min(1e-9)
        return (u, v), (x * inv, y * inv, cap * zsign)
    hx, hy, hz = s * 3 if prim.kind == "sphere" else s
    ax, ay, az = (x / hx).abs(), (y / hy).abs(), (z / hz).abs()
    on_x = (ax >= ay) & (ax >= az)
    on_z = ~on_x & (az >= ay)
    q = torch.where(on_x, x / hx, torch.where(on_z, z / hz, y / hy))  # signed coordinate along the face axis
    face = torch.where(on_x, 0.0, torch.where(on_z, 4.0, 2.0)) + (q > 0).float()  # 0..5
    u = torch.where(on_x, y, x) + 3.7 * face
    v = torch.where(on_z, y, z) + 5.3 * face
    if prim.kind == "sphere":
        return (u, v), (x / hx, y / hx, z / hx)
    sign = torch.sign(q)
    return (u, v), (on_x * sign, (~on_x & ~on_z) * sign, on_z * sign)


def _wrap(g: Tensor, T: int) -> Tensor:
    """g mod T for float tensors (cheaper than ``remainder``)."""
    return g - T * torch.floor(g * (1.0 / T))


def value_noise(table: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Smooth value noise in [0, 1] at lattice coordinates (u, v), each (n,), from a periodic (T, T) table.

    Smoothstep interpolation between lattice values (C1 across cells), done by one bilinear
    ``grid_sample`` at the smoothstep-remapped coordinate floor(g) + s(frac(g)).
    """
    T = table.shape[0]
    padded = torch.cat([table, table[:1]], 0)
    padded = torch.cat([padded, padded[:, :1]], 1)[None, None]  # 1,1,T+1,T+1 with wrap-around

    def remap(g: Tensor) -> Tensor:
        g = _wrap(g, T)
        g0 = torch.floor(g)
        f = g - g0
        return (g0 + f * f * (3 - 2 * f)) * (2.0 / T) - 1.0

    grid = torch.stack([remap(v), remap(u)], dim=-1)[None, None]  # grid_sample: x = column (v), y = row (u)
    return F.grid_sample(padded, grid, mode="bilinear", align_corners=True).reshape(-1)


def _ramp(x: Tensor, scale: float) -> Tensor:
    """Anti-aliased step: 0 below -EDGE_M/2, 1 above +EDGE_M/2 (x in units of 1/scale metres)."""
    return (x * (scale / EDGE_M) + 0.5).clamp_(0, 1)


def _cells(scene: Scene, tex: TextureParams, u: Tensor, v: Tensor) -> tuple[Tensor, list[Tensor]]:
    """Per texture cell a random rectangle, a blob or nothing -> mask (n,), colour 3 x (n,)."""
    T = scene.lattice.shape[0]
    gu, gv = u * (1.0 / tex.cell_m), v * (1.0 / tex.cell_m)
    iu, iv = torch.floor(gu), torch.floor(gv)
    fu, fv = gu - iu, gv - iv  # position inside the cell in [0, 1)
    idx = _wrap(iu + tex.cell_offset[0], T) * T + _wrap(iv + tex.cell_offset[1], T)
    h = scene.lattice.reshape(T * T, -1).index_select(0, idx.long()).T  # 8,n (strided rows)
    lo_u, lo_v = 0.08 + 0.3 * h[1], 0.08 + 0.3 * h[2]
    c = tex.cell_m
    rect = _ramp(fu - lo_u, c) * _ramp(lo_u + (0.2 + 0.35 * h[3]) - fu, c)
    rect = rect * _ramp(fv - lo_v, c) * _ramp(lo_v + (0.2 + 0.35 * h[4]) - fv, c)
    du, dv = fu - (0.35 + 0.3 * h[1]), fv - (0.35 + 0.3 * h[2])
    blob = (1 - (du * du + dv * dv) / (0.15 + 0.2 * h[3]) ** 2).clamp_(min=0) ** 3  # compact Gaussian-like bump
    mask = torch.where(h[0] < 0.35, rect, torch.where(h[0] < 0.7, blob, 0.0))
    return mask, [h[5], h[6], h[7]]


def batch_textures(texs: list[TextureParams], which: Tensor) -> TextureParams:
    """Per-point texture parameters: fields become (n,) tensors, point i taking texs[which[i]].

    Lets :func:`texture_rgb` shade the points of many primitives in one call (fewer, longer ops).
    """
    rows = [
        [*t.c0, *t.c1, *t.c2, t.noise_m, t.checker_m if t.checker_m > 0 else 1.0,
         t.checker_weight if t.checker_m > 0 else 0.0, t.cell_m, *t.cell_offset, *t.uv_offset]
        for t in texs
    ]  # fmt: skip
    c = torch.tensor(rows, dtype=torch.float32, device=which.device).index_select(0, which).T.contiguous()  # 17,n
    return TextureParams(
        c0=(c[0], c[1], c[2]), c1=(c[3], c[4], c[5]), c2=(c[6], c[7], c[8]), noise_m=c[9], checker_m=c[10],
        checker_weight=c[11], cell_m=c[12], cell_offset=(c[13], c[14]), uv_offset=(c[15], c[16]),
    )  # fmt: skip


def texture_rgb(scene: Scene, tex: TextureParams, u: Tensor, v: Tensor) -> list[Tensor]:
    """Albedo, 3 channels x (n,) in [0, 1], at surface coordinates (u, v), each (n,) metres.

    Value noise between colours c0 and c1, a soft checker in c2, and per-cell rectangles and blobs.
    ``tex`` holds python numbers (one primitive) or (n,) tensors (:func:`batch_textures`).
    """
    u, v = u + tex.uv_offset[0], v + tex.uv_offset[1]
    s = 1.0 / tex.noise_m
    n = 0.65 * value_noise(scene.noise, u * s, v * s) + 0.35 * value_noise(scene.noise, u * (s / 0.3), v * (s / 0.3))
    col = [a + (b - a) * n for a, b in zip(tex.c0, tex.c1, strict=True)]
    if isinstance(tex.checker_m, Tensor) or (tex.checker_m > 0 and tex.checker_weight > 0):
        k, w = tex.checker_m / (math.pi * EDGE_M), math.pi / tex.checker_m
        chk = (torch.sin(u * w) * k).clamp_(-1, 1) * (torch.sin(v * w) * k).clamp_(-1, 1)  # soft checker in [-1, 1]
        wgt = (chk + 1) * (0.5 * tex.checker_weight)
        col = [ch + (c2 - ch) * wgt for ch, c2 in zip(col, tex.c2, strict=True)]
    mask, colour = _cells(scene, tex, u, v)
    return [torch.lerp(ch, cc, mask) for ch, cc in zip(col, colour, strict=True)]


_ATLAS_CACHE: OrderedDict[str, Tensor] = OrderedDict()  # baked atlases shared by equal scenes (same seed)
_ATLAS_CACHE_SIZE = 16
ATLAS_MAX_TEXELS = 2048  # per side; larger planes get coarser texels


def _atlas_texel(scene: Scene) -> float:
    return max(ATLAS_TEXEL_M, ATLAS_TEXEL_PX_AT_M / float(scene.K[0, 0]))


def _atlas_key(scene: Scene, prim: Primitive) -> str:
    h = hashlib.sha1(repr((prim.size, prim.texture, EDGE_M, _atlas_texel(scene), ATLAS_MAX_TEXELS)).encode())
    h.update(scene.lattice.numpy().tobytes())
    h.update(scene.noise.numpy().tobytes())
    return h.hexdigest()


def plane_atlas(scene: Scene, k: int) -> Tensor:
    """(1, 3, Ht, Wt) albedo of plane primitive k baked on a regular grid over its rectangle (cached).

    Texel (i, j) holds ``texture_rgb`` at u = -hx + j * 2hx / (Wt - 1), v = -hy + i * 2hy / (Ht - 1), so
    ``grid_sample(atlas, (u / hx, v / hy), align_corners=True)`` is a fixed function of the surface
    point: rendering stays exactly rigid, at the cost of bilinear interpolation over ATLAS_TEXEL_M texels
    (coarser for low-resolution cameras, like a mip-map, and for planes wider than ATLAS_MAX_TEXELS
    texels). Baked once per distinct plane, texture and texel size.
    """
    if k in scene._atlas:
        return scene._atlas[k]
    prim = scene.primitives[k]
    key = _atlas_key(scene, prim)
    if key not in _ATLAS_CACHE:
        hx, hy = prim.size
        texel = _atlas_texel(scene)
        Wt = min(math.ceil(2 * hx / texel) + 1, ATLAS_MAX_TEXELS)
        Ht = min(math.ceil(2 * hy / texel) + 1, ATLAS_MAX_TEXELS)
        u = torch.linspace(-hx, hx, Wt, device="cpu")
        rows = []
        for v in torch.linspace(-hy, hy, Ht, device="cpu").split(256):  # chunks of rows bound the memory
            uu, vv = u.repeat(len(v)), v.repeat_interleave(Wt)
            rows.append(torch.stack(texture_rgb(scene, prim.texture, uu, vv)).reshape(3, len(v), Wt))
        _ATLAS_CACHE[key] = torch.cat(rows, dim=1)[None].contiguous(memory_format=torch.channels_last)  # fast reads
        while len(_ATLAS_CACHE) > _ATLAS_CACHE_SIZE:
            _ATLAS_CACHE.popitem(last=False)
    _ATLAS_CACHE.move_to_end(key)
    scene._atlas[k] = _ATLAS_CACHE[key]
    return scene._atlas[k]


def plane_rgb(scene: Scene, k: int, uv_unit: Tensor) -> Tensor:
    """Albedo (n, 3) of plane primitive k read from its baked atlas at (u / hx, v / hy) in [-1, 1], (n, 2)."""
    out = F.grid_sample(plane_atlas(scene, k), uv_unit[None, None], mode="bilinear", align_corners=True)  # 1,3,1,n
    return out.permute(0, 2, 3, 1).reshape(-1, 3)


def light_local(scene: Scene) -> list[list[float]]:
    """Per primitive the unit light direction in its local frame (light is fixed in each rigid group)."""
    light = torch.tensor(scene.light_dir, dtype=torch.float64, device="cpu")
    R = torch.stack([p.T_group_prim[:3, :3].double() for p in scene.primitives])  # P,3,3 group <- local
    return (R.transpose(1, 2) @ (light / light.norm())).tolist()


def shade(scene: Scene, normal_local: Vec3, light: list[float]) -> Tensor | float:
    """Lambert factor (n,) for unit local normals: ambient + (1 - ambient) max(0, n . l), l local (light_local)."""
    cos = normal_local[0] * light[0] + normal_local[1] * light[1] + normal_local[2] * light[2]
    if isinstance(cos, float):
        return scene.ambient + (1 - scene.ambient) * max(cos, 0.0)
    return scene.ambient + (1 - scene.ambient) * cos.clamp_min(0)
