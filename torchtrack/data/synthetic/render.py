"""Analytic ray casting of a :class:`Scene`: exact depth and textured colour for every pixel.

Rays leave the camera centre along ``d = ((u - cx)/fx, (v - cy)/fy, 1)``, so the ray parameter of a
hit is its z-depth. Each primitive is intersected in its local frame (rigid transforms keep the ray
parameter), vectorised over all rays of the primitive's screen-space bounding box; a z-buffer keeps
the nearest hit. Colour is evaluated once per pixel, for the primitive it sees (a Python loop over
primitives, never over pixels).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.data.synthetic.scene import Primitive, Scene, pixel_rays
from torchtrack.data.synthetic.texture import (
    batch_textures,
    light_local,
    plane_rgb,
    shade,
    surface_uv_normal,
    texture_rgb,
)
from torchtrack.geometry import T_inv

_EPS = 1e-6
_INF = float("inf")


class RGBD(NamedTuple):
    """rgb: (3, H, W) or (B, 3, H, W) in [0, 1]; depth: (1, H, W) or (B, 1, H, W) metres, 0 = no surface."""

    rgb: Tensor
    depth: Tensor


class RayHits(NamedTuple):
    """Nearest hit per ray: depth (...) metres (0 = none) and primitive index (...) (-1 = none)."""

    depth: Tensor
    prim: Tensor


# Intersections in the primitive's local frame: rays o + t d with origin o (3 floats) and directions
# d = (dx, dy, dz), each (h, w); they return the nearest t > 0 per ray, inf where it misses.


def _hit_plane(o: list[float], d: tuple[Tensor, Tensor, Tensor], s: tuple[float, ...]) -> Tensor:
    """Rectangle z = 0, |x| <= s[0], |y| <= s[1]. Overwrites d (temporaries of the caller)."""
    dx, dy, dz = d
    t = dz.reciprocal_().mul_(-o[2])  # dz is a temporary of the caller: reuse its memory
    hit = t > _EPS
    for oi, di, si in ((o[0], dx, s[0]), (o[1], dy, s[1])):
        w = di.mul_(t)  # |o + t d| <= s on both in-plane axes
        hit &= (w >= -si - oi) & (w <= si - oi)
    return t.masked_fill_(~hit, _INF)


def _hit_sphere(o: list[float], d: tuple[Tensor, Tensor, Tensor], s: tuple[float, ...]) -> Tensor:
    """Sphere of radius s[0] about the origin: the near root of |o + t d|^2 = r^2."""
    dx, dy, dz = (c.double() for c in d)  # quadrics cancel badly near silhouettes in float32
    a = dx * dx + dy * dy + dz * dz
    b = o[0] * dx + o[1] * dy + o[2] * dz
    c = o[0] ** 2 + o[1] ** 2 + o[2] ** 2 - s[0] ** 2
    disc = b * b - a * c
    t = (-b - disc.clamp_min(0).sqrt()) / a
    return torch.where((disc >= 0) & (t > _EPS), t, _INF).float()


def _hit_box(o: list[float], d: tuple[Tensor, Tensor, Tensor], s: tuple[float, ...]) -> Tensor:
    """Box |x| <= s[0], |y| <= s[1], |z| <= s[2] (Kay-Kajiya slabs)."""
    t_near, t_far = None, None
    for oi, di, hi in zip(o, d, s, strict=True):  # slab method, one axis at a time
        inv = 1.0 / di
        t1, t2 = (-hi - oi) * inv, (hi - oi) * inv
        lo, hi_ = torch.minimum(t1, t2), torch.maximum(t1, t2)
        t_near = lo if t_near is None else torch.maximum(t_near, lo)
        t_far = hi_ if t_far is None else torch.minimum(t_far, hi_)
    return torch.where((t_near <= t_far) & (t_near > _EPS), t_near, _INF)


def _hit_cylinder(o: list[float], d: tuple[Tensor, Tensor, Tensor], s: tuple[float, ...]) -> Tensor:
    """Capped cylinder x^2 + y^2 <= s[0]^2, |z| <= s[1]: nearer of the side and the cap facing o."""
    r, hh = s
    dx, dy, dz = (c.double() for c in d)
    a = dx * dx + dy * dy
    b = o[0] * dx + o[1] * dy
    c = o[0] ** 2 + o[1] ** 2 - r * r
    disc = b * b - a * c
    ts = (-b - disc.clamp_min(0).sqrt()) / a
    side = (disc >= 0) & (ts > _EPS) & ((o[2] + ts * dz).abs() <= hh)
    t = torch.where(side, ts, _INF)
    cap_z = hh if o[2] > 0 else -hh  # the only cap visible from outside
    tc = (cap_z - o[2]) / dz
    cap = (tc > _EPS) & ((o[0] + tc * dx) ** 2 + (o[1] + tc * dy) ** 2 <= r * r) & (tc < t)
    return torch.where(cap, tc, t).float()


_HIT = {"plane": _hit_plane, "sphere": _hit_sphere, "box": _hit_box, "cylinder": _hit_cylinder}


class _PrimPoses(NamedTuple):
    """Camera-to-primitive transforms of all primitives: T (P, 4, 4) float64, and R, o as Python floats."""

    T: Tensor
    R: list[list[list[float]]]
    o: list[list[float]]


def _T_prim_cam(scene: Scene, T_world_cam: Tensor, T_world_obj: Tensor | None) -> _PrimPoses:
    """Per primitive camera-to-primitive transforms, batched (one transform chain for all primitives)."""
    groups = [p.group for p in scene.primitives]
    if T_world_obj is None and 1 in groups:
        raise ValueError("render: the scene has a moving object (group 1) but T_world_obj was not given")
    T_cam_world = T_inv(T_world_cam.double())
    T_world_group1 = torch.eye(4, dtype=torch.float64, device="cpu") if T_world_obj is None else T_world_obj.double()
    group = torch.tensor(groups, dtype=torch.long, device="cpu")
    T_cam_group = torch.stack([T_cam_world, T_cam_world @ T_world_group1])[group]
    T = T_inv(T_cam_group @ torch.stack([p.T_group_prim.double() for p in scene.primitives]))
    T_list = T.tolist()
    return _PrimPoses(T, [[row[:3] for row in Tk[:3]] for Tk in T_list], [[row[3] for row in Tk[:3]] for Tk in T_list])


_NEAR = 1e-3


def _local_box(prim: Primitive) -> list[float]:
    """Half extents of the primitive's local bounding box."""
    s = prim.size
    if prim.kind == "plane":
        return [s[0], s[1], 0.0]
    if prim.kind == "cylinder":
        return [s[0], s[0], s[1]]
    return [s[0]] * 3 if prim.kind == "sphere" else list(s)


