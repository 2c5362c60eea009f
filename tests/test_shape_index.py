"""Shape Index Map (eq. 8): analytic surfaces rendered as depth by closed-form ray intersection.

Convention under test: convex cap -> 1, convex ridge -> 0.75, saddle -> 0.5, concave rut -> 0.25,
concave cup -> 0 (normal towards the camera, Dorai & Jain).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch
from tolerances import F32_UNIT

from torchtrack.image.shape_index import (
    SIM,
    ShapeIndex,
    ShapeIndexMap,
    compute_sim,
    compute_sim_reference,
    shape_index,
    sim_image,
)

H, W, FOCAL, CX, CY = 480, 640, 525.0, 319.5, 239.5
TOL = 0.05  # the bound on interior pixels


def K1(f=FOCAL, cx=CX, cy=CY) -> torch.Tensor:
    return torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])[None]


def rays(f=FOCAL, cx=CX, cy=CY):
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    return (u - cx) / f, (v - cy) / f


def sphere(zc: float, r: float, far: bool = False, **kw) -> torch.Tensor:
    """z-depth of the sphere |p - (0, 0, zc)| = r along each pixel ray (near or far intersection), 0 = miss."""
    x, y = rays(**kw)
    a = x * x + y * y + 1.0
    disc = zc * zc - a * (zc * zc - r * r)
    t = (zc + (1 if far else -1) * disc.clamp_min(0).sqrt()) / a
    return torch.where(disc > 0, t, torch.zeros_like(t))


def cylinder(zc: float, r: float, far: bool = False, **kw) -> torch.Tensor:
    """z-depth of the cylinder x^2 + (z - zc)^2 = r^2 (axis along the image y axis)."""
    x, _ = rays(**kw)
    a = x * x + 1.0
    disc = zc * zc - a * (zc * zc - r * r)
    t = (zc + (1 if far else -1) * disc.clamp_min(0).sqrt()) / a
    return torch.where(disc > 0, t, torch.zeros_like(t))


def saddle(z0: float, r: float, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """z-depth of Z = z0 + (X^2 - Y^2) / (2 r) and its exact SI per pixel (closed form of the graph surface)."""
    x, y = rays(**kw)
    a = (x * x - y * y) / (2 * r)
    z = 2 * z0 / (1 + (1 - 4 * a * z0).clamp_min(0).sqrt())  # root of a Z^2 - Z + z0 = 0 near z0
    X, Y = x * z, y * z
    fx, fy, fxx, fyy = X / r, -Y / r, 1 / r, -1 / r
    g = 1 + fx * fx + fy * fy
    h_up = ((1 + fy * fy) * fxx + (1 + fx * fx) * fyy) / (2 * g**1.5)  # normal away from the camera
    k = fxx * fyy / g**2
    si = 0.5 - torch.atan2(-h_up, (h_up * h_up - k).clamp_min(0).sqrt()) / math.pi  # normal towards the camera
    return z, si


def incidence_deg(z: torch.Tensor, **kw) -> torch.Tensor:
    """Angle between the viewing ray and the surface normal (finite differences of the exact points)."""
    x, y = rays(**kw)
    P = torch.stack([x * z, y * z, z])
    n = torch.linalg.cross(P[:, 1:-1, 2:] - P[:, 1:-1, :-2], P[:, 2:, 1:-1] - P[:, :-2, 1:-1], dim=0)
    r = torch.stack([x, y, torch.ones_like(x)])[:, 1:-1, 1:-1]
    c = (n * r).sum(0).abs() / (n.norm(dim=0) * r.norm(dim=0))
    out = torch.full_like(z, 90.0)
    out[1:-1, 1:-1] = torch.rad2deg(torch.acos(c.clamp(max=1.0)))
    return out


def erode(mask: torch.Tensor, margin: int) -> torch.Tensor:
    """Pixels at least ``margin`` px (square) inside ``mask`` (H, W) and the image."""
    m = np.zeros(mask.shape, np.uint8)
    m[margin:-margin, margin:-margin] = mask.numpy()[margin:-margin, margin:-margin]
    return torch.from_numpy(cv2.erode(m, np.ones((2 * margin + 1,) * 2, np.uint8)) > 0)


def interior(z: torch.Tensor, margin: int = 20, max_deg: float = 55.0) -> torch.Tensor:
    """Pixels at least ``margin`` px inside the surface's silhouette/image and facing the camera within max_deg."""
    return erode(z > 0, margin) & (incidence_deg(z) < max_deg)


