"""Keyframe alignment (torchtrack.keyframes): exact synthetic oracle, identity, batched == looped, bad input."""

import math

import pytest
import torch

from torchtrack.geometry import T_inv, se3_exp, se3_log
from torchtrack.keyframes import KeyframeAligner, align_coarse_to_fine, align_to_keyframe, downsample

H, W = 120, 160
K1 = torch.tensor([[130.0, 0.0, 79.5], [0.0, 130.0, 59.5], [0.0, 0.0, 1.0]])
# a corner of a room: back wall z = 2.0, floor y = 0.6, side wall x = -0.9 (plane n.X = c, camera at the origin)
PLANES = [
    (torch.tensor([0.0, 0.0, 1.0]), 2.0),
    (torch.tensor([0.0, 1.0, 0.0]), 0.6),
    (torch.tensor([1.0, 0.0, 0.0]), -0.9),
]


def texture(X):
    """Smooth procedural grey value of world points X (..., 3), in [0.1, 0.9]."""
    return (
        0.5
        + 0.2 * torch.sin(7 * X[..., 0] + 3 * X[..., 1]) * torch.cos(5 * X[..., 2] - 4 * X[..., 1])
        + 0.2 * (torch.sin(11 * X[..., 1] + 9 * X[..., 2] + 2 * X[..., 0]))
    )


def render(T_world_cam):
    """Ray-cast grey and depth (1, 1, H, W) float64 of the room corner from camera T_world_cam (4, 4)."""
    T = T_world_cam.double()
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K1[0, 2]) / K1[0, 0], (v - K1[1, 2]) / K1[1, 1], torch.ones_like(u)], -1)  # z = 1
    d_w, o = rays @ T[:3, :3].T, T[:3, 3]
    best = torch.full((H, W), float("inf"), dtype=torch.float64)
    for n, c in PLANES:
        n = n.double()
        s = (c - (n * o).sum()) / (d_w @ n)  # ray parameter = depth (rays have z = 1 in the camera)
        best = torch.where((s > 0.1) & (s < best), s, best)
    X = o + d_w * best[..., None]
    return texture(X)[None, None], best[None, None].float()


def pose(v, w):
    return se3_exp(torch.tensor([*v, *w], dtype=torch.float64))


def test_recovers_known_pose():
    T_w_ref = pose([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    T_w_cur = pose([0.03, -0.02, 0.04], [0.02, -0.03, 0.015])
    g_r, d_r = render(T_w_ref)
    g_c, d_c = render(T_w_cur)
    T_true = T_inv(T_w_ref) @ T_w_cur
    res = align_coarse_to_fine(g_c, d_c, g_r, d_r, K1[None], torch.eye(4, dtype=torch.float64)[None], levels=(2, 1))
    err = se3_log(T_inv(T_true) @ res.T_ref_cur[0])
    # tolerance from the resolution: 0.1 px at the finest grid, f = 130 px at ~2 m depth -> 1.5 mm, 0.8 mrad
    assert bool(res.valid[0])
    assert err[:3].norm() < 0.1 * 2.0 / 130.0
    assert err[3:].norm() < 0.1 / 130.0
    assert se3_log(T_true)[:3].norm() > 0.05  # the start is far from the answer


@pytest.mark.parametrize("terms", [dict(use_geometric=False), dict(use_photometric=False)])
def test_each_term_alone_recovers_pose(terms):
    T_w_cur = pose([0.01, 0.015, -0.02], [-0.01, 0.02, 0.0])
    g_r, d_r = render(torch.eye(4, dtype=torch.float64))
    g_c, d_c = render(T_w_cur)
    res = align_coarse_to_fine(g_c, d_c, g_r, d_r, K1[None], torch.eye(4, dtype=torch.float64)[None], iters=10, **terms)
    err = se3_log(T_inv(T_w_cur) @ res.T_ref_cur[0])
    assert err[:3].norm() < 0.2 * 2.0 / 130.0 and err[3:].norm() < 0.2 / 130.0


def test_identity_when_frames_identical():
    g, d = render(pose([0.01, 0.0, 0.0], [0.0, 0.01, 0.0]))
    res = align_to_keyframe(g, d, g, d, K1[None], torch.eye(4, dtype=torch.float64)[None])
    assert torch.allclose(res.T_ref_cur[0], torch.eye(4, dtype=torch.float64), atol=1e-9)


@pytest.mark.equivalence
def test_batched_equals_looped():
    poses = [pose([0.02, 0.0, 0.01], [0.0, 0.01, 0.0]), pose([-0.01, 0.02, 0.0], [0.015, 0.0, -0.01])]
    refs = [torch.eye(4, dtype=torch.float64), pose([0.0, 0.01, 0.0], [0.0, 0.0, 0.01])]
    cur = [render(T) for T in poses]
    ref = [render(T) for T in refs]
    init = torch.stack([T_inv(r) @ p @ pose([0.005, 0, 0], [0, 0, 0.005]) for r, p in zip(refs, poses, strict=True)])
    batched = align_coarse_to_fine(
        torch.cat([c[0] for c in cur]), torch.cat([c[1] for c in cur]), torch.cat([r[0] for r in ref]),
        torch.cat([r[1] for r in ref]), K1.expand(2, 3, 3), init,
    )  # fmt: skip
    for b in range(2):
        one = align_coarse_to_fine(cur[b][0], cur[b][1], ref[b][0], ref[b][1], K1[None], init[b : b + 1])
        assert torch.allclose(batched.T_ref_cur[b], one.T_ref_cur[0], atol=1e-9)


def test_aligner_corrects_against_nearest_keyframe():
    kf_poses = [torch.eye(4, dtype=torch.float64), pose([0.3, 0.0, 0.0], [0.0, 0.2, 0.0])]
    aligner = KeyframeAligner(count=2, factor=1, levels=(2, 1))
    for T in kf_poses:
        g, d = render(T)
        aligner.add(g, d, K1[None], T[None], torch.ones(1, dtype=torch.bool))
    T_true = pose([0.02, 0.01, 0.0], [0.01, 0.0, 0.0])  # near the first keyframe
    g, d = render(T_true)
    T_est = pose([0.0, 0.0, 0.01], [0.0, 0.0, 0.0]) @ T_true  # 1 cm off
    fix = aligner.correct(g, d, T_est[None], torch.ones(1, dtype=torch.bool))
    assert bool(fix.used[0]) and not bool(fix.latest[0])  # the first keyframe is nearer than the newest
    assert se3_log(T_inv(T_true) @ fix.T_world_color[0])[:3].norm() < 0.1 * 2.0 / 130.0


def test_bad_input_raises():
    g, d = render(torch.eye(4, dtype=torch.float64))
    with pytest.raises(ValueError, match="depth_ref"):
        align_to_keyframe(g, d, g, d[..., :-1], K1[None], torch.eye(4)[None])
    with pytest.raises(ValueError, match="downsample"):
        downsample(g[0], d[0], K1[None], 2)
    with pytest.raises(ValueError, match="blend"):
        KeyframeAligner(blend=0.0)


def test_downsample_intrinsics_keep_pixel_centres():
    g, d = render(torch.eye(4, dtype=torch.float64))
    _, d2, K2 = downsample(g, d, K1[None], 2)
    # the coarse pixel centre (0, 0) is the fine pixel (0.5, 0.5): same ray
    ray_fine = (0.5 - K1[0, 2]) / K1[0, 0]
    ray_coarse = (0.0 - K2[0, 0, 2]) / K2[0, 0, 0]
    assert math.isclose(float(ray_fine), float(ray_coarse), rel_tol=1e-6)
