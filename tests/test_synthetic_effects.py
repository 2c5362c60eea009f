"""Real-sensor effects of the synthetic renderer (torchtrack/data/synthetic/effects.py, config.SensorEffects), each
against its definition: the misregistration shift against a loop; the time offset against the plain sequence's
later frame (the same pose, so the same depth); motion blur against the mean of renders at the sub-exposure poses;
the lighting gain against the clean render times 1 + A sin(2 pi t / T); flying pixels against the 3 x 3 range
written out here; the depth-noise level against the measured standard deviation on a wall.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import torch

from torchtrack.data.synthetic import (
    RGBD,
    KinectNoise,
    SyntheticConfig,
    apply_kinect_noise,
    default_scene,
    depth_sigma,
    render_frame,
    render_sequence,
    sequence_poses,
)
from torchtrack.data.synthetic.config import SensorEffects
from torchtrack.data.synthetic.effects import blur_offsets, edge_range, flying_pixels, shift_depth

TINY = dict(width=64, height=48, frames=3, noise="none", trans_step_m=0.03, rot_step_deg=2.0)


def pngs(folder, i: int) -> tuple[np.ndarray, np.ndarray]:
    stamp = f"{i / 30.0:.6f}"
    rgb = cv2.imread(str(folder / "rgb" / f"{stamp}.png"), cv2.IMREAD_UNCHANGED)[:, :, ::-1].astype(np.float64) / 255
    return rgb, cv2.imread(str(folder / "depth" / f"{stamp}.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000


def test_off_by_default_and_same_digests():
    cfg = SyntheticConfig()
    assert cfg.effects == SensorEffects() and cfg.kinect.sigma_scale == 1.0
    d = cfg.to_dict()
    assert "effects" not in d and "sigma_scale" not in d["kinect"]  # the cached renders keep their names
    on = SyntheticConfig(effects={"depth_shift_px": [2, -1]}, kinect={"sigma_scale": 2.0})
    assert on.to_dict()["effects"]["depth_shift_px"] == [2, -1] and on.digest() != cfg.digest()
    with pytest.raises(ValueError, match="flying_pixel_prob"):
        SensorEffects(flying_pixel_prob=1.5)


def test_shift_depth_against_a_loop():
    depth = torch.rand(2, 1, 6, 7) + 0.5
    for dx, dy in [(2, 1), (-3, 0), (0, -2), (7, 0)]:
        out = shift_depth(depth, dx, dy)
        for v in range(6):
            for u in range(7):
                want = depth[..., v - dy, u - dx] if 0 <= v - dy < 6 and 0 <= u - dx < 7 else torch.zeros(2, 1)
                assert torch.equal(out[..., v, u], want), (dx, dy, u, v)


def test_timing_and_lighting_effects_against_their_definitions(tmp_path):
    plain = render_sequence(SyntheticConfig(seed=4, **TINY), tmp_path / "plain")
    e = dict(depth_time_offset_s=1 / 30, depth_shift_px=(1, 2), blur_exposure_s=0.02, blur_samples=3,
             light_gain_amplitude=0.3, light_period_s=0.2)  # fmt: skip
    cfg = SyntheticConfig(seed=4, effects=e, **TINY)
    out = render_sequence(cfg, tmp_path / "fx")
    scene = default_scene(cfg)
    for i in range(2):
        rgb, depth = pngs(out, i)
        _, later = pngs(plain, i + 1)  # depth taken one frame later, then moved by (1, 2) px
        assert np.array_equal(depth[2:, 1:], later[:-2, :-1]) and not depth[:2].any() and not depth[:, :1].any()
        assert blur_offsets(cfg.effects) == pytest.approx([-0.01, 0.0, 0.01])
        sub = [sequence_poses(cfg, dt).T_world_cam[i] for dt in (-0.01, 0.0, 0.01)]
        mean = torch.stack([render_frame(scene, T).rgb for T in sub]).mean(0).double()
        gain = 1 + 0.3 * math.sin(2 * math.pi * (i / 30) / 0.2)
        want = (mean * gain).clamp(0, 1).permute(1, 2, 0).numpy()
        assert np.abs(rgb - want).max() <= 0.5 / 255 + 1e-6, i  # 8-bit rounding
        sharp = render_frame(scene, sub[1]).rgb.double().permute(1, 2, 0).numpy()
        assert np.abs(rgb - (sharp * gain).clip(0, 1)).max() > 2 / 255  # blur changed the image


def test_flying_pixels_mix_the_two_sides_of_an_edge():
    clean = torch.full((1, 1, 20, 30), 1.0, dtype=torch.float64)
    clean[..., 10:, :] = 2.5  # an edge between rows 9 and 10
    clean[..., :3, :] = 0.0  # empty space above: a silhouette, no mixing
    edge, lo, hi = edge_range(clean, 0.05)
    rows = edge[0, 0].any(1).nonzero().flatten().tolist()
    assert (
        rows == [9, 10] and bool(edge[0, 0, 9].all()) and float(lo[0, 0, 9, 5]) == 1.0 and float(hi[0, 0, 9, 5]) == 2.5
    )
    measured = clean + 0.001
    every = flying_pixels(measured, clean, 1.0, 0.05, torch.Generator().manual_seed(0))
    changed = every != measured
    assert torch.equal(changed, edge) and bool(((every >= 1.0) & (every <= 2.5))[edge].all())
    assert float(every[edge].std()) > 0.3  # a ~ U(0, 1): std 1.5 / sqrt(12) = 0.43
    some = flying_pixels(measured, clean, 0.3, 0.05, torch.Generator().manual_seed(1))
    frac = float((some != measured)[edge].double().mean())
    assert abs(frac - 0.3) < 4 * math.sqrt(0.3 * 0.7 / int(edge.sum())) and torch.equal(some[~edge], measured[~edge])


@pytest.mark.parametrize("scale", [0.5, 3.0])
def test_depth_noise_level_scales_sigma(scale):
    z = 2.0
    k = KinectNoise(disparity_subpixel=0.0, dropout_prob=0.0, sigma_scale=scale)
    frame = RGBD(torch.full((3, 120, 160), 0.5), torch.full((1, 120, 160), z))
    noisy = apply_kinect_noise(frame, k, torch.Generator().manual_seed(0))
    err = (noisy.depth - frame.depth)[noisy.depth > 0]
    sigma = scale * (0.0012 + 0.0019 * (z - 0.4) ** 2)
    assert float(depth_sigma(torch.tensor(z), k)) == pytest.approx(sigma)
    assert float(err.std()) == pytest.approx(sigma, rel=0.05)  # 19k samples: the std's rel. spread ~0.5 %