def as_depth(z: torch.Tensor) -> torch.Tensor:
    return z.float()[None, None]


# ---------------------------------------------------------------------------------------------- smoke/shape
@pytest.mark.equivalence
def test_shapes_dtypes_and_range():
    d = torch.stack([as_depth(sphere(0.8, 0.15))[0], as_depth(cylinder(0.8, 0.1))[0]])
    K = K1().expand(2, 3, 3)
    s = shape_index(d, K)
    assert isinstance(s, ShapeIndex)
    assert s.si.shape == s.valid.shape == s.curvedness.shape == (2, 1, H, W)
    assert s.si.dtype == torch.float32 and s.valid.dtype == torch.bool
    assert float(s.si.min()) >= 0.0 and float(s.si.max()) <= 1.0
    assert torch.all(s.si[~s.valid] == 0.5)  # masked pixels carry the fill
    out = compute_sim_reference(d, K)  # the reference, one image at a time: other shapes, so within float32 rounding
    assert isinstance(out, SIM)
    torch.testing.assert_close(out.si, s.si, atol=F32_UNIT, rtol=0)
    assert torch.equal(out.valid, s.valid)  # thresholds: a flip needs a value within rounding of one (none here)
    odd = shape_index(d[..., :301, :457], K)  # sizes not divisible by the decimation
    assert odd.si.shape == odd.valid.shape == odd.curvedness.shape == (2, 1, 301, 457)
    lean = shape_index(d, K, curvedness=False)  # as compute_sim calls it
    assert lean.curvedness is None and torch.equal(lean.si, s.si) and torch.equal(lean.valid, s.valid)  # same shapes


@pytest.mark.parametrize(
    "depth, K, match",
    [
        (torch.ones(1, H, W), K1(), "depth must be"),
        (torch.ones(1, 2, H, W), K1(), "depth must be"),
        (torch.ones(2, 1, H, W), K1(), "K must be"),
    ],
)
def test_bad_input_raises(depth, K, match):
    with pytest.raises(ValueError, match=match):
        shape_index(depth, K)


def test_bad_decimate_raises():
    with pytest.raises(ValueError, match="decimate"):
        shape_index(torch.ones(1, 1, 8, 8), K1(), decimate=0)


# ---------------------------------------------------------------------------------------------- oracles
SURFACES = {
    "sphere (convex cap)": (lambda: sphere(0.8, 0.15), 1.0),
    "bowl (concave cup)": (lambda: sphere(0.8, 0.15, far=True), 0.0),
    "cylinder (convex ridge)": (lambda: cylinder(0.8, 0.1), 0.75),
    "pipe (concave rut)": (lambda: cylinder(0.8, 0.1, far=True), 0.25),
}


@pytest.mark.parametrize("decimate", [1, 2])
@pytest.mark.parametrize("name", list(SURFACES))
def test_analytic_surfaces(name, decimate):
    z, expected = SURFACES[name]
    z = z()
    s = shape_index(as_depth(z), K1(), decimate=decimate)
    core = interior(z)
    err = (s.si[0, 0] - expected).abs()
    assert core.sum() > 5000
    assert s.valid[0, 0][core].float().mean() > 0.95  # the interior is not masked away
    assert float(err[s.valid[0, 0]].max()) <= TOL  # and every valid pixel is right, not just the interior


@pytest.mark.parametrize("decimate", [1, 2])
def test_saddle_matches_closed_form(decimate):
    z, si_true = saddle(0.8, 0.15)
    s = shape_index(as_depth(z), K1(), decimate=decimate)
    core = interior(z) & s.valid[0, 0]
    assert core.sum() > 5000
    err = (s.si[0, 0].double() - si_true).abs()[core]
    assert float(err.max()) <= TOL
    centre = s.si[0, 0, 230:250, 310:330]
    assert float((centre - 0.5).abs().max()) <= 0.01  # at the apex k1 = -k2 exactly


