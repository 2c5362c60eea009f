"""Depth-to-colour alignment: masked NCC, pixel map <-> intrinsics, shift/scale recovery, TumSequence option, real data.

Oracles: brute-force masked NCC; the closed-form pixel map of K_depth / K; depth images made unregistered by a known
map (recovered exactly when the intensity is a function of depth, within the content's own edge offset with
rendered colour or real frames); 7-Scenes against the Kinect v1 colour/depth focal ratio 525/585 and against its
own edges after warp_depth.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from kornia.color import rgb_to_grayscale
from tolerances import F64_UNIT

from torchtrack.data import DataError, TumSequence
from torchtrack.data.alignment import ShiftEstimate, colour_intrinsics, depth_intrinsics, estimate_depth_shift
from torchtrack.data.edge_match import depth_edges, intensity_edges, masked_ncc
from torchtrack.geometry import backproject, intrinsics_matrix, project, warp_depth

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data not present")


# ----------------------------------------------------------------------------------------------- helpers


def unregister(depth: torch.Tensor, centre, shift, scale: float = 1.0) -> torch.Tensor:
    """The depth camera's image for the map colour = c + s (depth - c) + t: depth_d(u) = depth(c + s (u - c) + t).

    Backward nearest sampling of a registered depth (B, 1, H, W) (T_color_depth = I: no parallax), 0 outside.
    """
    B, _, H, W = depth.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=depth.dtype), torch.arange(W, dtype=depth.dtype), indexing="ij")
    u = centre[0] + scale * (xs - centre[0]) + shift[0]
    v = centre[1] + scale * (ys - centre[1]) + shift[1]
    grid = torch.stack([2 * u / (W - 1) - 1, 2 * v / (H - 1) - 1], -1).expand(B, H, W, 2)
    return F.grid_sample(depth, grid, mode="nearest", padding_mode="zeros", align_corners=True)


def edge_ncc(gray: torch.Tensor, depth: torch.Tensor) -> float:
    """Frame-averaged NCC of depth edges with intensity edges at the same pixel (both (B, 1, H, W), one grid)."""
    D, M = depth_edges(depth)
    G = intensity_edges(gray)
    return float(masked_ncc(D[:, 0], M[:, 0], G[:, 0], 0)[:, 0, 0].mean())


def brute_masked_ncc(t: np.ndarray, mask: np.ndarray, s: np.ndarray, m: int) -> np.ndarray:
    out = np.zeros((2 * m + 1, 2 * m + 1))
    H, W = t.shape
    ys, xs = np.nonzero(mask)
    a = t[ys, xs] - t[ys, xs].mean()
    for dy in range(-m, m + 1):
        for dx in range(-m, m + 1):
            b = s[(ys + dy) % H, (xs + dx) % W]
            b = b - b.mean()
            out[m + dy, m + dx] = (a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum())
    return out


def write_folder(root: Path, n: int = 3, H: int = 6, W: int = 8, intrinsics: str = "100 100 4 3 1000") -> Path:
    rng = np.random.default_rng(0)
    for kind in ("rgb", "depth"):
        (root / kind).mkdir(parents=True)
        lines = []
        for i in range(n):
            img = (
                rng.integers(0, 256, (H, W, 3), np.uint8)
                if kind == "rgb"
                else rng.integers(500, 5000, (H, W), np.uint16)
            )
            assert cv2.imwrite(str(root / kind / f"{i}.png"), img)
            lines.append(f"{i / 30:.6f} {kind}/{i}.png")
        (root / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    (root / "intrinsics.txt").write_text(intrinsics + "\n")
    return root


@pytest.fixture(scope="module")
def rendered():
    """Three noise-free registered frames (rgb (3,3,H,W), depth (3,1,H,W)) of the synthetic room, and its centre."""
    from torchtrack.data.synthetic import SyntheticConfig, default_scene, render_frame, sequence_poses

    cfg = SyntheticConfig(frames=30, seed=0, mode="scene", noise="none")
    out = render_frame(default_scene(cfg), sequence_poses(cfg).T_world_cam[[0, 14, 29]])
    return out.rgb, out.depth, (cfg.cx, cfg.cy)


# ----------------------------------------------------------------------------------------------- masked NCC


@pytest.mark.equivalence
def test_masked_ncc_equals_brute_force_and_batched_equals_looped():
    g = torch.Generator().manual_seed(0)
    N, H, W, m = 3, 20, 24, 3
    t = torch.rand(N, H, W, generator=g, dtype=torch.float64)
    s = torch.rand(N, H, W, generator=g, dtype=torch.float64)
    mask = (torch.rand(N, H, W, generator=g) > 0.3).double()
    mask[:, :m], mask[:, -m:], mask[:, :, :m], mask[:, :, -m:] = 0, 0, 0, 0
    out = masked_ncc(t, mask, s, m)
    assert out.shape == (N, 2 * m + 1, 2 * m + 1)
    for n in range(N):
        ref = brute_masked_ncc(t[n].numpy(), mask[n].numpy() > 0, s[n].numpy(), m)
        np.testing.assert_allclose(out[n].numpy(), ref, atol=1e-9)
        torch.testing.assert_close(masked_ncc(t[n : n + 1], mask[n : n + 1], s[n : n + 1], m)[0], out[n])


def test_masked_ncc_peaks_at_a_known_shift():
    g = torch.Generator().manual_seed(1)
    s = torch.rand(1, 40, 48, generator=g)
    t = torch.roll(s, shifts=(-3, 5), dims=(-2, -1))  # t(p) = s(p + (dx, dy)) with dx = -5, dy = 3
    mask = torch.zeros_like(s)
    mask[:, 8:-8, 8:-8] = 1
    S = masked_ncc(t, mask, s, 6)[0]
    iy, ix = divmod(int(S.argmax()), 13)
    assert (ix - 6, iy - 6) == (-5, 3) and abs(float(S.max()) - 1) < 1e-5


def test_intensity_edges_of_a_plane_are_its_slope():
    """The blurred central-difference gradient of a plane a u + b v is sqrt(a^2 + b^2) away from the border, 0 on it."""
    v, u = torch.meshgrid(
        torch.arange(48.0, dtype=torch.float64), torch.arange(64.0, dtype=torch.float64), indexing="ij"
    )
    G = intensity_edges((0.003 * u - 0.004 * v)[None, None], sigma=1.0)[0, 0]
    torch.testing.assert_close(G[5:-5, 5:-5], torch.full_like(G[5:-5, 5:-5], 0.005), atol=F64_UNIT, rtol=0)
    assert G[0].abs().max() == G[:, -1].abs().max() == 0


def test_depth_edges_mark_steps_not_slopes_and_skip_holes():
    z = torch.linspace(1.0, 1.2, 64).repeat(48, 1)  # a slope: 0.3 % per pixel
    z[:, 40:] = 2.0  # a step at x = 39.5
    z[5:10, 5:10] = 0  # a hole
    D, M = depth_edges(z[None, None], sigma=0.5)
    assert D.shape == M.shape == (1, 1, 48, 64)
    assert D[0, 0, 20, 39] > 0.5 and D[0, 0, 20, 40] > 0.5 and float(D[0, 0, 20, 15:30].max()) < 1e-3
    assert M[0, 0, 4:11, 4:11].sum() == 0 and M[0, 0, 20, 20] == 1


# ----------------------------------------------------------------------------------------------- intrinsics


@pytest.mark.parametrize("est", [(-10.0, 8.0), (3.0, -2.5, 0.9), (0.0, 0.0, 1.1)])
def test_depth_intrinsics_realise_the_map(est):
    K = intrinsics_matrix(585.0, 585.0, 320.0, 240.0).double()
    Kd = depth_intrinsics(K, est)
    dx, dy, s = est[0], est[1], est[2] if len(est) == 3 else 1.0
    if len(est) == 2:
        torch.testing.assert_close(Kd[:2, 2], torch.tensor([330.0, 232.0], dtype=torch.float64))  # cx - dx, cy - dy
    g = torch.Generator().manual_seed(2)
    u_d = torch.rand(50, 2, generator=g, dtype=torch.float64) * torch.tensor([640.0, 480.0])
    z = 0.5 + 3 * torch.rand(50, generator=g, dtype=torch.float64)
    u_c = project(K, backproject(Kd, u_d, z))  # T_color_depth = I
    c = K[:2, 2]
    torch.testing.assert_close(u_c, c + s * (u_d - c) + torch.tensor([dx, dy], dtype=torch.float64))
    torch.testing.assert_close(
        colour_intrinsics(Kd, ShiftEstimate(dx, dy, s, 0, 0, True, (320.0, 240.0), 0, 0, (0, 0))), K
    )


def test_colour_intrinsics_inverts_depth_intrinsics_about_any_centre():
    K = intrinsics_matrix(525.0, 530.0, 318.0, 243.0).double()
    est = ShiftEstimate(-6.7, -1.5, 0.896, 0.0, 0.0, True, (320.0, 240.0), 5, 5, (480, 640))
    torch.testing.assert_close(depth_intrinsics(colour_intrinsics(K, est), est), K)
    torch.testing.assert_close(colour_intrinsics(depth_intrinsics(K, est), est), K)


def test_bad_inputs_raise():
    K = intrinsics_matrix(500.0, 500.0, 32.0, 24.0)
    with pytest.raises(ValueError, match="scale must be positive"):
        depth_intrinsics(K, (1.0, 2.0, 0.0))
    with pytest.raises(ValueError, match="need a ShiftEstimate"):
        depth_intrinsics(K, (1.0,))
    g, d = torch.rand(1, 1, 200, 240), torch.rand(1, 1, 200, 240) + 1
    with pytest.raises(ValueError, match="differ in shape"):
        estimate_depth_shift(g, d[..., :100])
    with pytest.raises(ValueError, match=r"must be \(1, H, W\)"):
        estimate_depth_shift(g[0, 0], d[0, 0])
    with pytest.raises(ValueError, match="max_shift"):
        estimate_depth_shift(g, d, max_shift=100)
    with pytest.raises(ValueError, match="scale_range"):
        estimate_depth_shift(g, d, scale_range=(1.1, 0.9))


# ----------------------------------------------------------------------------------------------- estimation


@pytest.mark.parametrize("truth", [(-10, 8, 1.0), (17.5, -6.25, 1.0), (-7, -2, 0.9), (3, 4, 1.08)])
def test_exact_recovery_when_intensity_edges_are_depth_edges(rendered, truth):
    """Gray = a function of depth: every colour edge is a depth edge, so the map is recovered exactly."""
    _, depth, c = rendered
    gray = (0.5 / depth.clamp_min(0.1)).clamp(0, 1)
    d = unregister(depth, c, truth[:2], truth[2])
    est = estimate_depth_shift(gray, d, centre=c, min_spread=0.0)  # props in the middle: allow the scale anyway
    assert est.confident and est.frames == est.frames_agreeing == 3, est
    assert abs(est.dx - truth[0]) < 0.5 and abs(est.dy - truth[1]) < 0.5 and abs(est.scale - truth[2]) < 0.005, est
    assert est.score > 0.85 > est.score_at_zero


def test_rendered_colour_shift_recovered_and_registered_left_alone(rendered):
    """Rendered colour (textures, shading): shifts within 1 px of the truth relative to the registered estimate.

    The registered frames' own estimate is the content's edge offset (shading moves intensity edges off the
    silhouettes by about a pixel); it is not confident, and moves no pixel by 2 px.
    """
    rgb, depth, c = rendered
    base = estimate_depth_shift(rgb_to_grayscale(rgb), depth, centre=c)
    assert not base.confident or base.max_displacement() < 2.0, base
    assert abs(base.dx) < 2 and abs(base.dy) < 2 and base.scale == 1.0
    est = estimate_depth_shift(rgb_to_grayscale(rgb), unregister(depth, c, (-10, 8)), centre=c)
    assert est.confident and est.scale == 1.0, est
    assert abs(est.dx - base.dx + 10) < 1 and abs(est.dy - base.dy - 8) < 1, (est, base)
    shift_only = estimate_depth_shift(rgb_to_grayscale(rgb), unregister(depth, c, (-10, 8)), centre=c, scale_range=None)
    assert abs(shift_only.dx - est.dx) < 0.5 and abs(shift_only.dy - est.dy) < 0.5


def test_single_object_scene_is_left_alone():
    """One textured object in front of a far room (registered, 320 x 240): its depth edges form one compact
    contour, whose magnification is confounded with the object's texture; no map may be applied."""
    from torchtrack.data.synthetic import SyntheticConfig, default_scene, render_frame, sequence_poses

    cfg = SyntheticConfig(width=320, height=240, frames=12, seed=0, mode="object", noise="none")
    poses = sequence_poses(cfg)
    idx = [0, 3, 6, 9, 11]
    out = render_frame(default_scene(cfg), poses.T_world_cam[idx], poses.T_world_obj[idx])
    est = estimate_depth_shift(rgb_to_grayscale(out.rgb), out.depth, centre=(cfg.cx, cfg.cy))
    assert est.scale == 1.0 and (not est.confident or est.max_displacement() < 2.0), est


