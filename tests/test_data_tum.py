"""TUM-layout reader: association, ground truth, intrinsics, image decoding, errors, trajectory IO, real data."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchtrack.data import (
    CAMERAS,
    DataError,
    TumSequence,
    associate,
    get_camera,
    nearest_within,
    read_tum_trajectory,
    write_tum_trajectory,
)
from torchtrack.data.batching import FrameCursor
from torchtrack.geometry import T_inv, backproject, make_T, project, sample_depth, so3_exp, transform_points

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


# ----------------------------------------------------------------------------------------------- helpers


def write_sequence(root: Path, t_rgb, t_depth=None, *, H=6, W=8, seed=0, gt=None, intrinsics="100 100 4 3 1000"):
    """Small TUM folder: random 8-bit colour PNGs, 16-bit depth PNGs, list files; gt = (timestamps, (F,4,4))."""
    rng = np.random.default_rng(seed)
    t_depth = t_rgb if t_depth is None else t_depth
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for kind, ts in (("rgb", t_rgb), ("depth", t_depth)):
        lines = [f"# {kind} images", "", "# timestamp filename"]
        for t in ts:
            name = f"{kind}/{t:.6f}.png"
            if kind == "rgb":
                img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
            else:
                img = rng.integers(500, 5000, (H, W), dtype=np.uint16)
            assert cv2.imwrite(str(root / name), img)
            lines.append(f"{t:.6f} {name}")
        (root / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    if gt is not None:
        write_tum_trajectory(root / "groundtruth.txt", *gt)
    if intrinsics is not None:
        (root / "intrinsics.txt").write_text(f"# fx fy cx cy depth_scale\n{intrinsics}\n")
    return root


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    axis_angle = torch.randn(n, 3, generator=g, dtype=torch.float64) * 1.5  # includes angles near pi
    return make_T(so3_exp(axis_angle), torch.randn(n, 3, generator=g, dtype=torch.float64)).numpy()


def tum_associate_reference(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """TUM associate.py, literally: all pairs below max_dt, sorted by difference, greedy one-to-one."""
    cands = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) < max_dt)
    used_a, used_b, out = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i), used_b.add(j), out.append((i, j))
    return sorted(out)


# ----------------------------------------------------------------------------------------------- association


def test_associate_equals_tum_reference_on_jittered_times():
    rng = np.random.default_rng(1)
    for trial in range(5):
        a = np.sort(rng.uniform(0, 3, 60))
        b = rng.permutation(a + rng.normal(0, 0.012, len(a)))[: 50 + trial]  # jittered, shuffled, some dropped
        ia, ib = associate(a, b, 0.02)
        assert list(zip(ia.tolist(), ib.tolist(), strict=True)) == tum_associate_reference(a, b, 0.02)


def test_associate_one_to_one_and_max_dt():
    a = np.array([0.0, 0.1, 0.2])
    b = np.array([0.001, 0.004, 0.15, 0.2199])  # two candidates for a[0]; b[2] is 0.05 from a[1], a[2]
    ia, ib = associate(a, b, 0.02)
    assert ia.tolist() == [0, 2] and ib.tolist() == [0, 3]  # a[1] has nothing within 0.02 s
    assert len(associate(a, b + 10.0, 0.02)[0]) == 0


def test_nearest_within():
    idx, valid = nearest_within(np.array([0.0, 0.5, 1.004, 2.0]), np.array([1.0, 0.0, 1.01, 0.49]), 0.02)
    assert idx.tolist() == [1, 3, 0, 0] and valid.tolist() == [True, True, True, False]


def test_sequence_associates_jittered_list_files(tmp_path):
    t = np.arange(10) / 30.0
    rng = np.random.default_rng(2)
    t_depth = np.concatenate([t + rng.uniform(-0.008, 0.008, 10), [5.0]])  # one depth frame without colour
    seq = TumSequence(write_sequence(tmp_path / "s", t, t_depth), max_dt=0.01)
    assert len(seq) == 10 and seq.name == "s"
    np.testing.assert_allclose(seq.timestamps, np.round(t, 6))
    np.testing.assert_allclose(seq.depth_timestamps, np.round(t_depth[:10], 6))
    sub = TumSequence(tmp_path / "s", max_dt=0.01, stride=3, max_frames=3)
    assert sub.rgb_paths == seq.rgb_paths[::3][:3] and sub.depth_paths == seq.depth_paths[::3][:3]


def test_nothing_matches_raises(tmp_path):
    write_sequence(tmp_path / "s", np.arange(3) / 30.0, np.arange(3) / 30.0 + 100.0)
    with pytest.raises(DataError, match="rgb.txt.*depth.txt.*no colour-depth pair"):
        TumSequence(tmp_path / "s")


# ----------------------------------------------------------------------------------------------- ground truth


def test_groundtruth_nearest_within_max_dt(tmp_path):
    t = np.arange(6) / 30.0
    t_gt = np.arange(0, 0.1, 0.01)  # 100 Hz up to 0.09 s: frame 3 (0.1 s) is 0.01 s away, frames 4, 5 have none
    T_gt = random_poses(len(t_gt))
    seq = TumSequence(write_sequence(tmp_path / "s", t, gt=(t_gt, T_gt)))
    assert seq.gt_valid.tolist() == [True, True, True, True, False, False]
    for i in range(4):
        j = int(np.argmin(np.abs(t_gt - seq.timestamps[i])))
        np.testing.assert_allclose(seq.groundtruth[i], T_gt[j], atol=1e-8)
        frame = seq[i]
        assert frame.gt_valid and frame.T_world_color_gt.dtype == torch.float64
        np.testing.assert_allclose(frame.T_world_color_gt.numpy(), T_gt[j], atol=1e-8)
    np.testing.assert_array_equal(seq.groundtruth[4:], np.tile(np.eye(4), (2, 1, 1)))
    assert not seq[4].gt_valid


def test_no_groundtruth_file(tmp_path):
    seq = TumSequence(write_sequence(tmp_path / "s", np.arange(3) / 30.0))
    assert not seq.has_groundtruth and seq.groundtruth.shape == (3, 4, 4) and seq.gt_valid.dtype == bool


# ----------------------------------------------------------------------------------------------- intrinsics


def test_camera_presets_published_values():
    assert (CAMERAS["fr1"].fx, CAMERAS["fr1"].fy, CAMERAS["fr1"].cx, CAMERAS["fr1"].cy) == (517.3, 516.5, 318.6, 255.3)
    assert (CAMERAS["fr2"].fx, CAMERAS["fr2"].fy, CAMERAS["fr2"].cx, CAMERAS["fr2"].cy) == (520.9, 521.0, 325.1, 249.7)
    assert (CAMERAS["fr3"].fx, CAMERAS["fr3"].fy, CAMERAS["fr3"].cx, CAMERAS["fr3"].cy) == (535.4, 539.2, 320.1, 247.6)
    k = CAMERAS["kinect_default"]
    assert (k.fx, k.fy, k.cx, k.cy, k.depth_scale) == (525.0, 525.0, 319.5, 239.5, 5000.0)
    assert get_camera("Freiburg3") is CAMERAS["fr3"] and all(c.depth_scale == 5000.0 for c in CAMERAS.values())
    with pytest.raises(DataError, match="unknown camera preset 'fr9'"):
        get_camera("fr9")


def test_intrinsics_priority(tmp_path, caplog):
    t = np.arange(2) / 30.0
    root = write_sequence(tmp_path / "s", t, intrinsics="100 101 4 3 1000")
    seq = TumSequence(root, camera="fr1")
    assert seq.K.tolist() == [[100, 0, 4], [0, 101, 3], [0, 0, 1]] and seq.depth_scale == 1000.0
    assert seq.K.dtype == torch.float32 and torch.equal(seq.K_depth, seq.K) and not caplog.records
    seq = TumSequence(root, camera="fr1", intrinsics=(1, 2, 1, 1), depth_scale=7.0)  # explicit values win, logged
    assert seq.K.tolist() == [[1, 0, 1], [0, 2, 1], [0, 0, 1]] and seq.depth_scale == 7.0
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == 2 and all(m.startswith(f"{root / 'intrinsics.txt'}: explicit") for m in warned)
    assert "[1.0, 2.0, 1.0, 1.0] override the file's [100.0, 101.0, 4.0, 3.0]" in warned[0]
    assert "depth_scale 7 overrides the file's 1000" in warned[1]
    caplog.clear()
    TumSequence(root, intrinsics=(100, 101, 4, 3), depth_scale=1000)  # agreeing values: nothing to say
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    (root / "intrinsics.txt").unlink()
    seq = TumSequence(root, camera="fr1")
    assert torch.allclose(seq.K, CAMERAS["fr1"].K) and seq.depth_scale == 5000.0
    seq = TumSequence(root, camera="fr1", intrinsics=(1, 1, 1, 1))
    assert seq.K[0, 0] == 1 and seq.depth_scale == 5000.0
    seq = TumSequence(root, camera="fr1", depth_scale=1000.0)
    assert seq.depth_scale == 1000.0
    seq = TumSequence(root, intrinsics=(200, 201, 4, 3))
    assert seq.K[0, 0] == 200 and seq.K[1, 1] == 201 and seq.depth_scale == 5000.0
    with pytest.raises(DataError, match="no intrinsics.txt"):
        TumSequence(root)


def test_extrinsic_and_depth_intrinsics(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0)
    T = random_poses(1)[0]
    seq = TumSequence(root, T_color_depth=T, intrinsics_depth=(90, 91, 4, 3))
    assert seq.T_color_depth.shape == (4, 4) and torch.allclose(seq.T_color_depth, torch.tensor(T).float())
    assert seq.K_depth[0, 0] == 90 and seq.K[0, 0] == 100
    with pytest.raises(DataError, match="T_color_depth"):
        TumSequence(root, T_color_depth=np.eye(3))


# ----------------------------------------------------------------------------------------------- image decoding


def test_frame_values_equal_written_images(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0, H=5, W=7)
    seq = TumSequence(root)
    f = seq[1]
    bgr = cv2.imread(str(seq.rgb_paths[1]), cv2.IMREAD_COLOR)
    d = cv2.imread(str(seq.depth_paths[1]), cv2.IMREAD_UNCHANGED)
    assert f.rgb.shape == (3, 5, 7) and f.rgb.dtype == torch.float32 and f.depth.shape == (1, 5, 7)
    np.testing.assert_allclose(f.rgb.numpy(), bgr[..., ::-1].transpose(2, 0, 1) / 255.0, atol=1e-7)
    np.testing.assert_allclose(f.depth[0].numpy(), d / 1000.0, rtol=1e-7)
    assert f.index == 1 and f.timestamp == pytest.approx(1 / 30.0, abs=1e-6)
    assert seq[-1].index == 1
    with pytest.raises(IndexError):
        seq[2]


def test_grayscale_and_jpeg_colour(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0, H=16, W=16)
    seq = TumSequence(root)
    gray = np.tile(np.arange(16, dtype=np.uint8)[None] * 15, (16, 1))
    cv2.imwrite(str(seq.rgb_paths[0]), gray)
    f = seq[0]
    assert torch.equal(f.rgb[0], f.rgb[1]) and torch.equal(f.rgb[0], f.rgb[2])
    np.testing.assert_allclose(f.rgb[0].numpy(), gray / 255.0, atol=1e-7)
    jpg = root / "rgb" / "x.jpg"
    colour = np.zeros((16, 16, 3), np.uint8)
    colour[..., 2] = 200  # red in BGR
    cv2.imwrite(str(jpg), colour, [cv2.IMWRITE_JPEG_QUALITY, 100])
    seq.rgb_paths[1] = jpg
    rgb = seq[1].rgb
    assert rgb[0].mean() > 0.7 and rgb[1].mean() < 0.05 and rgb[2].mean() < 0.05


# ----------------------------------------------------------------------------------------------- errors


def _raises_naming(path: Path, match: str):
    return pytest.raises(DataError, match=f"^{str(path)}.*{match}")


def test_error_wrong_root(tmp_path):
    with _raises_naming(tmp_path / "nope", "folder not found"):
        TumSequence(tmp_path / "nope")


def test_error_missing_or_empty_list_files(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0)
    (root / "depth.txt").write_text("# only a comment\n\n")
    with _raises_naming(root / "depth.txt", "no entries"):
        TumSequence(root)
    (root / "rgb.txt").unlink()
    with _raises_naming(root / "rgb.txt", "file not found"):
        TumSequence(root)


def test_error_malformed_list_and_groundtruth(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0)
    (root / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0\n")
    with _raises_naming(root / "groundtruth.txt", ":1: expected 8 fields"):
        TumSequence(root)
    (root / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0 x\n")
    with _raises_naming(root / "groundtruth.txt", "non-numeric"):
        TumSequence(root)
    (root / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0 0\n")
    with _raises_naming(root / "groundtruth.txt", "zero quaternion"):
        TumSequence(root)


def test_error_missing_image(tmp_path):
    """One missing file of 3 frames is more than max_bad_fraction (0.25): an error at load, naming the file."""
    root = write_sequence(tmp_path / "s", np.arange(3) / 30.0)
    missing = root / "depth" / f"{1 / 30:.6f}.png"
    missing.unlink()
    with _raises_naming(missing, "listed in depth.txt not found"):
        TumSequence(root)


def test_missing_image_is_a_dropped_frame(tmp_path, caplog):
    """A listed frame whose file is missing loads (one warning naming it) and is dropped when reached."""
    root = write_sequence(tmp_path / "s", np.arange(8) / 30.0)
    missing = root / "rgb" / f"{2 / 30:.6f}.png"
    missing.unlink()
    with caplog.at_level(logging.WARNING):
        seq = TumSequence(root)
    assert len(seq) == 8 and any(str(missing) in r.getMessage() and "1 of 8" in r.getMessage() for r in caplog.records)
    with _raises_naming(missing, "colour image not found"):
        seq[2]
    cursor = FrameCursor(seq)
    read = [f.index for f in iter(cursor.read, None)]
    assert read == [0, 1, 3, 4, 5, 6, 7] and [d.index for d in cursor.dropped] == [2]
    with _raises_naming(missing, "listed in rgb.txt not found"):
        TumSequence(root, on_bad_frame="error")


def test_error_corrupt_images(tmp_path):
    seq = TumSequence(write_sequence(tmp_path / "s", np.arange(3) / 30.0))
    seq.rgb_paths[0].write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    with _raises_naming(seq.rgb_paths[0], "unreadable or corrupt colour image"):
        seq[0]
    seq.depth_paths[1].write_bytes(b"garbage")
    with _raises_naming(seq.depth_paths[1], "unreadable or corrupt depth image"):
        seq[1]


def test_error_depth_not_16_bit_or_empty(tmp_path):
    seq = TumSequence(write_sequence(tmp_path / "s", np.arange(3) / 30.0, H=4, W=4))
    cv2.imwrite(str(seq.depth_paths[0]), np.full((4, 4), 7, np.uint8))
    with _raises_naming(seq.depth_paths[0], "single-channel 16-bit, got 8-bit"):
        seq[0]
    cv2.imwrite(str(seq.depth_paths[1]), np.zeros((4, 4), np.uint16))
    with _raises_naming(seq.depth_paths[1], "no valid pixel"):
        seq[1]
    cv2.imwrite(str(seq.depth_paths[2]), np.ones((3, 4), np.uint16))
    with _raises_naming(seq.depth_paths[2], r"depth size \(3, 4\) differs from colour \(4, 4\)"):
        seq[2]  # frames 0 and 1 were bad: the sequence's size is not known yet


def test_size_change_blames_the_file_that_changed(tmp_path):
    seq = TumSequence(write_sequence(tmp_path / "s", np.arange(3) / 30.0, H=4, W=4))
    seq[0]
    cv2.imwrite(str(seq.rgb_paths[1]), np.ones((5, 4, 3), np.uint8))  # one colour frame changes size
    with _raises_naming(seq.rgb_paths[1], r"colour image size \(5, 4\) differs from the sequence's \(4, 4\)"):
        seq[1]
    fresh = TumSequence(seq.root)  # size not known yet: both files named
    cv2.imwrite(str(seq.rgb_paths[0]), np.ones((5, 4, 3), np.uint8))
    with pytest.raises(DataError, match=r"depth size \(4, 4\) differs from colour \(5, 4\)"):
        fresh[0]


def test_too_little_depth_is_an_error_at_load(tmp_path):
    seq = TumSequence(write_sequence(tmp_path / "s", np.arange(2) / 30.0, H=10, W=10), min_depth_fraction=0.05)
    d = np.zeros((10, 10), np.uint16)
    d[0, :4] = 1000  # 4 % of the pixels
    cv2.imwrite(str(seq.depth_paths[1]), d)
    seq[0]
    with _raises_naming(seq.depth_paths[1], r"only 4.00% of the pixels have depth \(min_depth_fraction=0.05\)"):
        seq[1]
    seq.min_depth_fraction = 0.04
    assert seq[1].depth.count_nonzero() == 4


# ----------------------------------------------------------------------------------------------- trajectory IO


def test_trajectory_round_trip(tmp_path):
    t = 1305031102.175304 + np.arange(20) / 30.0
    T = random_poses(20, seed=3)
    path = write_tum_trajectory(tmp_path / "out" / "traj.txt", t, T)
    t2, T2 = read_tum_trajectory(path)
    np.testing.assert_allclose(t2, t, atol=1e-6)
    np.testing.assert_allclose(T2, T, atol=1e-8)
    rows = np.loadtxt(path)
    assert rows.shape == (20, 8) and (rows[:, 7] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(rows[:, 4:], axis=1), 1.0, atol=1e-8)
    assert [p.name for p in path.parent.iterdir()] == ["traj.txt"]  # no temporary left behind
    write_tum_trajectory(path, t[:2], T[:2])  # replaces atomically
    assert read_tum_trajectory(path).T_world_cam.shape == (2, 4, 4)


def test_trajectory_reader_matches_evo_and_q_equals_minus_q(tmp_path):
    file_interface = pytest.importorskip("evo.tools.file_interface")
    T = random_poses(10, seed=4)
    path = write_tum_trajectory(tmp_path / "a.txt", np.arange(10) * 0.1, T)
    rows = np.loadtxt(path)
    rows[::2, 4:] *= -1  # q and -q are the same rotation
    np.savetxt(tmp_path / "b.txt", rows, fmt="%.9f")
    ours = read_tum_trajectory(tmp_path / "b.txt")
    evo = file_interface.read_tum_trajectory_file(str(tmp_path / "b.txt"))
    np.testing.assert_allclose(ours.T_world_cam, np.stack(evo.poses_se3), atol=1e-9)
    np.testing.assert_allclose(ours.timestamps, evo.timestamps)
    np.testing.assert_allclose(ours.T_world_cam, T, atol=1e-8)


def test_write_trajectory_bad_shape(tmp_path):
    with pytest.raises(ValueError, match="traj.txt.*T_world_cam"):
        write_tum_trajectory(tmp_path / "traj.txt", np.zeros(3), np.zeros((2, 4, 4)))


# ----------------------------------------------------------------------------------------------- real data


def depth_warp_residuals(seq: TumSequence, i: int, j: int, step: int = 4) -> dict[str, float]:
    """Median |z predicted - z measured| (m) of frame i's depth warped into frame j, for three relative motions.

    gt: T_j_i from ground truth; identity: no motion; inverted: poses read as world-to-camera (wrong convention);
    reversed: the inverse relative motion. Depth to depth only, so it holds for unregistered depth too.
    """
    a, b = seq[i], seq[j]
    d = a.depth[0, ::step, ::step].double()
    ys, xs = torch.nonzero(d > 0, as_tuple=True)
    K = seq.K_depth.double()
    p_i = backproject(K, torch.stack([xs, ys], -1).double() * step, d[ys, xs])
    T_wi, T_wj = a.T_world_color_gt, b.T_world_color_gt
    motions = {
        "gt": T_inv(T_wj) @ T_wi,
        "identity": torch.eye(4, dtype=torch.float64),
        "inverted": T_wj @ T_inv(T_wi),
        "reversed": T_inv(T_wi) @ T_wj,
    }
    out = {}
    for name, T_ji in motions.items():
        p_j = transform_points(T_ji, p_i)
        z = sample_depth(b.depth[None].double(), project(K, p_j)[None])[0]
        ok = (z > 0) & (p_j[:, 2] > 0)
        out[name] = (p_j[ok, 2] - z[ok]).abs().median().item()
    return out


# name, frames, depth_scale, gap k, bound on the GT median residual (m)
REAL = [
    ("visp_castle_simu", 40, 5000.0, 3, 0.001),
    ("visp_rbt_sequence", 99, 1000.0, 10, 0.02),
    ("sun3d_fragment1", 50, 1000.0, 10, 0.04),  # ~3.5 m: Kinect noise alone is ~3 cm, so a larger gap
    ("sun3d_fragment2", 50, 1000.0, 5, 0.03),
    ("7scenes_redkitchen", 1000, 1000.0, 5, 0.01),
]


@pytest.mark.data
@pytest.mark.skipif(not DATA.is_dir(), reason="../shared/data not present")
@pytest.mark.parametrize(("name", "frames", "scale", "k", "gt_bound"), REAL, ids=[r[0] for r in REAL])
def test_real_sequence_depth_warp_with_groundtruth(name, frames, scale, k, gt_bound):
    seq = TumSequence(DATA / name)
    assert len(seq) == frames and seq.gt_valid.all() and seq.depth_scale == scale and seq.name == name
    np.testing.assert_allclose(np.linalg.det(seq.groundtruth[:, :3, :3]), 1.0, atol=1e-6)
    starts = np.linspace(0, len(seq) - 1 - k, 3).astype(int)
    res = [depth_warp_residuals(seq, int(i), int(i) + k) for i in starts]
    med = {m: float(np.median([r[m] for r in res])) for m in res[0]}
    assert med["gt"] < gt_bound, med
    assert med["gt"] < 0.5 * min(med["identity"], med["inverted"], med["reversed"]), med


# ----------------------------------------------------------------------------------------------- validation at load


@pytest.mark.parametrize(
    "row, match",
    [
        ("0.0 nan 2 3 0 0 0 1", "non-finite value in '0.0 nan 2 3 0 0 0 1'"),
        ("0.0 1 2 inf 0 0 0 1", "non-finite value"),
        ("0.0 1 2 3 0 0 nan 1", "non-finite value"),
        ("0.0 1 2 3 0 0 0.5 1", r"quaternion not of unit norm \(1.11803\)"),
        ("0.0 1 2 3 0 0 0 0", "zero quaternion"),
    ],
)
def test_groundtruth_bad_rows_named_by_file_and_line(tmp_path, row, match):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0)
    good = "0.5 1 2 3 0 0 0 1"
    (root / "groundtruth.txt").write_text(f"# header\n{good}\n{row}\n{good.replace('0.5', '0.9')}\n")
    with _raises_naming(root / "groundtruth.txt", f":3: {match}"):
        TumSequence(root)
    (root / "groundtruth.txt").write_text(f"{row}\n")  # a bad first row: an error too, not an all-NaN trajectory
    with _raises_naming(root / "groundtruth.txt", f":1: {match}"):
        TumSequence(root)


def test_rounded_unit_quaternions_are_accepted(tmp_path):
    root = write_sequence(tmp_path / "s", np.arange(2) / 30.0)
    (root / "groundtruth.txt").write_text("0.0 1 2 3 0.1826 0.3651 0.5477 0.7303\n")  # 4 decimals: norm 0.99998
    assert TumSequence(root).gt_valid.tolist() == [True, False]


def test_unsorted_and_duplicate_rows_are_ordered_with_warnings(tmp_path, caplog):
    t = np.arange(5) / 30.0
    poses = random_poses(5)
    root = write_sequence(tmp_path / "s", t, gt=(t, poses))
    reference = TumSequence(root)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        lines = [ln for ln in (root / name).read_text().splitlines() if ln and not ln.startswith("#")]
        shuffled = [lines[3], lines[0], lines[4], lines[1], lines[1], lines[2], lines[0]]  # unsorted, repeats
        (root / name).write_text("\n".join(shuffled) + "\n")
    caplog.clear()
    seq = TumSequence(root)
    assert len(seq) == 5 and np.array_equal(seq.timestamps, reference.timestamps)
    assert seq.rgb_paths == reference.rgb_paths and seq.depth_paths == reference.depth_paths
    assert np.array_equal(seq.groundtruth, reference.groundtruth) and seq.gt_valid.all()
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        assert any(m.startswith(f"{root / name}:2: not sorted by time") for m in warned)
        assert any(m.startswith(f"{root / name}:") and "2 repeated timestamp(s)" in m for m in warned)
