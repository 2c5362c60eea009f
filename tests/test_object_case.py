"""The object case: the small-object synthetic preset, tracking it against its exact ground truth, and
experiments/eval/object_case.py's table against its run folders."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data.synthetic import SyntheticConfig, default_scene, render_frame, render_sequence, sequence_poses
from torchtrack.factory import build_sequences, build_tracker
from torchtrack.geometry import T_inv, rotation_angle
from torchtrack.run import run_tracker

pytestmark = pytest.mark.slow  # the object-case script end to end


# ---------------------------------------------------------------------------------------------- the preset
def test_small_object_preset_geometry():
    """A static camera at object_distance_m from the object's centre (exactly, along the default viewing ray), only
    the object in view (empty background) on 5-15 % of the image, depths within the object's extent of it."""
    cfg = SyntheticConfig(mode="object", object="small", background=False, frames=30, noise="none")
    scene, poses = default_scene(cfg), sequence_poses(cfg)
    assert all(p.group == 1 for p in scene.primitives) and len(scene.primitives) == 3
    assert float(poses.T_cam_obj[0, :3, 3].norm()) == pytest.approx(0.55, abs=1e-9)
    radius = max(float(p.T_group_prim[:3, 3].norm()) + p.bounding_radius for p in scene.primitives)
    assert radius < 0.15  # a small object: ~18 cm across (its bounding sphere is generous)
    for i in (0, 29):
        depth = render_frame(scene, poses.T_world_cam[i], poses.T_world_obj[i]).depth
        valid = depth > 0
        assert 0.05 < float(valid.float().mean()) < 0.15
        z = float(poses.T_cam_obj[i, 2, 3])
        assert z - radius < float(depth[valid].min()) and float(depth[valid].max()) < z + radius
    far = SyntheticConfig(mode="object", object="small", object_distance_m=0.8, background=False)
    assert float(sequence_poses(far).T_cam_obj[0, :3, 3].norm()) == pytest.approx(0.8, abs=1e-9)


def test_new_keys_leave_the_old_digests_alone():
    """object / object_distance_m at their defaults are not part of the digest (cached sequences stay valid);
    any other value is."""
    base = SyntheticConfig(mode="object")
    assert "object" not in base.to_dict() and "object_distance_m" not in base.to_dict()
    digests = {
        base.digest(),
        SyntheticConfig(mode="object", object="small").digest(),
        SyntheticConfig(mode="object", object="small", object_distance_m=0.7).digest(),
    }
    assert len(digests) == 3
    with pytest.raises(ValueError, match="object must be one of"):
        SyntheticConfig(object="tiny")
    with pytest.raises(ValueError, match="object_distance_m must be > 0.1 m"):
        SyntheticConfig(object_distance_m=0.05)


# ---------------------------------------------------------------------------------------------- tracking it
@pytest.fixture(scope="module")
def clean_object(tmp_path_factory):
    cfg = SyntheticConfig(
        mode="object", object="small", background=False, noise="none", frames=12, trans_step_m=0.003, rot_step_deg=1.0
    )
    return render_sequence(cfg, tmp_path_factory.mktemp("object") / "small_object")


def track(folder, out, *overrides):
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
        cfg = compose("config", overrides=["data=tum", f"data.root={folder}", *overrides])
    (seq,) = build_sequences(cfg.data)
    (metrics,) = run_tracker(build_tracker(cfg), [seq], out, plots=False)
    traj = np.loadtxt(out / seq.name / "trajectory.txt", comments="#")
    return metrics, torch.as_tensor(traj), seq


def pose_errors(traj: torch.Tensor, seq) -> tuple[float, float]:
    """Largest position (m) and rotation (deg) error of the camera in the object's frame against the exact truth."""
    from torchtrack.geometry import make_T, quat_xyzw_to_matrix

    T = make_T(quat_xyzw_to_matrix(traj[:, 4:8]), traj[:, 1:4])
    gt = torch.as_tensor(np.asarray(seq.groundtruth)).double()
    dT = T_inv(gt) @ T
    return float(dT[:, :3, 3].norm(dim=-1).max()), float(rotation_angle(dT[:, :3, :3]).max()) * 180 / math.pi


def test_object_tracking_follows_the_exact_truth(clean_object, tmp_path):
    """region=object on the noise-free small object: the camera in the object's frame within 1.5 mm / 0.3 deg of the
    truth over 12 frames (1.03 mm, 0.11 deg), with the patches shrunk to the object (roi_fraction): many more features than the fixed
    grid gives (~20), which is what keeps the pose from following a few drifting tracks."""
    metrics, traj, seq = track(clean_object, tmp_path / "on", "region=object")
    pos, rot = pose_errors(traj, seq)
    assert pos < 1.25e-3 and rot < 0.15, (pos, rot)  # the fixed grid: 1.42 mm, 0.19 deg
    off, _, _ = track(clean_object, tmp_path / "off", "region=object", "select.roi_fraction=null")
    assert metrics["mean_features"] > 2.5 * off["mean_features"] and off["mean_features"] < 40


# ---------------------------------------------------------------------------------------------- the script
def test_object_case_script_table_matches_its_runs(tmp_path):
    """experiments/eval/object_case.py on a 4-frame case: the table's numbers are those of the run folders, and the
    exact dense peer (OpenCV RGB-D odometry) is within a millimetre of the truth on clean data."""
    pytest.importorskip("cv2")
    import object_case as oc  # experiments/eval/, on pytest's pythonpath

    args = ["--cases", "clean", "--frames", "4", "--peers", "cv2_rgbd", "--ours", "object=region=object"]
    assert oc.main([*args, "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "out")]) == 0
    (row,) = json.loads((tmp_path / "out" / "object_case.json").read_text())["rows"]
    run = json.loads((tmp_path / "out" / "ours" / "object" / row["sequence"] / "metrics.json").read_text())
    assert row["ours"]["object"]["ate_rmse_m"] == pytest.approx(run["ate_rmse_m"], rel=1e-9)
    assert row["frames"] == 4 and 0.05 < row["depth_fraction"] < 0.15 and row["best"] == "cv2_rgbd"
    assert row["peers"]["cv2_rgbd"]["ate_rmse_m"] < 1e-3
    md = (tmp_path / "out" / "object_case.md").read_text()
    assert f"{run['ate_rmse_m'] * 1e3:.1f} / {run['rpe_trans_m'] * 1e3:.2f}" in md
    with pytest.raises(SystemExit):
        oc.main(["--cases", "nope"])


def test_data_preset_is_the_slow_case():
    """data=synthetic_object is experiments/eval/object_case.py's "slow" case (same digest: same rendered folder)."""
    import object_case as oc  # experiments/eval/, on pytest's pythonpath

    with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
        cfg = compose("config", overrides=["data=synthetic_object", "region=object"])
    scene = SyntheticConfig(**cfg.data.scene)
    assert scene.digest() == oc.case_config("slow").digest()
    assert cfg.region.whole_frame is False and cfg.select.roi_fraction == 0.5
