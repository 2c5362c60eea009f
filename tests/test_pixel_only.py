"""A tracked feature without depth (a hole, an edge, a band a separate depth camera does not see) is a pixel-only
measurement (eq. 7 needs no depth): the filter uses its pixel and not its 3D point.

Oracles: the update with a feature's depth missing equals the update where that feature's 3D variance is so large
that its 3D point carries no information (the limit the mask takes), and equals the update without the feature
when its pixel is dropped as well; a NaN depth sample behind the mask changes nothing; and the gate judges a
pixel-only feature by its own pixel test."""

import dataclasses

import torch
from test_backend_grad import noisy_observations, variances
from test_fusion import true_pose

from torchtrack.filter import FusionEKF, Variances
from torchtrack.filter.frame import ekf_frame

F64 = torch.float64


def one_frame(obs, var, gate=None, refit=None):
    ekf = FusionEKF(jacobian="forward")
    return ekf_frame(ekf, ekf.initial_state(true_pose(0.0)), obs, var, gate=gate, refit=refit)


def setup(seed=0):
    obs = noisy_observations(frames=1, outlier=False, seed=seed)[0]
    var_xyz, var_pix = variances(1, *obs.valid.shape)
    no_depth = torch.zeros_like(obs.valid)
    no_depth[0, 2:5] = True
    no_depth[1, 0] = True
    return obs, Variances(var_pix[0], var_xyz[0]), no_depth


def test_a_feature_without_depth_measures_its_pixel_only():
    obs, var, no_depth = setup()
    masked = one_frame(dataclasses.replace(obs, has_depth=~no_depth), var)
    huge = Variances(var.var_pix, torch.where(no_depth, torch.full_like(var.var_xyz, 1e12), var.var_xyz))
    limit = one_frame(obs, huge)
    torch.testing.assert_close(masked.T_cam_obj, limit.T_cam_obj, atol=1e-9, rtol=0)
    torch.testing.assert_close(masked.cov, limit.cov, atol=1e-12, rtol=1e-6)
    assert bool((masked.used_pix == obs.valid).all()) and not bool(masked.used_xyz[no_depth].any())
    without = one_frame(dataclasses.replace(obs, valid=obs.valid & ~no_depth), var)
    assert (masked.T_cam_obj - without.T_cam_obj).abs().max() > 1e-7  # the pixels do count


def test_nan_depth_behind_the_mask_changes_nothing():
    obs, var, no_depth = setup(seed=3)
    clean = one_frame(dataclasses.replace(obs, has_depth=~no_depth), var, gate=0.999, refit=0.999)
    points = torch.where(no_depth[..., None], torch.full_like(obs.points_d, float("nan")), obs.points_d)
    nan = one_frame(dataclasses.replace(obs, points_d=points, has_depth=~no_depth), var, gate=0.999, refit=0.999)
    torch.testing.assert_close(nan.T_cam_obj, clean.T_cam_obj, atol=0, rtol=0)
    assert torch.isfinite(nan.innovation).all()


def test_the_gate_drops_a_pixel_only_outlier_on_its_pixel_test():
    obs, var, no_depth = setup(seed=5)
    pixels = obs.pixels.clone()
    pixels[0, 3] += 40.0  # a gross pixel outlier among the pixel-only features
    out = one_frame(dataclasses.replace(obs, pixels=pixels, has_depth=~no_depth), var, gate=0.999)
    assert not bool(out.used_pix[0, 3])  # its own pixel test failed and it has no 3D point to vouch for it
    assert bool(out.used_pix[0, 2]) and bool(out.used_pix[0, 4])  # the other pixel-only features stay
    # with depth, the pixel goes with its 3D point (the pixel test alone is not calibrated): unchanged behaviour
    out = one_frame(dataclasses.replace(obs, pixels=pixels), var, gate=0.999)
    assert bool(out.used_pix[0, 3]) and bool(out.used_xyz[0, 3])


def blanked_run(root, overrides=()):
    """Track the render at ``root`` with the left half of every depth image from frame 3 on blanked: (poses, results)."""
    from test_frames_api import camera, capture

    from torchtrack.stream import RGBDTracker

    K, depth_scale = camera(root)
    stream = RGBDTracker(K, depth_scale=depth_scale, overrides=list(overrides), announce=False)
    results, step = [], stream.tracker.step
    stream.tracker.step = lambda frame: results.append(step(frame)) or results[-1]
    poses = []
    for k, (colour, depth) in enumerate(capture(root)):
        if k >= 3:
            depth = depth.copy()
            depth[:, : depth.shape[1] // 2] = 0
        poses.append(stream.track(colour, depth).T_world_color)
    return poses, results


def test_the_tracker_keeps_tracking_features_whose_depth_went_missing(tmp_path):
    """On a noise-free render, the left half of every depth image after the first frames is blanked (a band the depth
    camera does not see): the features there stay tracked as pixel-only measurements (the filter uses their pixels,
    not their 3D points), and the poses stay within 4 mm and 0.2 deg of the render's (measured with the default's dense
    map aligned every frame: 1.78 mm and 0.097 deg; without the map's weak-direction gate, ``+dense.weak=0``: 4.87 mm,
    half a surface leaves a direction the alignment wanders along; without the map 1.98 mm and 0.045 deg; with every
    depth image whole and no map 1.11 mm and 0.026 deg)."""
    import numpy as np

    from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence, sequence_poses
    from torchtrack.geometry import rotation_angle

    cfg = SyntheticConfig(width=320, height=240, frames=12, seed=3, mode="scene", noise="none")
    root = ensure_sequence(cfg, tmp_path)
    poses, results = blanked_run(root)
    pixel_only = 0
    for res in results[3:]:
        obs, est = res.observation, res.estimate
        only = obs.valid & ~obs.has_depth
        pixel_only += int(only.sum())
        assert bool((obs.pixels[..., 0][only] < 160 + 3).all())  # where the depth is missing (bilinear: 1 px wider)
        assert not bool(est.used_xyz[only].any())
        assert float(est.used_pix[only].float().mean()) > 0.9
    assert pixel_only > 100
    gt, est = sequence_poses(cfg).T_world_cam.numpy(), np.stack(poses)  # the stream's world is its first camera
    gt, est = np.linalg.inv(gt[0]) @ gt, np.linalg.inv(est[0]) @ est
    E = torch.as_tensor(np.linalg.inv(gt) @ est)
    assert float(E[:, :3, 3].norm(dim=-1).max()) < 4e-3 and float(rotation_angle(E[:, :3, :3]).rad2deg().max()) < 0.2
    # the paper (pipeline.pixel_only=false, +experiment=paper): a feature without depth leaves the model
    _, results = blanked_run(root, ["pipeline.pixel_only=false"])
    assert all(int((r.observation.valid & ~r.observation.has_depth).sum()) == 0 for r in results[1:])
