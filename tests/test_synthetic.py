"""Synthetic renderer: closed-form depth, pose/texture consistency across frames, noise statistics, files.

Oracles: analytic ray-plane and ray-sphere depth in float64; re-rendering the exact sub-pixel position a
back-projected point lands on in another frame (same surface point -> same depth and colour); the
written PNG/TUM files reprojected with the written ground truth; the noise model's formulas.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from tolerances import F32_UNIT

from torchtrack.data.synthetic import (
    RGBD,
    KinectNoise,
    Primitive,
    SyntheticConfig,
    apply_kinect_noise,
    default_scene,
    depth_sigma,
    edge_holes,
    ensure_sequence,
    look_at,
    main,
    make_scene,
    random_texture,
    raycast,
    render_frame,
    render_pixels,
    render_sequence,
    sequence_poses,
)
from torchtrack.data.synthetic.scene import pose
from torchtrack.geometry import (
    T_inv,
    backproject_depth,
    make_T,
    matrix_to_quat_xyzw,
    pixel_grid,
    quat_xyzw_to_matrix,
    rotation_angle,
    sample_depth,
    so3_exp,
    transform_points,
)

SMALL = dict(width=160, height=120)


def rays64(cfg: SyntheticConfig) -> torch.Tensor:
    """(H, W, 3) float64 rays with z = 1 through cfg's pixel centres."""
    g = pixel_grid(cfg.height, cfg.width, dtype=torch.float64)
    return torch.stack([(g[..., 0] - cfg.cx) / cfg.fx, (g[..., 1] - cfg.cy) / cfg.fy, torch.ones_like(g[..., 0])], -1)


def read_tum(path: Path) -> torch.Tensor:
    """(F, 4, 4) float64 poses of a TUM trajectory file."""
    rows = np.loadtxt(path, comments="#", ndmin=2)
    R = quat_xyzw_to_matrix(torch.as_tensor(rows[:, 4:8]))
    return make_T(R, torch.as_tensor(rows[:, 1:4]))


def read_frame(folder: Path, stamp: str, depth_scale: float) -> RGBD:
    bgr = cv2.imread(str(folder / "rgb" / f"{stamp}.png"), cv2.IMREAD_UNCHANGED)
    d = cv2.imread(str(folder / "depth" / f"{stamp}.png"), cv2.IMREAD_UNCHANGED)
    assert bgr.dtype == np.uint8 and bgr.shape[2] == 3 and d.dtype == np.uint16
    rgb = torch.from_numpy(bgr[:, :, ::-1].copy()).permute(2, 0, 1).float() / 255
    return RGBD(rgb, torch.from_numpy(d.astype(np.float32))[None] / depth_scale)