def test_tilted_plane_is_masked_with_zero_curvature():
    # plane n . p = d with a 40 degree tilt: in inverse depth it is linear, so curvature vanishes
    x, y = rays()
    n = torch.tensor([math.sin(math.radians(40.0)), 0.2, math.cos(math.radians(40.0))], dtype=torch.float64)
    z = 1.2 / (n[0] * x + n[1] * y + n[2])
    s = shape_index(as_depth(z), K1(), min_curvature=0.0)
    core = interior(z)
    assert float(s.curvedness[0, 0][core].max()) < 0.05  # 1/m, against 6.7 for the sphere above
    assert float(s.curvedness[0, 0][s.valid[0, 0]].max()) < 2.5  # no artefact at the image border either
    assert not shape_index(as_depth(z), K1()).valid.any()


def test_curvedness_is_metric():
    for r in (0.1, 0.2):
        z = sphere(0.9, r)
        s = shape_index(as_depth(z), K1(), min_curvature=0.0)
        core = interior(z) & s.valid[0, 0]
        assert torch.allclose(s.curvedness[0, 0][core].median(), torch.tensor(1.0 / r), rtol=0.02)


def test_holes_do_not_bleed():
    z = sphere(0.8, 0.15)
    holed = z.clone()
    holed[200:215, 300:340] = 0.0  # a missing-depth stripe across the sphere
    s = shape_index(as_depth(holed), K1())
    assert not s.valid[0, 0, 200:215, 300:340].any()
    err = (s.si[0, 0] - 1.0).abs()[s.valid[0, 0]]
    assert float(err.max()) <= TOL


def test_depth_edges_are_masked_not_smeared():
    z = sphere(0.8, 0.15)
    scene = torch.where(z > 0, z, torch.full_like(z, 1.6))  # the sphere in front of a wall
    s = shape_index(as_depth(scene), K1())
    sphere_px = s.valid[0, 0] & (z > 0)
    wall_px = s.valid[0, 0] & (z == 0)
    assert float((s.si[0, 0][sphere_px] - 1.0).abs().max()) <= TOL
    assert not wall_px.any()  # the flat wall is masked, the silhouette band too
    silhouette = (z > 0) & ~interior(z, margin=2, max_deg=90.0)
    assert not s.valid[0, 0][silhouette].any()


def test_intrinsics_change_the_metric_curvature_consistently():
    # the same sphere rendered with another camera (focal, principal point) has the same SI and curvedness
    kw = dict(f=400.0, cx=300.0, cy=250.0)
    z = sphere(0.8, 0.15, **kw)
    s = shape_index(as_depth(z), K1(**kw), min_curvature=0.0)
    core = interior(z) & s.valid[0, 0]
    assert float((s.si[0, 0][core] - 1.0).abs().max()) <= TOL
    assert torch.allclose(s.curvedness[0, 0][core].median(), torch.tensor(1 / 0.15), rtol=0.02)


# ---------------------------------------------------------------------------------------------- SIM image
def test_sim_image_is_quantised_and_masked():
    z = sphere(0.8, 0.15)
    s = shape_index(as_depth(z), K1())
    img = sim_image(s)
    assert img.shape == (1, 1, H, W) and img.dtype == torch.float32
    assert torch.allclose(img * 255, (img * 255).round(), atol=1e-4)
    assert torch.all(img[~s.valid] == 128 / 255)
    assert float((img - s.si).abs().max()) <= 0.5 / 255 + 1e-6
    assert torch.equal(sim_image(s.si, s.valid), img)
    with pytest.raises(ValueError, match="SI must be"):
        sim_image(torch.zeros(1, H, W))