def test_estimate_is_deterministic_and_list_equals_batch(rendered):
    rgb, depth, c = rendered
    d = unregister(depth, c, (5, -3))
    a = estimate_depth_shift(rgb_to_grayscale(rgb), d, centre=c)
    b = estimate_depth_shift(list(rgb_to_grayscale(rgb)), list(d), centre=c)
    assert a == b


@pytest.mark.data
@needs_data
def test_real_frames_shift_and_scale_recovered():
    """sun3d_fragment1 (registered Kinect frames) made unregistered by known maps: recovered relative to its own
    estimate (the data's own offset is (0.3, -1.7) px, below the confidence gain)."""
    seq = TumSequence(DATA / "sun3d_fragment1", depth_alignment="none")
    frames = [seq[i] for i in (0, 24, 49)]
    gray, depth = rgb_to_grayscale(torch.stack([f.rgb for f in frames])), torch.stack([f.depth for f in frames])
    c = (float(seq.K[0, 2]), float(seq.K[1, 2]))
    base = estimate_depth_shift(gray, depth, centre=c)
    assert not base.confident, base
    for truth in [(-10, 8, 1.0), (-7, -2, 0.9)]:
        est = estimate_depth_shift(gray, unregister(depth, c, truth[:2], truth[2]), centre=c)
        assert est.confident, est
        assert abs(est.dx - base.dx - truth[0]) < 1 and abs(est.dy - base.dy - truth[1]) < 1, (est, base)
        assert abs(est.scale - truth[2]) < 0.005, est