# ---------------------------------------------------------------------------------------------- config / errors
def test_config_derives_intrinsics_from_image_size():
    assert (SyntheticConfig().fx, SyntheticConfig().cx, SyntheticConfig().cy) == (525.0, 319.5, 239.5)
    cfg = SyntheticConfig(width=320, height=240)
    assert (cfg.fx, cfg.fy, cfg.cx, cfg.cy) == (262.5, 262.5, 159.5, 119.5)
    assert SyntheticConfig(seed=1).digest() != SyntheticConfig(seed=2).digest()
    assert SyntheticConfig(seed=1).digest() == SyntheticConfig(seed=1).digest()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(mode="video"), "mode"),
        (dict(noise="gauss"), "noise"),
        (dict(frames=0), "frames"),
        (dict(width=8), "size"),
        (dict(fx=-1.0), "focal"),
        (dict(trans_step_m=-0.1), "steps"),
        (dict(kinect=KinectNoise(dropout_prob=1.5)), "kinect"),
    ],
)
def test_bad_config_raises(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SyntheticConfig(**kwargs)


def test_bad_render_input_raises():
    cfg = SyntheticConfig(mode="object", **SMALL)
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    with pytest.raises(ValueError, match="T_world_cam"):
        render_frame(scene, poses.T_world_cam[0, :3])
    with pytest.raises(ValueError, match="T_world_obj"):
        render_frame(scene, poses.T_world_cam[0])  # object scene without the object's pose
    with pytest.raises(ValueError, match="pixels"):
        render_pixels(scene, poses.T_world_cam[0], torch.zeros(5, 3), poses.T_world_obj[0])
    with pytest.raises(ValueError, match="kind"):
        Primitive("torus", (1.0,), pose((0, 0, 0)), random_texture(0))


# ---------------------------------------------------------------------------------------------- shapes
@pytest.mark.equivalence
def test_shapes_and_batched_equals_looped():
    cfg = SyntheticConfig(mode="object", frames=3, **SMALL)
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    one = render_frame(scene, poses.T_world_cam[0], poses.T_world_obj[0])
    assert one.rgb.shape == (3, 120, 160) and one.depth.shape == (1, 120, 160)
    assert one.rgb.dtype == torch.float32 and one.depth.dtype == torch.float32
    assert 0 <= float(one.rgb.min()) and float(one.rgb.max()) <= 1
    batch = render_frame(scene, poses.T_world_cam, poses.T_world_obj)
    assert batch.rgb.shape == (3, 3, 120, 160) and batch.depth.shape == (3, 1, 120, 160)
    for i in range(3):
        looped = render_frame(scene, poses.T_world_cam[i], poses.T_world_obj[i])
        # other batch shapes, other kernels: colour in [0, 1] and depth (~1-3 m) within F32_UNIT; no pixel's ray grazes
        # an edge within rounding here (a flipped hit would differ by a whole colour or depth step)
        torch.testing.assert_close(batch.rgb[i], looped.rgb, atol=F32_UNIT, rtol=0)
        torch.testing.assert_close(batch.depth[i], looped.depth, atol=F32_UNIT, rtol=0)


def test_render_pixels_equals_grid():
    """The sub-pixel entry point at pixel centres reproduces the image (no screen-box culling there)."""
    cfg = SyntheticConfig(**SMALL)
    scene, T = default_scene(cfg), sequence_poses(cfg).T_world_cam[0]
    img = render_frame(scene, T)
    px = pixel_grid(120, 160).reshape(-1, 2)
    rgb, depth = render_pixels(scene, T, px)
    assert torch.allclose(depth, img.depth.reshape(-1), atol=1e-5)
    assert torch.allclose(rgb.T, img.rgb.reshape(3, -1), atol=1e-4)


# ---------------------------------------------------------------------------------------------- closed forms
def test_plane_depth_equals_closed_form():
    """Tilted rectangle n.p = c seen from a moved camera: z(u, v) = c / (n . d(u, v)) inside it, 0 outside."""
    cfg = SyntheticConfig(**SMALL)
    half = (1.5, 1.0)
    T_world_plane = pose((0.1, 0.2, 3.0), (170.0, 20.0, 35.0))  # local +z (its visible side) faces the camera
    scene = make_scene([Primitive("plane", half, T_world_plane, random_texture(0))], cfg)
    T_world_cam = make_T(so3_exp(torch.tensor([0.05, -0.1, 0.03], dtype=torch.float64)), torch.tensor([0.2, -0.1, 0.3]))
    depth = render_frame(scene, T_world_cam).depth[0].double()
    T_cam_plane = T_inv(T_world_cam) @ T_world_plane
    n, o = T_cam_plane[:3, 2], T_cam_plane[:3, 3]
    d = rays64(cfg)
    expected = (n @ o) / (d @ n)
    local = transform_points(T_inv(T_cam_plane), (d * expected[..., None]).reshape(1, -1, 3))[0].reshape(120, 160, 3)
    margin = local[..., :2].abs() - torch.tensor(half, dtype=torch.float64)  # < 0 inside the rectangle
    inside, outside = (margin < -1e-3).all(-1), (margin > 1e-3).any(-1)
    assert int(inside.sum()) > 5000 and int(outside.sum()) > 1000
    assert float((depth[inside] - expected[inside]).abs().max()) < 1e-4
    assert bool((depth[outside] == 0).all())


def test_sphere_depth_equals_closed_form():
    """Sphere of radius r at c (camera frame): z = (d.c - sqrt((d.c)^2 - |d|^2 (|c|^2 - r^2))) / |d|^2."""
    cfg = SyntheticConfig(**SMALL)
    r, c_world = 0.4, torch.tensor([0.3, 1.9, 0.8], dtype=torch.float64)
    scene = make_scene([Primitive("sphere", (r,), pose(tuple(c_world.tolist()), (10, 20, 30)), random_texture(1))], cfg)
    T_world_cam = look_at((0.0, -0.2, 0.5), (0.25, 2.0, 0.9))
    depth = render_frame(scene, T_world_cam).depth[0].double()
    c = transform_points(T_inv(T_world_cam), c_world[None])[0]
    d = rays64(cfg)
    a, b = (d * d).sum(-1), d @ c
    disc = b * b - a * (c @ c - r * r)
    inside = disc > 1e-3 * a  # away from the silhouette, where float32 may round either way
    outside = disc < -1e-3 * a
    expected = (b - disc.clamp_min(0).sqrt()) / a
    assert int(inside.sum()) > 500 and int(outside.sum()) > 500
    assert float((depth[inside] - expected[inside]).abs().max()) < 1e-4
    assert bool((depth[outside] == 0).all())


# ---------------------------------------------------------------------------------------------- consistency
def _groups(scene, hits):
    """(H, W) rigid group of each pixel's primitive (0 static, 1 object; -1 none)."""
    table = torch.tensor([p.group for p in scene.primitives] + [-1])
    return table[hits.prim]


@pytest.mark.parametrize("mode", ["scene", "object"])
def test_backprojected_points_rerender_identically_in_another_frame(mode):
    """Back-project frame i, move with the ground-truth poses into frame j, re-render the exact sub-pixel.

    Same surface point: its depth in j equals the transformed z unless occluded (never deeper), and its
    colour is identical. This proves poses, object motion and texture attachment are consistent.
    """
    cfg = SyntheticConfig(mode=mode, frames=9, trans_step_m=0.03, rot_step_deg=2.0, **SMALL)
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    i, j = 0, 8
    Tc, To = poses.T_world_cam, poses.T_world_obj
    obj = (lambda k: None) if To is None else (lambda k: To[k])
    img = render_frame(scene, Tc[i], obj(i))
    hits = raycast(scene, Tc[i], obj(i))
    assert torch.equal(hits.depth, img.depth[0])
    pts = backproject_depth(scene.K[None], img.depth[None].double())[0].reshape(-1, 3)
    group = _groups(scene, hits).reshape(-1)
    keep = group >= 0
    # camera i -> camera j: static points through the world, object points through the object frame
    T_ji_static = T_inv(Tc[j]) @ Tc[i]
    T_ji = T_ji_static if To is None else T_inv(Tc[j]) @ To[j] @ T_inv(To[i]) @ Tc[i]
    moved = torch.where((group == 1)[:, None], transform_points(T_ji, pts), transform_points(T_ji_static, pts))
    uv = moved[:, :2] / moved[:, 2:] * torch.stack([scene.K[0, 0], scene.K[1, 1]]).double() + scene.K[:2, 2].double()
    keep &= (moved[:, 2] > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] <= 159) & (uv[:, 1] >= 0) & (uv[:, 1] <= 119)
    rgb_j, depth_j = render_pixels(scene, Tc[j], uv[keep], obj(j))
    z = moved[keep, 2]
    assert float((depth_j.double() - z).max()) < 1e-4  # nothing is seen behind the surface point
    visible = (depth_j.double() - z).abs() < 1e-4
    assert float(visible.float().mean()) > 0.85 and int(keep.sum()) > 0.6 * keep.numel()
    if mode == "object":
        assert int((group[keep][visible] == 1).sum()) > 500  # the moving object is really tested
    colour_i = img.rgb.reshape(3, -1).T[keep][visible]
    err = (rgb_j[visible] - colour_i).abs().max(-1).values
    # identical up to float32; a handful of points on box edges / cube-map seams may flip to the adjacent face
    assert float((err < 2e-3).float().mean()) > 0.999 and float(err.median()) < 1e-5


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """Noise-free 3-frame sequences on disk, scene and object mode (320 x 240)."""
    root = tmp_path_factory.mktemp("synth")
    out = {}
    for mode in ("scene", "object"):
        cfg = SyntheticConfig(mode=mode, frames=3, noise="none", width=320, height=240, trans_step_m=0.02)
        out[mode] = (cfg, render_sequence(cfg, root / mode))
    return out


