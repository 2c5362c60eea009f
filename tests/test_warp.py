"""Pose-warped templates (torchtrack/image/warp.py): plane homography, depth normals and warped tracks vs exact truth."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from tolerances import LK_PX

from torchtrack.geometry import make_T, project, so3_exp, transform_points
from torchtrack.image.warp import (
    crop_at,
    depth_normals,
    plane_homography,
    sample_through,
    track_warped,
    translation_homography,
)

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


def test_depth_normals_of_a_plane_are_its_normal():
    n = F.normalize(torch.tensor([0.3, 0.2, -1.0], dtype=F64), dim=0)
    depth = _plane(n, -1.5)
    px = torch.tensor([[[100.0, 80.0], [320.0, 240.0], [500.3, 400.7]]], dtype=F64)
    normals, ok = depth_normals(depth, K1, px)
    assert bool(ok.all())
    torch.testing.assert_close(normals, n.expand(1, 3, 3), rtol=0, atol=1e-9)
    depth[..., 240, 317] = 0  # a hole next to the centre pixel
    assert depth_normals(depth, K1, px)[1].tolist() == [[True, False, True]]


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