# ----------------------------------------------------------------------------------------------- TumSequence


def test_sequence_given_shift_sets_depth_intrinsics(tmp_path):
    root = write_folder(tmp_path / "s")
    seq = TumSequence(root, depth_alignment=(-10, 8))
    assert seq.depth_aligned and seq.depth_shift.dx == -10 and seq.depth_shift.frames == 0
    torch.testing.assert_close(seq.K_depth, intrinsics_matrix(100.0, 100.0, 14.0, -5.0))  # cx - dx, cy - dy
    torch.testing.assert_close(seq.T_color_depth, torch.eye(4))
    seq = TumSequence(root, depth_alignment=[2, 1, 0.5], intrinsics_camera="depth")
    torch.testing.assert_close(seq.K_depth, intrinsics_matrix(100.0, 100.0, 4.0, 3.0))  # as given
    torch.testing.assert_close(seq.K, intrinsics_matrix(50.0, 50.0, 6.0, 4.0))


def test_sequence_auto_on_small_images_and_none(tmp_path):
    root = write_folder(tmp_path / "s")
    for mode in ("auto", "none"):
        seq = TumSequence(root, depth_alignment=mode)
        assert seq.depth_shift is None and not seq.depth_aligned
        torch.testing.assert_close(seq.K_depth, seq.K)
    seq = TumSequence(root, intrinsics_depth=(90, 90, 4, 3))  # explicit: no estimation, as given
    assert seq.depth_shift is None and seq.K_depth[0, 0] == 90


