"""Pose-warped templates (torchtrack/image/warp.py): plane homography, depth normals and warped tracks vs exact truth."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from tolerances import LK_PX

from torchtrack.data.frame import FrameBatch
from torchtrack.data.synthetic import SyntheticConfig
from torchtrack.data.synthetic.motion import SCENE_EYE, SCENE_TARGET, look_at
from torchtrack.data.synthetic.render import render_frame
from torchtrack.data.synthetic.scene import default_scene
from torchtrack.frontend import FrontEnd, PreparedFrame, smooth_depth_mask
from torchtrack.geometry import T_inv, backproject, make_T, project, sample_depth, se3_exp, so3_exp, transform_points
from torchtrack.image.flow import CombinedTracker, prepare_frame
from torchtrack.image.pyramid import build_pyramid
from torchtrack.image.select import select_features
from torchtrack.image.warp import (
    crop_at,
    crop_pyramids,
    depth_normals,
    plane_homography,
    sample_through,
    track_warped,
    translation_homography,
)
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.landmarks import LandmarkMap

F64 = torch.float64
K1 = torch.tensor([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]], dtype=F64)[None]


def _apply(Hm: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    p = (Hm @ torch.cat([x, torch.ones_like(x[..., :1])], -1)[..., None])[..., 0]
    return p[..., :2] / p[..., 2:]


def _plane(normal, d, H=480, W=640):
    """Depth (1, 1, H, W) of the plane n . X = d seen by K1 (every pixel's ray meets it in front)."""
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    ray = torch.stack([(u - 319.5) / 525, (v - 239.5) / 525, torch.ones_like(u)], -1)
    return (d / (ray @ normal))[None, None]


def test_plane_homography_maps_plane_points_exactly():
    g = torch.Generator().manual_seed(0)
    n = F.normalize(torch.tensor([0.2, -0.3, -1.0], dtype=F64), dim=0)
    X = torch.cat([torch.rand(1, 50, 2, generator=g, dtype=F64) - 0.5, torch.zeros(1, 50, 1, dtype=F64)], -1)
    X = X - X @ n[:, None] * n + (-2.0) * n  # onto n . X = 2 (n points at the camera)
    T = make_T(so3_exp(torch.tensor([0.1, -0.2, 0.05], dtype=F64)), torch.tensor([0.1, 0.05, -0.2], dtype=F64))[None]
    Hm = plane_homography(K1, T, X, n.expand(1, 50, 3))
    torch.testing.assert_close(_apply(Hm, project(K1, X)), project(K1, transform_points(T, X)), rtol=0, atol=1e-9)
    T2 = make_T(so3_exp(torch.tensor([-0.1, 0.1, 0.2], dtype=F64)), torch.tensor([-0.1, 0.0, 0.1], dtype=F64))[None]
    each = torch.where(
        torch.arange(50)[None, :, None, None] % 2 == 0, T[:, None], T2[:, None]
    )  # per landmark: 1,50,4,4
    Hm = plane_homography(K1, each, X, n.expand(1, 50, 3))
    truth = torch.where(torch.arange(50)[None, :, None] % 2 == 0, transform_points(T, X), transform_points(T2, X))
    torch.testing.assert_close(_apply(Hm, project(K1, X)), project(K1, truth), rtol=0, atol=1e-9)


def test_depth_normals_of_a_plane_are_its_normal():
    n = F.normalize(torch.tensor([0.3, 0.2, -1.0], dtype=F64), dim=0)
    depth = _plane(n, -1.5)
    px = torch.tensor([[[100.0, 80.0], [320.0, 240.0], [500.3, 400.7]]], dtype=F64)
    normals, ok = depth_normals(depth, K1, px)
    assert bool(ok.all())
    torch.testing.assert_close(normals, n.expand(1, 3, 3), rtol=0, atol=1e-9)
    depth[..., 240, 317] = 0  # a hole next to the centre pixel
    assert depth_normals(depth, K1, px)[1].tolist() == [[True, False, True]]
    m = F.normalize(torch.tensor([-0.2, 0.1, -1.0], dtype=F64), dim=0)  # pixel (b, c) in depth map image[b, c]
    normals, ok = depth_normals(torch.cat([_plane(m, -2.0), _plane(n, -1.5)]), K1, px, torch.tensor([[1, 0, 0]]))
    assert bool(ok.all())
    torch.testing.assert_close(normals, torch.stack([n, m, m])[None], rtol=0, atol=1e-9)


def _texture(H=480, W=640, seed=1):
    g = torch.Generator().manual_seed(seed)
    noise = torch.rand(1, 1, H // 8, W // 8, generator=g, dtype=F64)
    return F.interpolate(noise, size=(H, W), mode="bicubic", align_corners=True).clamp(0, 1)


@pytest.mark.parametrize("angle_deg, scale", [(20.0, 1.25), (0.0, 1.0)])
def test_warped_template_tracks_a_known_homography_exactly(angle_deg, scale):
    """Current image = keyframe image through a known similarity about the centre (a plane rotated and approached):
    with the template warped by it, LK from a start 2 px off recovers the exact image of each point (within 0.1 px:
    LK's eps and the bilinear resampling of both images); the unwarped template is off by more than 0.3 px (median) when it is a rotation
    and scaling, and is the same tracker (same answer) when it is a pure translation."""
    kf = _texture()
    a = math.radians(angle_deg)
    c = torch.tensor([319.5, 239.5], dtype=F64)
    A = scale * torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=F64)
    Hm = torch.eye(3, dtype=F64)
    Hm[:2, :2], Hm[:2, 2] = A, c - A @ c + torch.tensor([6.0, -4.0], dtype=F64)
    Hm = Hm[None, None]
    cur = F.grid_sample(kf, _grid(torch.linalg.inv(Hm[0, 0]), 480, 640), align_corners=True)
    g = torch.Generator().manual_seed(2)
    px = torch.rand(1, 40, 2, generator=g, dtype=F64) * torch.tensor([360.0, 240.0], dtype=F64) + torch.tensor(
        [140.0, 120.0], dtype=F64
    )
    truth = _apply(Hm, px)
    pred = truth + torch.tensor([2.0, -1.5], dtype=F64)
    valid = torch.ones(1, 40, dtype=torch.bool)
    H_pred = torch.eye(3, dtype=F64).repeat(1, 40, 1, 1)
    H_pred[..., :2, 2] = pred - truth
    H_pred = H_pred @ Hm  # the prediction's homography: the true one, moved by the start's offset
    warped = track_warped(kf, cur, H_pred.expand(1, 40, 3, 3), px, valid, pred)
    e_w = (warped.pixels - truth).norm(dim=-1)[warped.status]
    assert warped.status.sum() >= 36 and e_w.max() < 0.1, e_w
    two = track_warped(kf, cur, H_pred.expand(1, 40, 3, 3), px, valid, torch.stack([pred, pred + 3.0], 2))
    assert two.pixels.shape == (1, 40, 2, 2)  # a second start (the re-acquisition's probe) per landmark
    torch.testing.assert_close(two.pixels[:, :, 0], warped.pixels, rtol=0, atol=LK_PX)  # other shapes
    both = two.status.all(-1)
    assert (two.pixels[:, :, 0] - two.pixels[:, :, 1]).norm(dim=-1)[both].max() < 0.05
    plain = track_warped(kf, cur, translation_homography(px, pred), px, valid, pred)
    e_p = (plain.pixels - truth).norm(dim=-1)[plain.status]
    if angle_deg == 0:
        torch.testing.assert_close(plain.pixels, warped.pixels, rtol=0, atol=1e-3)
    else:
        # without the warp the rotated patch is lost (most tracks fail) or biased (the rest sit > 0.3 px off)
        assert 2 * plain.status.sum() < warped.status.sum() or e_p.median() > 0.3, (plain.status.sum(), e_p)


def _grid(M: torch.Tensor, H: int, W: int) -> torch.Tensor:
    v, u = torch.meshgrid(torch.arange(H, dtype=F64), torch.arange(W, dtype=F64), indexing="ij")
    p = torch.stack([u, v, torch.ones_like(u)], -1) @ M.T
    xy = p[..., :2] / p[..., 2:]
    return torch.stack([2 * xy[..., 0] / (W - 1) - 1, 2 * xy[..., 1] / (H - 1) - 1], -1)[None]


def test_sample_through_a_translation_is_a_crop():
    img = _texture(60, 80)
    M = torch.eye(3, dtype=F64).repeat(1, 2, 1, 1)
    M[0, 0, :2, 2] = torch.tensor([10.0, 5.0], dtype=F64)
    M[0, 1, :2, 2] = torch.tensor([30.0, 20.0], dtype=F64)
    out = sample_through(img, M, 16)
    assert out.shape == (1, 2, 1, 16, 16)
    torch.testing.assert_close(out[0, 0, 0], img[0, 0, 5:21, 10:26], rtol=0, atol=1e-5)  # float32 coordinates
    torch.testing.assert_close(out[0, 1, 0], img[0, 0, 20:36, 30:46], rtol=0, atol=1e-5)
    crops = crop_at(img, torch.tensor([[[10, 5], [70, 50]]]), 16)  # the second runs off the image: zeros there
    assert torch.equal(crops[0, 0, 0], img[0, 0, 5:21, 10:26])
    assert torch.equal(crops[0, 1, 0, :10, :10], img[0, 0, 50:60, 70:80]) and crops[0, 1, 0, 10:].abs().max() == 0


def _padded(pyr, level: int, i: int) -> torch.Tensor:
    """Image i's padded block (H_l + 2 pad, W_l + 2 pad) at a level of a pyramid."""
    h, w = pyr.size(level)
    r0 = int(pyr.row_start[level, i])
    return pyr.flat.view(-1, pyr.stride)[r0 : r0 + h + 2 * pyr.pad, : w + 2 * pyr.pad]


def test_crop_pyramids_are_crops_of_the_whole_pyramids():
    """Target: level l of a crop is the current pyramid's level l from origin / 2^l on, padding included (image
    content), exactly. Template: through a translation by a multiple of 2^l it is the keyframe pyramid's level l,
    exactly (bilinear at integer positions); through a homography its level 0 is :func:`sample_through` of the
    keyframe image (float32 coordinates: 1e-5)."""
    kf = build_pyramid(torch.cat([_texture(160, 200, seed=3), _texture(160, 200, seed=4)]).float(), 3, window=31)
    cur = build_pyramid(_texture(160, 200, seed=5).float(), 3, window=31)
    origin = torch.tensor([[60, 40], [88, 72]])
    shift = torch.tensor([[8.0, -4.0], [-12.0, 16.0]], dtype=F64)  # template = keyframe at origin + shift
    M = torch.eye(3, dtype=F64).repeat(2, 1, 1)
    M[:, :2, 2] = origin + shift
    kf_image = torch.tensor([1, 0])
    tpl, tgt = crop_pyramids(kf, cur, M, kf_image, torch.zeros(2, dtype=torch.long), origin, 24, 3, 21)
    p = tgt.pad
    for level in range(3):
        s = 2**level
        for n in range(2):
            x, y = (origin[n] // s).tolist()
            h, w = tgt.size(level)
            want = _padded(cur, level, 0)[cur.pad + y - p : cur.pad + y + h + p, cur.pad + x - p : cur.pad + x + w + p]
            assert torch.equal(_padded(tgt, level, n), want)
            x, y = ((origin[n] + shift[n].long()) // s).tolist()
            want = _padded(kf, level, int(kf_image[n]))[
                kf.pad + y - p : kf.pad + y + h + p, kf.pad + x - p : kf.pad + x + w + p
            ]
            assert torch.equal(_padded(tpl, level, n), want)
    a = math.radians(15.0)
    M[:, :2, :2] = 1.1 * torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=F64)
    M[:, 2, :2] = torch.tensor([1e-4, -2e-4], dtype=F64)  # projective
    tpl = crop_pyramids(kf, cur, M, kf_image, torch.zeros(2, dtype=torch.long), origin, 24, 3, 21)[0]
    for n in range(2):
        ref = sample_through(kf.images[0][int(kf_image[n])][None], M[n][None, None], 24)[0, 0, 0]
        torch.testing.assert_close(tpl.images[0][n, 0], ref, rtol=0, atol=1e-5)


def test_warped_tracks_from_stacked_keyframe_images_are_their_own():
    """Landmarks of several keyframe images in one call (``kf_index``): each is tracked from its own keyframe image;
    the same tracks as the call with that image alone, and exact against the known homography."""
    kf = _texture()
    a = math.radians(10.0)
    Hm = torch.eye(3, dtype=F64)
    Hm[:2, :2] = 1.1 * torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=F64)
    Hm[:2, 2] = torch.tensor([319.5, 239.5], dtype=F64) - Hm[:2, :2] @ torch.tensor([319.5, 239.5], dtype=F64)
    cur = F.grid_sample(kf, _grid(torch.linalg.inv(Hm), 480, 640), align_corners=True)
    g = torch.Generator().manual_seed(7)
    px = torch.rand(1, 30, 2, generator=g, dtype=F64) * torch.tensor([360.0, 240.0], dtype=F64) + 140
    truth, valid = _apply(Hm, px), torch.ones(1, 30, dtype=torch.bool)
    H = Hm.expand(1, 30, 3, 3)
    alone = track_warped(kf, cur, H, px, valid, truth + 1.5)
    stacked = torch.cat([_texture(seed=9), kf, _texture(seed=11)])
    index = torch.full((1, 30), 1)
    index[0, ::3] = 0  # a third from another image: those are not the same tracks
    got = track_warped(stacked, cur, H, px, valid, truth + 1.5, kf_index=index)
    own = index == 1
    assert torch.equal(got.status[own], alone.status[own]) and int(alone.status.sum()) >= 27
    torch.testing.assert_close(got.pixels[own], alone.pixels[own], rtol=0, atol=LK_PX)
    assert (got.pixels - truth).norm(dim=-1)[own & got.status].max() < 0.1
    H = H.clone()
    H[0, 1] = float("nan")  # no homography (e.g. no normal): not tracked, the start is returned
    H[0, 2, :2, 2] = 1e6  # the template's point outside the current image: not tracked
    bad = track_warped(kf, cur, H, px, valid, truth + 1.5)
    assert not bad.status[0, 1:3].any() and torch.equal(bad.pixels[0, 1:3], truth[0, 1:3] + 1.5)
    assert torch.equal(bad.pixels[0, 3:], alone.pixels[0, 3:])


def test_warped_reacquisition_over_slots_and_sequences_is_exact():
    """The landmark map's warped re-acquisition (one call over all keyframe slots): B = 2 sequences of a rendered
    room corner, landmarks in 3 slots of 2 keyframes (the second rolled by 11 degrees) 2-4 cm from the current camera;
    every slot and sequence re-acquires its landmarks at their exact projections (each from its own keyframe image,
    pose and depth). Measured: 151 re-acquired (77 + 74; slots 62, 65, 24), error median 0.05 px, max 0.58 px; with
    slot 0's pose for every landmark: 25 of slot 1's, max error 1.4 px."""
    cfg = SyntheticConfig(width=320, height=240, mode="scene", noise="none", seed=3)
    scene, fe = default_scene(cfg), FrontEnd(levels=3)
    K = scene.K.float()[None].expand(2, 3, 3)

    def prepared(T0, T1):
        frames = []
        for T in (T0, T1):
            rgbd = render_frame(scene, T)
            frames.append(fe(FrameBatch(rgb=rgbd.rgb[None].float(), depth=rgbd.depth[None].float(), K=K[:1],
                                        K_depth=K[:1], T_color_depth=torch.eye(4)[None],
                                        timestamp=torch.zeros(1, dtype=F64), T_world_color_gt=T[None],
                                        gt_valid=torch.ones(1, dtype=torch.bool), active=torch.ones(1, dtype=torch.bool),
                                        index=torch.zeros(1, dtype=torch.long))))  # fmt: skip
        a, b = frames
        sim = type(a.sim)(*(torch.cat([x, y]) for x, y in zip(a.sim, b.sim, strict=True)))
        flow = prepare_frame(*(torch.cat([x, y]) for x, y in zip(a.flow.images, b.flow.images, strict=True)), 3)
        return PreparedFrame(torch.cat([a.gray, b.gray]), torch.cat([a.depth, b.depth]), sim, flow)

    move = lambda *v: se3_exp(torch.tensor(v, dtype=F64))  # noqa: E731
    T0 = look_at(SCENE_EYE, SCENE_TARGET)
    T_kf = [torch.stack([T0, T0 @ move(0.01, 0, 0, 0, 0.01, 0)]), None]
    T_kf[1] = T_kf[0] @ move(0.01, 0.005, 0, 0, -0.01, 0.2)  # rolled by 11 degrees
    T_cur = T_kf[0] @ move(0.02, -0.01, 0.015, 0.01, 0.02, -0.01)
    store, lm = KeyframeStore(size=3), LandmarkMap(per_keyframe=128, max_candidates=256, correct=False, warp=True,
                                                   warp_crop=48)  # fmt: skip
    store.reset(2)
    for k, split in ((0, slice(0, None, 2)), (1, slice(None)), (0, slice(1, None, 2))):
        kf = prepared(*T_kf[k])
        feats = select_features(kf.gray, kf.depth, K, roi=smooth_depth_mask(kf.depth, 0.03), sim=kf.sim)
        keep = torch.zeros_like(feats.valid)
        keep[:, split] = True
        pix = feats.pixels.float()
        z = sample_depth(kf.depth, pix).double()
        world = transform_points(T_kf[k], backproject(K.double(), pix.double(), z))
        slot = store.add(torch.zeros(2), T_kf[k], torch.ones(2, dtype=torch.bool), torch.ones(2, dtype=torch.bool))
        lm.add(store, slot, kf, pix, world, torch.zeros(*pix.shape[:2], 2), feats.valid & keep & (z > 0))
    cur, none, no = prepared(*T_cur), torch.zeros(2, 0, 2), torch.zeros(2, 0, dtype=torch.bool)
    acq = lm.reacquire(store, CombinedTracker(), cur, K, torch.eye(4).expand(2, 4, 4), T_cur, none, no,
                       torch.ones(2, dtype=torch.bool))  # fmt: skip
    index = lm.candidates(
        store, cur, K, torch.eye(4).expand(2, 4, 4), T_cur, none, no, torch.ones(2, dtype=torch.bool)
    )[0]
    truth = project(K.double(), transform_points(T_inv(T_cur), acq.points_world))
    err = (acq.pixels.double() - truth).norm(dim=-1)[acq.valid]
    slots = (index // 128)[acq.valid]
    counts = [int((slots == s).sum()) for s in range(3)]
    assert all(n >= low for n, low in zip(counts, (50, 50, 15), strict=True)) and acq.valid.sum(1).min() >= 60, counts
    assert float(err.median()) < 0.1 and float(err.max()) < 1.0, err