_SIGNS = torch.tensor(
    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64, device="cpu"
)


def _screen_boxes(scene: Scene, T_pc: Tensor) -> list[tuple[int, int, int, int] | None]:
    """Per primitive a conservative pixel rectangle (v0, v1, u0, u1) covering it; None if it cannot be seen.

    Each local bounding box is clipped against the plane z = _NEAR in the camera (the clipped convex
    hull is spanned by the corners in front and the crossings of all corner pairs), then projected.
    Planes are one-sided: seen from behind (camera at local z <= 0) they are culled. Batched over primitives.
    """
    T_cp = T_inv(T_pc)  # P,4,4 primitive -> camera
    half = torch.tensor([_local_box(p) for p in scene.primitives], dtype=torch.float64, device="cpu")  # P,3
    pts = (_SIGNS * half[:, None]) @ T_cp[:, :3, :3].transpose(1, 2) + T_cp[:, None, :3, 3]  # P,8,3 corners
    a, b = pts[:, :, None], pts[:, None, :]  # crossings of every corner pair with z = _NEAR
    w = ((_NEAR - a[..., 2]) / (b[..., 2] - a[..., 2])).nan_to_num(-1.0)
    cross = (a + w[..., None] * (b - a)).flatten(1, 2)  # P,64,3
    use = torch.cat([pts[..., 2] > _NEAR, ((w > 0) & (w < 1)).flatten(1)], dim=1)  # P,72
    pts = torch.cat([pts, cross], dim=1)
    z = torch.where(use, pts[..., 2], 1.0)
    K = scene.K.double()
    u = (K[0, 0] * pts[..., 0] / z + K[0, 2]).clamp(-1e6, 1e6)
    v = (K[1, 1] * pts[..., 1] / z + K[1, 2]).clamp(-1e6, 1e6)
    big = torch.tensor(1e7, dtype=torch.float64, device="cpu")
    lo_u, hi_u = torch.where(use, u, big).amin(1), torch.where(use, u, -big).amax(1)
    lo_v, hi_v = torch.where(use, v, big).amin(1), torch.where(use, v, -big).amax(1)
    backface = torch.tensor([p.kind == "plane" for p in scene.primitives], device="cpu") & (T_pc[:, 2, 3] <= 0)
    seen = use.any(1) & ~backface
    boxes: list[tuple[int, int, int, int] | None] = []
    for ok, u0, u1, v0, v1 in zip(
        seen.tolist(), lo_u.tolist(), hi_u.tolist(), lo_v.tolist(), hi_v.tolist(), strict=True
    ):
        u0, u1 = max(0, int(u0) - 1), min(scene.width, int(u1) + 2)
        v0, v1 = max(0, int(v0) - 1), min(scene.height, int(v1) + 2)
        boxes.append((v0, v1, u0, u1) if ok and u0 < u1 and v0 < v1 else None)
    return boxes