def test_sequence_bad_alignment_options_raise(tmp_path):
    root = write_folder(tmp_path / "s")
    with pytest.raises(ValueError, match="depth_alignment must be 'auto', 'none'"):
        TumSequence(root, depth_alignment="yes")
    with pytest.raises(ValueError, match=r"\(dx, dy\) or \(dx, dy, scale > 0\)"):
        TumSequence(root, depth_alignment=(1, 2, 3, 4))
    with pytest.raises(ValueError, match="either depth_alignment"):
        TumSequence(root, depth_alignment=(1, 2), T_color_depth=np.eye(4))
    with pytest.raises(ValueError, match="intrinsics_camera"):
        TumSequence(root, intrinsics_camera="ir")


def test_sequence_auto_survives_a_corrupt_frame(tmp_path):
    """A frame that cannot be read skips the estimate; the error comes when the frame itself is read."""
    root = write_folder(tmp_path / "s", H=200, W=240)
    (root / "depth" / "2.png").write_bytes(b"not a png")
    seq = TumSequence(root, depth_alignment="auto")
    assert seq.depth_shift is None and not seq.depth_aligned
    with pytest.raises(DataError, match="corrupt"):
        seq[2]


REGISTERED = ["visp_castle_simu", "sun3d_fragment1", "sun3d_fragment2", "visp_rbt_sequence"]