@pytest.mark.parametrize("mode", ["scene", "object"])
def test_written_frames_reproject_with_written_groundtruth(written, mode):
    """Files only: depth PNG of frame 0, groundtruth.txt and intrinsics.txt predict frame 2's depth and colour."""
    cfg, folder = written[mode]
    fx, fy, cx, cy, scale = np.loadtxt(folder / "intrinsics.txt", comments="#")
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64)
    stamps = [line.split()[0] for line in (folder / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    T_gt = read_tum(folder / "groundtruth.txt")
    f0, f2 = read_frame(folder, stamps[0], scale), read_frame(folder, stamps[2], scale)
    pts = backproject_depth(K[None], f0.depth[None].double())[0].reshape(-1, 3)
    keep = f0.depth.reshape(-1) > 0
    if mode == "object":
        keep &= f0.depth.reshape(-1) < 1.3  # the object (background starts beyond 1.5 m)
    moved = transform_points(T_inv(T_gt[2]) @ T_gt[0], pts[keep])
    uv = moved[:, :2] / moved[:, 2:] * K.diagonal()[:2] + K[:2, 2]
    grid = (uv / torch.tensor([cfg.width - 1, cfg.height - 1]) * 2 - 1).float()[None, None]
    corner = uv.floor()[None]  # the 4 pixels that bilinear sampling reads must lie on one smooth surface
    near = torch.cat([sample_depth(f2.depth[None], corner + torch.tensor(o)) for o in ((0, 0), (1, 0), (0, 1), (1, 1))])
    smooth = ((near.max(0).values - near.min(0).values) < 0.02) & (near.min(0).values > 0)
    ok = smooth & (grid[0, 0].abs() < 0.98).all(-1)
    assert int(ok.sum()) > 0.5 * int(keep.sum()) > 1000
    d2 = F.grid_sample(f2.depth[None], grid, align_corners=True).reshape(-1).double()
    err = (d2 - moved[:, 2])[ok].abs()
    assert float(err.median()) < 1e-3 and float(err.quantile(0.95)) < 5e-3
    c2 = F.grid_sample(f2.rgb[None], grid, align_corners=True)[0, :, 0]
    cerr = (c2 - f0.rgb.reshape(3, -1)[:, keep])[:, ok].abs().max(0).values
    assert float(cerr.median()) < 0.02 and float(cerr.quantile(0.9)) < 0.08


def test_written_object_pose_is_inverse_of_groundtruth(written):
    cfg, folder = written["object"]
    T_obj_cam, T_cam_obj = read_tum(folder / "groundtruth.txt"), read_tum(folder / "object_pose.txt")
    assert torch.allclose(T_obj_cam @ T_cam_obj, torch.eye(4, dtype=torch.float64).expand(3, 4, 4), atol=1e-7)
    assert torch.allclose(T_cam_obj, sequence_poses(cfg).T_cam_obj, atol=1e-7)
    assert "world := object" in (folder / "SOURCE.txt").read_text()


# ---------------------------------------------------------------------------------------------- layout / cache
@pytest.mark.parametrize("mode", ["scene", "object"])
def test_tum_layout(written, mode):
    cfg, folder = written[mode]
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt", "SOURCE.txt", "config.json"):
        assert (folder / name).is_file(), name
    assert (folder / "object_pose.txt").is_file() == (mode == "object")
    assert np.allclose(np.loadtxt(folder / "intrinsics.txt", comments="#"), [cfg.fx, cfg.fy, cfg.cx, cfg.cy, 5000.0])
    for kind in ("rgb", "depth"):
        rows = [r.split() for r in (folder / f"{kind}.txt").read_text().splitlines() if not r.startswith("#")]
        assert [float(r[0]) for r in rows] == pytest.approx([i / 30 for i in range(3)], abs=1e-6)
        assert all((folder / r[1]).is_file() and r[1].startswith(f"{kind}/") for r in rows)
    gt = np.loadtxt(folder / "groundtruth.txt", comments="#")
    assert gt.shape == (3, 8) and np.allclose(np.linalg.norm(gt[:, 4:], axis=1), 1)
    T = sequence_poses(cfg)
    expected = T.T_world_cam if mode == "scene" else T_inv(T.T_cam_obj)
    assert np.allclose(gt[:, 1:4], expected[:, :3, 3].numpy(), atol=1e-8)
    q = matrix_to_quat_xyzw(expected[:, :3, :3]).numpy()
    assert np.allclose(np.abs((gt[:, 4:] * q).sum(1)), 1, atol=1e-8)  # same rotation, xyzw order


def test_default_scene_is_well_covered_and_textured():
    """Kinect-noisy default frame: > 80 % valid depth in scene mode, depths 1-4.5 m, lots of texture."""
    cfg = SyntheticConfig()
    scene, T = default_scene(cfg), sequence_poses(cfg).T_world_cam[0]
    clean = render_frame(scene, T)
    noisy = apply_kinect_noise(clean, cfg.kinect, torch.Generator().manual_seed(0))
    assert float((noisy.depth > 0).float().mean()) > 0.8
    d = clean.depth[clean.depth > 0]
    assert 0.8 < float(d.min()) and float(d.max()) < 4.5
    gray = clean.rgb.mean(0)
    grad = (gray[1:, 1:] - gray[:-1, 1:]).abs() + (gray[1:, 1:] - gray[1:, :-1]).abs()
    assert float((grad > 0.05).float().mean()) > 0.02  # edges and corners everywhere, not flat colour
    assert {p.kind for p in scene.primitives} == {"plane", "box", "sphere", "cylinder"}


def test_object_mode_without_background_has_depth_only_on_the_object():
    cfg = SyntheticConfig(mode="object", background=False, **SMALL)
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    assert all(p.group == 1 for p in scene.primitives)
    frame = render_frame(scene, poses.T_world_cam[0], poses.T_world_obj[0])
    valid = frame.depth > 0
    assert 0.03 < float(valid.float().mean()) < 0.3 and float(frame.depth[valid].max()) < 1.3
    assert torch.equal(
        frame.rgb[:, ~valid[0]], torch.tensor(scene.background_rgb)[:, None].expand(3, int((~valid).sum()))
    )


def test_determinism_same_seed_identical_files_different_seed_different(tmp_path):
    tiny = dict(width=64, height=48, frames=2, noise="kinect")
    a = render_sequence(SyntheticConfig(seed=3, **tiny), tmp_path / "a")
    b = render_sequence(SyntheticConfig(seed=3, **tiny), tmp_path / "b")
    c = render_sequence(SyntheticConfig(seed=4, **tiny), tmp_path / "c")
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) == 10
    assert all((a / f).read_bytes() == (b / f).read_bytes() for f in files)
    for f in ("rgb/0.033333.png", "depth/0.033333.png", "groundtruth.txt"):
        assert (a / f).read_bytes() != (c / f).read_bytes(), f


def test_ensure_sequence_renders_once_and_keys_on_config(tmp_path, monkeypatch):
    cfg = SyntheticConfig(width=48, height=32, frames=1, noise="none")
    first = ensure_sequence(cfg, tmp_path)
    assert (first / "SOURCE.txt").is_file()

    def fail(*args, **kwargs):
        raise AssertionError("re-rendered a cached sequence")

    monkeypatch.setattr("torchtrack.data.synthetic.writer.render_sequence", fail)
    assert ensure_sequence(SyntheticConfig(width=48, height=32, frames=1, noise="none"), tmp_path) == first
    monkeypatch.undo()
    other = ensure_sequence(SyntheticConfig(width=48, height=32, frames=1, noise="none", seed=1), tmp_path)
    assert other != first and (other / "SOURCE.txt").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([first.name, other.name])  # no temporaries left


def test_render_sequence_refuses_to_overwrite(tmp_path):
    cfg = SyntheticConfig(width=48, height=32, frames=1, noise="none")
    out = render_sequence(cfg, tmp_path / "x")
    with pytest.raises(ValueError, match="not empty"):
        render_sequence(cfg, out)
    assert render_sequence(SyntheticConfig(width=48, height=32, frames=2, noise="none"), out, overwrite=True) == out
    assert len(list((out / "rgb").iterdir())) == 2


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    args = [
        "--out",
        str(out),
        "--frames",
        "2",
        "--width",
        "48",
        "--height",
        "32",
        "--mode",
        "object",
        "--noise",
        "none",
    ]
    assert main(args) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert len(list((out / "depth").iterdir())) == 2 and (out / "object_pose.txt").is_file()
    assert main(args) == 2  # exists
    assert main(["--out", str(tmp_path / "y"), "--frames", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("torchtrack-synth: error:") for e in err)


# ---------------------------------------------------------------------------------------------- motion
def test_motion_steps_match_config_and_prefix_property():
    cfg = SyntheticConfig(frames=1500, trans_step_m=0.01, rot_step_deg=1.0)
    T = sequence_poses(cfg).T_world_cam
    D = T_inv(T[:-1]) @ T[1:]
    trans_rms = float(D[:, :3, 3].norm(dim=-1).pow(2).mean().sqrt())
    rot_rms = math.degrees(float(rotation_angle(D[:, :3, :3]).pow(2).mean().sqrt()))
    assert trans_rms == pytest.approx(0.01, rel=0.25) and rot_rms == pytest.approx(1.0, rel=0.25)
    acc = T[2:, :3, 3] - 2 * T[1:-1, :3, 3] + T[:-2, :3, 3]  # smooth: acceleration << velocity
    assert float(acc.norm(dim=-1).max()) < 0.5 * 0.01
    short = sequence_poses(SyntheticConfig(frames=10)).T_world_cam
    assert torch.equal(short, sequence_poses(SyntheticConfig(frames=30)).T_world_cam[:10])
    obj = sequence_poses(SyntheticConfig(frames=50, mode="object"))
    assert torch.equal(obj.T_world_cam[0], obj.T_world_cam[-1])  # static camera, moving object
    assert float((obj.T_world_obj[0] - obj.T_world_obj[-1]).abs().max()) > 0.05


# ---------------------------------------------------------------------------------------------- noise
def flat_wall(z: float, kinect: KinectNoise) -> tuple[RGBD, KinectNoise]:
    """Clean fronto-parallel wall at depth z (mid-grey colour), 160 x 120."""
    depth = torch.full((1, 120, 160), z)
    return RGBD(torch.full((3, 120, 160), 0.5), depth), kinect


@pytest.mark.parametrize("z", [1.0, 2.5])
def test_depth_noise_std_matches_model(z):
    frame, k = flat_wall(z, KinectNoise(disparity_subpixel=0.0, dropout_prob=0.0))
    noisy = apply_kinect_noise(frame, k, torch.Generator().manual_seed(0))
    err = (noisy.depth - frame.depth)[noisy.depth > 0]
    sigma = float(depth_sigma(torch.tensor(z), k))
    assert sigma == pytest.approx(0.0012 + 0.0019 * (z - 0.4) ** 2)
    assert float(err.std()) == pytest.approx(sigma, rel=0.1) and abs(float(err.mean())) < 0.1 * sigma
    assert float((noisy.rgb - 0.5).std()) == pytest.approx(k.rgb_sigma, rel=0.1)


def test_disparity_quantisation_grid_and_std():
    z = 2.5
    frame, k = flat_wall(z, KinectNoise(dropout_prob=0.0))
    noisy = apply_kinect_noise(frame, k, torch.Generator().manual_seed(1))
    d = noisy.depth[noisy.depth > 0].double()
    fb = k.disparity_focal_px * k.disparity_baseline_m
    steps = fb / (d * k.disparity_subpixel)
    assert float((steps - steps.round()).abs().max()) < 1e-3  # on the 1/8-pixel disparity grid
    step = z * z / fb * k.disparity_subpixel  # 1.8 cm at 2.5 m
    sigma = float(depth_sigma(torch.tensor(z), k))
    assert float(d.std()) == pytest.approx(math.sqrt(sigma**2 + step**2 / 12), rel=0.15)


def test_holes_dropouts_and_range():
    depth = torch.full((1, 1, 60, 80), 1.0)
    depth[..., 40:] = 2.0  # a 1 m jump between columns 39 and 40
    holes = edge_holes(depth, jump_m=0.05, dilate_px=1)[0, 0]
    assert torch.equal(holes.any(0), (torch.arange(80) >= 38) & (torch.arange(80) <= 41))
    assert bool(holes[:, 38:42].all())
    frame, k = flat_wall(1.5, KinectNoise(dropout_prob=0.05))
    noisy = apply_kinect_noise(frame, k, torch.Generator().manual_seed(2))
    assert float((noisy.depth == 0).float().mean()) == pytest.approx(0.05, abs=0.006)
    far, k = flat_wall(7.0, KinectNoise())
    assert bool((apply_kinect_noise(far, k, torch.Generator()).depth == 0).all())  # beyond max_depth_m