# ---------------------------------------------------------------------------------------------- batching
@pytest.mark.equivalence
def test_batched_equals_looped():
    zs = [sphere(0.8, 0.15), cylinder(0.8, 0.1, far=True), saddle(0.8, 0.15)[0]]
    Ks = torch.cat([K1(), K1(f=500.0), K1(f=550.0, cx=310.0)])
    d = torch.cat([as_depth(z) for z in zs])
    batched = shape_index(d, Ks)
    for b in range(3):
        one = shape_index(d[b : b + 1], Ks[b : b + 1])
        assert torch.equal(one.valid, batched.valid[b : b + 1])  # thresholds: no value within rounding of one here
        torch.testing.assert_close(one.si, batched.si[b : b + 1], atol=F32_UNIT, rtol=0)
    sim = compute_sim_reference(
        d, Ks
    )  # the reference, one image at a time (cache-sized temporaries): the batched map's values within rounding
    lean = shape_index(d, Ks, curvedness=False)
    torch.testing.assert_close(sim.si, lean.si, atol=F32_UNIT, rtol=0)
    assert torch.equal(sim.valid, lean.valid)
    assert torch.equal(sim.image, sim_image(sim.si))  # the quantised image of its own SI: the same arithmetic
    with pytest.raises(ValueError, match="K must be"):
        compute_sim(d, Ks[:2])


def test_module_equals_function():
    d, K = as_depth(sphere(0.8, 0.15)), K1()
    out = ShapeIndexMap(smooth_sigma=3.0, min_curvature=1.0)(d, K)
    ref = compute_sim(d, K, smooth_sigma=3.0, min_curvature=1.0)
    assert all(torch.equal(a, b) for a, b in zip(out, ref, strict=True))


# ---------------------------------------------------------------------------------------------- renderer
def test_synthetic_renderer_depth():
    """SIM of the synthetic renderer's exact depth: its spheres are caps (1), its cylinders ridges (0.75)."""
    synthetic = pytest.importorskip("torchtrack.data.synthetic")
    cfg = synthetic.SyntheticConfig(frames=2, seed=0, mode="object", noise="none")
    scene, poses = synthetic.default_scene(cfg), synthetic.sequence_poses(cfg)
    hits = synthetic.raycast(scene, poses.T_world_cam[0], poses.T_world_obj[0])
    s = shape_index(hits.depth.float()[None, None], scene.K[None].float())
    checked = 0
    for i, prim in enumerate(scene.primitives):
        if prim.kind not in ("sphere", "cylinder"):
            continue
        core = erode(hits.prim == i, 18)  # the whole smoothing window on this primitive
        v = s.valid[0, 0] & core
        if v.sum() < 50:
            continue
        err = (s.si[0, 0][v] - (1.0 if prim.kind == "sphere" else 0.75)).abs()
        if prim.kind == "sphere":
            assert float(err.max()) <= TOL
        else:  # cap-side creases of a cylinder are not a cylinder
            assert float((err <= TOL).float().mean()) >= 0.9
        checked += 1
    assert checked >= 2


@pytest.mark.parametrize("d", [2, 3])
def test_upsample_is_edge_clamped_linear_interpolation_with_nan_propagation(d):
    """Oracle: a pixel at (y, x) mixes the samples at floor(y / d), floor(y / d) + 1 (clamped) with weight (y mod d) / d,
    the same along x; a NaN sample makes exactly the pixels with non-zero weight on it NaN."""
    from torchtrack.image.shape_index import _upsample

    g = torch.Generator().manual_seed(d)
    x = torch.rand(2, 4, 5, generator=g, dtype=torch.float64)
    x[1, 2, 3] = math.nan
    H, W = 4 * d - 1, 5 * d - 2
    up = _upsample(x, d, H, W)
    assert up.shape == (2, H, W)
    for y in range(H):
        for xx in range(W):
            i, j, ty, tx = y // d, xx // d, (y % d) / d, (xx % d) / d
            i1, j1 = min(i + 1, 3), min(j + 1, 4)
            corners = [(i, j, (1 - ty) * (1 - tx)), (i, j1, (1 - ty) * tx), (i1, j, ty * (1 - tx)), (i1, j1, ty * tx)]
            for b in range(2):
                used = [x[b, r, c] for r, c, w in corners if w > 0]
                want = sum(w * x[b, r, c] for r, c, w in corners if w > 0)
                if any(math.isnan(v) for v in used):
                    assert math.isnan(up[b, y, xx])
                else:
                    assert up[b, y, xx].item() == pytest.approx(want.item(), abs=1e-12)