@pytest.mark.data
@needs_data
@pytest.mark.parametrize("name", REGISTERED)
def test_registered_sequences_are_left_alone(name):
    seq = TumSequence(DATA / name, depth_alignment="auto")
    est = seq.depth_shift
    assert est is not None and est.frames == 5
    assert not est.confident or est.max_displacement() < 2.0, est
    assert not seq.depth_aligned and torch.equal(seq.K_depth, seq.K)


@pytest.mark.data
@needs_data
def test_7scenes_depth_registered_by_the_estimated_map():
    """7-Scenes (Kinect v1, depth not registered): the map is a magnification by the colour/depth focal ratio
    (525 / 585 = 0.897 for Kinect v1's colour and depth cameras) plus a shift; warping depth with the resulting
    K_depth registers it: on frames not used by the estimate, the depth edges match the colour edges far better."""
    seq = TumSequence(DATA / "7scenes_redkitchen", depth_alignment="auto")
    est = seq.depth_shift
    assert seq.depth_aligned and est.confident and abs(est.scale - 525 / 585) < 0.01, est
    assert est.max_displacement() > 30  # a constant shift cannot register it
    frames = [seq[i] for i in (120, 420, 870)]
    gray, depth = rgb_to_grayscale(torch.stack([f.rgb for f in frames])), torch.stack([f.depth for f in frames])
    B = len(frames)
    warped = warp_depth(
        depth, seq.K_depth.expand(B, 3, 3), seq.K.expand(B, 3, 3), torch.eye(4).expand(B, 4, 4), (480, 640)
    )
    before, after = edge_ncc(gray, depth), edge_ncc(gray, warped)
    assert after > 2 * before, (before, after)
    # the same map with the given intrinsics as the depth camera's: K_depth as given, colour focal ~525 px
    seq_d = TumSequence(DATA / "7scenes_redkitchen", depth_alignment="auto", intrinsics_camera="depth")
    torch.testing.assert_close(seq_d.K_depth, intrinsics_matrix(585.0, 585.0, 320.0, 240.0))
    assert abs(float(seq_d.K[0, 0]) - 525) < 6
    torch.testing.assert_close(depth_intrinsics(seq_d.K, est), seq_d.K_depth)