def _local_dirs(scene: Scene, R: list[list[float]], box: tuple[int, int, int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """Rays of the pixel rectangle box rotated by R (3, 3): three (h, w) components.

    Separable: R @ (x_u, y_v, 1) = (R[:, 0] x_u + R[:, 2]) + R[:, 1] y_v, one broadcast add per component.
    """
    v0, v1, u0, u1 = box
    xs, ys = scene.ray_xy()
    xs, ys = xs[u0:u1], ys[v0:v1]
    return tuple((xs * R[i][0] + R[i][2])[None, :] + (ys * R[i][1])[:, None] for i in range(3))


def _cast(scene: Scene, poses: _PrimPoses, dirs: Tensor | None) -> tuple[Tensor, Tensor]:
    """Z-buffer over primitives -> t (h, w) (inf = miss), prim index (h, w) (-1 = miss).

    dirs None: the full image grid, each primitive restricted to its screen box. Else rays (1, n, 3).
    """
    h, w = (scene.height, scene.width) if dirs is None else dirs.shape[:2]
    zbuf = torch.full((h, w), _INF, device="cpu")
    ids = torch.full((h, w), -1, dtype=torch.int16, device="cpu")  # small ints: cheaper z-buffer writes
    boxes = _screen_boxes(scene, poses.T) if dirs is None else None
    for k, prim in enumerate(scene.primitives):
        if boxes is not None:
            box = boxes[k]
            if box is None:
                continue
            d_local = _local_dirs(scene, poses.R[k], box)
        else:
            box = (0, h, 0, w)
            d_local = tuple(c.contiguous() for c in (dirs @ poses.T[k, :3, :3].float().T).unbind(-1))
        v0, v1, u0, u1 = box
        t = _HIT[prim.kind](poses.o[k], d_local, prim.size)
        zc, ic = zbuf[v0:v1, u0:u1], ids[v0:v1, u0:u1]
        closer = t < zc
        torch.minimum(zc, t, out=zc)
        ic.masked_fill_(closer, k)
    return zbuf, ids.long()


def _colour(scene: Scene, poses: _PrimPoses, dx: Tensor, dy: Tensor, t: Tensor, ids: Tensor) -> Tensor:
    """Shaded texture colour (n, 3) of hits at depth t (n,) on primitives ids (n,) along rays (dx, dy, 1).

    Planes read their baked atlas; all other primitives are textured together in one call.
    """
    rgb = torch.tensor(scene.background_rgb, device="cpu")[None].repeat(t.shape[0], 1)  # rows: contiguous scatter
    small = torch.int8 if len(scene.primitives) < 127 else torch.int32  # small ints sort fastest
    order = torch.sort(ids.to(small), stable=True).indices  # pixels grouped by primitive, one pass
    counts = torch.bincount(ids + 1, minlength=len(scene.primitives) + 1).tolist()
    groups = order.split(counts)
    light = light_local(scene)
    solids: list[tuple[int, Tensor, Tensor, Tensor, Tensor | float]] = []
    for k, prim in enumerate(scene.primitives):
        idx = groups[k + 1]
        if idx.numel() == 0:
            continue
        z = t.index_select(0, idx)
        x, y = dx.index_select(0, idx).mul_(z), dy.index_select(0, idx).mul_(z)  # hit in the camera
        R, o = poses.R[k], poses.o[k]
        if prim.kind == "plane":  # atlas grid: local (u / hx, v / hy)
            s = [1.0 / prim.size[0], 1.0 / prim.size[1]]
            uv = [(R[i][0] * s[i]) * x + (R[i][1] * s[i]) * y + (R[i][2] * s[i]) * z + o[i] * s[i] for i in range(2)]
            lit = shade(scene, (0.0, 0.0, 1.0), light[k])
            rgb.index_copy_(0, idx, plane_rgb(scene, k, torch.stack(uv, dim=-1)).mul_(lit))
        else:
            p_local = tuple(R[i][0] * x + R[i][1] * y + R[i][2] * z + o[i] for i in range(3))
            (u, v), n_local = surface_uv_normal(prim, p_local)
            solids.append((k, idx, u, v, shade(scene, n_local, light[k])))
    if solids:
        ks, idx, u, v, lit = zip(*solids, strict=True)
        sizes = torch.tensor([len(i) for i in idx], device="cpu")
        which = torch.repeat_interleave(torch.tensor(ks, device="cpu"), sizes)
        tex = batch_textures([p.texture for p in scene.primitives], which)
        albedo = texture_rgb(scene, tex, torch.cat(u), torch.cat(v))
        lit = torch.cat([torch.as_tensor(x, device="cpu").expand(len(i)) for x, i in zip(lit, idx, strict=True)])
        rgb.index_copy_(0, torch.cat(idx), torch.stack(albedo, dim=1) * lit[:, None])
    return rgb.clamp_(0, 1)


def _render_one(scene: Scene, T_world_cam: Tensor, T_world_obj: Tensor | None, pixels: Tensor | None):
    """-> rgb (3, h, w), depth (h, w), prim index (h, w); (h, w) = (H, W) or (1, N) for given pixels (N, 2)."""
    poses = _T_prim_cam(scene, T_world_cam, T_world_obj)
    dirs = None if pixels is None else pixel_rays(scene.K, pixels.float())[None]
    t, ids = _cast(scene, poses, dirs)
    h, w = t.shape
    if pixels is None:
        dx, dy = scene.ray_xy_flat()
    else:
        dx, dy = dirs[0, :, 0].contiguous(), dirs[0, :, 1].contiguous()
    rgb = _colour(scene, poses, dx, dy, t.reshape(-1), ids.reshape(-1))
    depth = torch.where(ids >= 0, t, torch.zeros_like(t))
    return rgb.reshape(h, w, 3).permute(2, 0, 1).contiguous(), depth, ids


def _check_pose(name: str, T: Tensor | None) -> None:
    if T is not None and (T.shape[-2:] != (4, 4) or T.dim() not in (2, 3)):
        raise ValueError(f"render: {name} must be (4, 4) or (B, 4, 4), got {tuple(T.shape)}")


def render_frame(scene: Scene, T_world_cam: Tensor, T_world_obj: Tensor | None = None) -> RGBD:
    """Noise-free colour and depth of the scene seen from T_world_cam.

    Args:
        scene: primitives and intrinsics (``default_scene(cfg)``).
        T_world_cam: (4, 4) or (B, 4, 4) camera-to-world pose(s).
        T_world_obj: pose(s) of the moving group (object mode), same batch shape; None for static scenes.
    Returns:
        RGBD with rgb (3, H, W) / (B, 3, H, W) in [0, 1] and depth (1, H, W) / (B, 1, H, W) exact z-depth
        in metres, 0 where no surface is hit. Batches loop over B (each frame is already vectorised).
    A frame is many small operations: one torch thread (``torch.set_num_threads(1)``) is fastest on a
    shared machine (``render_sequence`` does this by default).
    """
    _check_pose("T_world_cam", T_world_cam)
    _check_pose("T_world_obj", T_world_obj)
    if T_world_cam.dim() == 3:
        objs = [None] * len(T_world_cam) if T_world_obj is None else list(T_world_obj)
        outs = [render_frame(scene, Tc, To) for Tc, To in zip(T_world_cam, objs, strict=True)]
        return RGBD(torch.stack([o.rgb for o in outs]), torch.stack([o.depth for o in outs]))
    rgb, depth, _ = _render_one(scene, T_world_cam, T_world_obj, None)
    return RGBD(rgb, depth[None])


def render_pixels(
    scene: Scene, T_world_cam: Tensor, pixels: Tensor, T_world_obj: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Colour (N, 3) and depth (N,) along the rays of arbitrary sub-pixel positions pixels (N, 2) (x, y)."""
    if pixels.dim() != 2 or pixels.shape[-1] != 2:
        raise ValueError(f"render_pixels: pixels must be (N, 2), got {tuple(pixels.shape)}")
    rgb, depth, _ = _render_one(scene, T_world_cam, T_world_obj, pixels)
    return rgb[:, 0].T, depth[0]


def raycast(scene: Scene, T_world_cam: Tensor, T_world_obj: Tensor | None = None) -> RayHits:
    """Depth (H, W) and primitive index (H, W) of the nearest surface, without shading."""
    t, ids = _cast(scene, _T_prim_cam(scene, T_world_cam, T_world_obj), None)
    return RayHits(torch.where(ids >= 0, t, torch.zeros_like(t)), ids)
