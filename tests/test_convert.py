"""torchtrack.data.convert: 7-Scenes / 3DMatch frame folders and SUN3D sequences into the TUM layout. Oracle: the
source's own values (depth in millimetres, 4x4 camera-to-world poses, intrinsics) read back through TumSequence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from torchtrack.data import TumSequence
from torchtrack.data.convert import convert_frames, convert_sun3d, main
from torchtrack.data.errors import DataError

H, W = 30, 40


def rigid(rng: np.random.Generator) -> np.ndarray:
    """A camera-to-world pose from a random axis-angle (< 1 rad) and translation (< 1 m)."""
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rng.uniform(-0.5, 0.5, 3))[0]
    T[:3, 3] = rng.uniform(-1, 1, 3)
    return T


def depth_mm(rng: np.random.Generator, invalid: int) -> np.ndarray:
    d = rng.integers(400, 4000, (H, W)).astype(np.uint16)  # 0.4-4 m
    d[:3, :5] = invalid
    return d


@pytest.fixture
def frames_folder(tmp_path) -> tuple[Path, list, list]:
    """A 7-Scenes-like sequence: 4 frames, depth with 65535 holes, the third pose lost (-inf, as 3DMatch marks it)."""
    src, rng = tmp_path / "seq-01", np.random.default_rng(0)
    src.mkdir()
    depths, poses = [], []
    for i in range(4):
        cv2.imwrite(str(src / f"frame-{i:06d}.color.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        depths.append(depth_mm(rng, 65535))
        cv2.imwrite(str(src / f"frame-{i:06d}.depth.png"), depths[-1])
        poses.append(rigid(rng) if i != 2 else np.full((4, 4), -np.inf))
        np.savetxt(src / f"frame-{i:06d}.pose.txt", poses[-1])
    return src, depths, poses


def test_frames_read_back_as_the_source(frames_folder, tmp_path):
    src, depths, poses = frames_folder
    seq = TumSequence(convert_frames(src, tmp_path / "tum", intrinsics=(585, 585, 320, 240)))
    assert len(seq) == 4 and seq.depth_scale == 1000.0
    np.testing.assert_allclose(seq.K.numpy(), [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    np.testing.assert_allclose(seq.timestamps, np.arange(4) / 30, atol=1e-6)
    for i in range(4):
        frame = seq[i]
        expected = np.where(depths[i] == 65535, 0, depths[i]) / 1000.0  # 65535 = no measurement
        np.testing.assert_allclose(frame.depth[0].numpy(), expected, rtol=1e-6)
        assert (src / f"frame-{i:06d}.color.png").read_bytes() == seq.rgb_paths[i].read_bytes()  # copied unchanged
    assert seq.gt_valid.tolist() == [True, True, False, True]
    for i in (0, 1, 3):
        np.testing.assert_allclose(seq.groundtruth[i], poses[i], atol=1e-7)


def test_frames_take_camera_intrinsics_from_one_folder_up(frames_folder, tmp_path):
    src, _, _ = frames_folder
    with pytest.raises(DataError, match="--intrinsics"):
        convert_frames(src, tmp_path / "none")
    np.savetxt(src.parent / "camera-intrinsics.txt", [[570.3, 0, 320], [0, 570.3, 240], [0, 0, 1]])
    seq = TumSequence(convert_frames(src, tmp_path / "tum"))
    np.testing.assert_allclose(seq.K.numpy()[[0, 1, 0], [0, 1, 2]], [570.3, 570.3, 320], rtol=1e-6)


def sun3d_folder(root: Path, n: int = 3, n_poses: int | None = None) -> tuple[list, list, list]:
    """A SUN3D-like sequence: depth stored with its bits rotated left by 3, timestamps in the file names (us),
    an older and a newer extrinsics file (the newer one is used)."""
    rng = np.random.default_rng(1)
    for d in ("image", "depth", "extrinsics"):
        (root / d).mkdir(parents=True)
    t_img, t_dep, depths, poses = [], [], [], [rigid(rng) for _ in range(n)]
    for i in range(n):
        t_img.append(33367 * i)
        t_dep.append(33367 * i + 5000)
        cv2.imwrite(
            str(root / "image" / f"{i + 1:07d}-{t_img[-1]:012d}.jpg"), rng.integers(0, 255, (H, W, 3), np.uint8)
        )
        depths.append(depth_mm(rng, 0))
        stored = (depths[-1] << 3) | (depths[-1] >> 13)  # SUN3D's encoding
        cv2.imwrite(str(root / "depth" / f"{i + 1:07d}-{t_dep[-1]:012d}.png"), stored)
    np.savetxt(root / "intrinsics.txt", [[570.342, 0, 320], [0, 570.342, 240], [0, 0, 1]])
    np.savetxt(root / "extrinsics" / "20130101000000.txt", np.zeros((3 * n, 4)))
    np.savetxt(root / "extrinsics" / "20130512130736.txt", np.concatenate([T[:3] for T in poses[:n_poses]]))
    return t_img, depths, poses


def test_sun3d_reads_back_as_the_source(tmp_path):
    t_img, depths, poses = sun3d_folder(tmp_path / "sun3d")
    seq = TumSequence(convert_sun3d(tmp_path / "sun3d", tmp_path / "tum"))
    assert len(seq) == 3 and seq.gt_valid.all()
    np.testing.assert_allclose(seq.timestamps, np.array(t_img) * 1e-6, atol=1e-6)
    np.testing.assert_allclose(seq.K.numpy()[[0, 1, 0, 1], [0, 1, 2, 2]], [570.342, 570.342, 320, 240], rtol=1e-6)
    for i in range(3):
        np.testing.assert_allclose(seq[i].depth[0].numpy(), depths[i] / 1000.0, rtol=1e-6)
        np.testing.assert_allclose(seq.groundtruth[i], poses[i], atol=1e-7)


def test_sun3d_pose_count_must_match_the_images(tmp_path):
    sun3d_folder(tmp_path / "sun3d", n_poses=2)
    with pytest.raises(DataError, match="2 poses for 3 images"):
        convert_sun3d(tmp_path / "sun3d", tmp_path / "tum")


def test_cli(frames_folder, tmp_path, capsys):
    src, _, _ = frames_folder
    main(["frames", str(src), str(tmp_path / "tum"), "--intrinsics", "585", "585", "320", "240"])
    assert capsys.readouterr().out.strip() == f"{tmp_path / 'tum'}: 4 frames in TUM layout"
    with pytest.raises(SystemExit) as e:
        main(["frames", str(tmp_path / "nothing"), str(tmp_path / "x"), "--intrinsics", "1", "1", "0", "0"])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("convert: error: ")
