"""Lockstep batching of B sequences: active mask, repeated last frames, batched == per-sequence, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from tolerances import F32_UNIT

from torchtrack.data import (
    DataError,
    FrameBatch,
    FrameCursor,
    SequenceBatch,
    TumSequence,
    iterate_batched,
    write_tum_trajectory,
)
from torchtrack.data.batching import frame_gray
from torchtrack.geometry import make_T, so3_exp


def write_sequence(root: Path, n: int, *, H: int = 6, W: int = 8, seed: int = 0, t0: float = 0.0) -> Path:
    """Small TUM folder of n random frames with ground truth and intrinsics.txt (fx = 100 + seed)."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) / 30.0
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for kind in ("rgb", "depth"):
        lines = []
        for ti in t:
            name = f"{kind}/{ti:.6f}.png"
            shape, lo, hi, dtype = ((H, W, 3), 0, 256, np.uint8) if kind == "rgb" else ((H, W), 1, 9000, np.uint16)
            assert cv2.imwrite(str(root / name), rng.integers(lo, hi, shape, dtype=dtype))
            lines.append(f"{ti:.6f} {name}")
        (root / f"{kind}.txt").write_text("\n".join(lines) + "\n")
    R = so3_exp(torch.tensor(rng.normal(size=(n, 3))))
    write_tum_trajectory(root / "groundtruth.txt", t, make_T(R, torch.tensor(rng.normal(size=(n, 3)))))
    (root / "intrinsics.txt").write_text(f"{100 + seed} {100 + seed} 4 3 5000\n")
    return root


@pytest.fixture
def three_sequences(tmp_path) -> list[TumSequence]:
    return [TumSequence(write_sequence(tmp_path / f"s{n}", n, seed=n, t0=n)) for n in (2, 4, 3)]


@pytest.mark.parametrize("prefetch", [True, False])
def test_lockstep_equals_per_sequence_frames(three_sequences, prefetch):
    seqs = three_sequences
    batches = list(iterate_batched(seqs, prefetch=prefetch))
    assert len(batches) == 4 and all(isinstance(b, FrameBatch) for b in batches)
    assert [b.active.tolist() for b in batches] == [[True] * 3, [True] * 3, [False, True, True], [False, True, False]]
    for t, b in enumerate(batches):
        assert b.rgb.shape == (3, 3, 6, 8) and b.depth.shape == (3, 1, 6, 8) and b.K.shape == (3, 3, 3)
        assert b.rgb.dtype == b.depth.dtype == b.K.dtype == b.T_color_depth.dtype == torch.float32
        assert b.timestamp.dtype == b.T_world_color_gt.dtype == torch.float64 and b.index.dtype == torch.int64
        for k, s in enumerate(seqs):
            i = min(t, len(s) - 1)  # ended sequences repeat their last frame
            f = s[i]
            assert b.index[k] == i and b.timestamp[k] == f.timestamp and bool(b.gt_valid[k]) == f.gt_valid
            assert torch.equal(b.rgb[k], f.rgb) and torch.equal(b.depth[k], f.depth)
            assert torch.equal(b.T_world_color_gt[k], f.T_world_color_gt)
            assert torch.equal(b.K[k], s.K) and torch.equal(b.K_depth[k], s.K_depth)
            assert torch.equal(b.T_color_depth[k], s.T_color_depth)
    assert batches[0].K[:, 0, 0].tolist() == [102.0, 104.0, 103.0]


@pytest.mark.parametrize("prefetch", [True, False])
def test_loader_luminance_equals_frame_gray(three_sequences, prefetch):
    """The luminance the loader threads compute is FrameBatch.gray bit for bit (ended sequences included); a batch that
    did not come from the loader, or a sliced one, falls back to computing it."""
    for b in iterate_batched(three_sequences, prefetch=prefetch):
        got = frame_gray(b)
        assert frame_gray(b) is got and torch.equal(got, b.gray) and got.shape == (3, 1, 6, 8)  # the loader's copy
    sliced = FrameBatch(**{k: v[1:2] for k, v in vars(b).items()})
    assert frame_gray(sliced) is not frame_gray(sliced) and torch.equal(frame_gray(sliced), b.gray[1:2])  # computed
    single = list(iterate_batched(three_sequences[1:2], prefetch=prefetch))
    assert all(torch.equal(frame_gray(x), x.gray) and frame_gray(x).shape == (1, 1, 6, 8) for x in single)


def test_gray_is_opencv_rgb2gray(three_sequences):
    """FrameBatch.gray (kornia's rgb_to_grayscale) is OpenCV's float RGB2GRAY (BT.601) on the same pixels."""
    b = next(iter(iterate_batched(three_sequences)))
    want = np.stack([cv2.cvtColor(np.ascontiguousarray(x.permute(1, 2, 0).numpy()), cv2.COLOR_RGB2GRAY) for x in b.rgb])
    np.testing.assert_allclose(b.gray[:, 0].numpy(), want, atol=F32_UNIT, rtol=0)


def test_ended_sequence_is_not_reloaded(three_sequences, monkeypatch):
    calls, original = [], TumSequence.__getitem__
    monkeypatch.setattr(TumSequence, "__getitem__", lambda self, i: calls.append((self.name, i)) or original(self, i))
    for prefetch in (True, False):
        calls.clear()
        list(iterate_batched(three_sequences, prefetch=prefetch))
        assert sorted(calls) == sorted((s.name, i) for s in three_sequences for i in range(len(s)))


def test_sequence_batch_helper(three_sequences):
    sb = SequenceBatch(three_sequences, prefetch=False)
    assert sb.names == ["s2", "s4", "s3"] and sb.lengths == [2, 4, 3] and len(sb) == 4
    assert [int(b.active.sum()) for b in sb] == [3, 3, 2, 1]


def test_mismatched_image_sizes_raise(tmp_path):
    a = TumSequence(write_sequence(tmp_path / "a", 2))
    b = TumSequence(write_sequence(tmp_path / "b", 2, H=5))
    for prefetch in (True, False):
        with pytest.raises(DataError, match=r"share the image size.*a: \(6, 8\), b: \(5, 8\)"):
            next(iterate_batched([a, b], prefetch=prefetch))


def test_load_error_surfaces_at_its_step(three_sequences):
    bad = three_sequences[1].rgb_paths[2]
    bad.write_bytes(b"corrupt")
    it = iterate_batched(three_sequences, prefetch=True)  # no cursors: strict, the first bad frame raises
    assert [int(next(it).index.max()) for _ in range(2)] == [0, 1]
    with pytest.raises(DataError, match=f"^{bad}.*corrupt colour image"):
        next(it)


def test_early_stop_and_bad_input(three_sequences):
    it = iterate_batched(three_sequences, prefetch=True)
    next(it)
    it.close()  # must not hang on the pending prefetch
    with pytest.raises(ValueError, match="at least one sequence"):
        next(iterate_batched([]))


def _break_frames(seq: TumSequence, kinds: dict[int, str]) -> None:
    """Make frame i of ``seq`` bad in the way ``kinds[i]`` says."""
    H, W = seq[0].rgb.shape[1:]
    for i, kind in kinds.items():
        if kind == "corrupt_rgb":
            seq.rgb_paths[i].write_bytes(b"\x89PNG\r\n\x1a\n truncated")
        elif kind == "unreadable_depth":
            seq.depth_paths[i].write_bytes(b"")
        elif kind == "8bit_depth":
            cv2.imwrite(str(seq.depth_paths[i]), np.full((H, W), 9, np.uint8))
        elif kind == "zero_depth":
            cv2.imwrite(str(seq.depth_paths[i]), np.zeros((H, W), np.uint16))
        elif kind == "little_depth":
            d = np.zeros((H, W), np.uint16)
            d[0, 0] = 1000
            cv2.imwrite(str(seq.depth_paths[i]), d)
        elif kind == "rgb_size":
            cv2.imwrite(str(seq.rgb_paths[i]), np.zeros((H + 1, W, 3), np.uint8))


@pytest.mark.parametrize("prefetch", [True, False])
def test_bad_frames_are_dropped_with_one_warning_each(tmp_path, prefetch, caplog):
    seq = TumSequence(write_sequence(tmp_path / "s", 9), min_depth_fraction=0.05, max_bad_fraction=0.7)
    kinds = {
        1: "corrupt_rgb",
        2: "unreadable_depth",
        4: "8bit_depth",
        5: "zero_depth",
        6: "little_depth",
        8: "rgb_size",
    }
    good = [seq[i] for i in range(9) if i not in kinds]
    _break_frames(seq, kinds)
    cursor = FrameCursor(seq)
    batches = list(iterate_batched([seq], prefetch=prefetch, cursors=[cursor]))
    assert [int(b.index[0]) for b in batches] == [0, 3, 7] and all(bool(b.active[0]) for b in batches)
    for b, f in zip(batches, good, strict=True):
        assert torch.equal(b.rgb[0], f.rgb) and torch.equal(b.depth[0], f.depth) and b.timestamp[0] == f.timestamp
    assert [d.index for d in cursor.dropped] == sorted(kinds)
    assert [d.timestamp for d in cursor.dropped] == [float(seq.timestamps[i]) for i in sorted(kinds)]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert len(warned) == len(kinds)
    reasons = ["corrupt colour", "corrupt depth", "16-bit, got 8-bit", "no valid pixel", "of the pixels have depth",
               "colour image size"]  # fmt: skip
    paths = [seq.rgb_paths[1], seq.depth_paths[2], seq.depth_paths[4], seq.depth_paths[5], seq.depth_paths[6],
             seq.rgb_paths[8]]  # fmt: skip
    for m, reason, path in zip(warned, reasons, paths, strict=True):
        assert m.startswith("s: frame ") and f"dropped: {path}: " in m and reason in m and "\n" not in m


def test_too_many_bad_frames_fail_the_sequence_and_isolate_keeps_the_others(tmp_path):
    seqs = [TumSequence(write_sequence(tmp_path / f"s{k}", 6, seed=k), max_bad_fraction=0.25) for k in range(2)]
    _break_frames(seqs[0], {1: "zero_depth", 3: "zero_depth"})  # 2 > 0.25 * 6
    with pytest.raises(DataError, match=r"^s0: 2 bad frames, more than max_bad_fraction=0.25 of its 6; the last: "):
        list(iterate_batched(seqs, prefetch=False, cursors=[FrameCursor(s) for s in seqs]))
    with pytest.raises(DataError, match=f"^{seqs[0].depth_paths[1]}: depth image has no valid pixel"):
        list(iterate_batched(seqs, prefetch=False))  # no cursors: strict
    cursors = [FrameCursor(s, isolate=True) for s in seqs]
    batches = list(iterate_batched(seqs, cursors=cursors))
    assert [b.active.tolist() for b in batches] == [[True, True], [True, True]] + [[False, True]] * 4
    assert "more than max_bad_fraction" in cursors[0].failure and cursors[1].failure is None
    assert [int(b.index[1]) for b in batches] == list(range(6)) and int(batches[-1].index[0]) == 2


def test_sequence_failing_before_its_first_frame_is_inactive(tmp_path):
    seqs = [TumSequence(write_sequence(tmp_path / f"s{k}", 3, seed=k), on_bad_frame="error") for k in range(2)]
    _break_frames(seqs[1], {0: "corrupt_rgb"})
    cursors = [FrameCursor(s, isolate=True) for s in seqs]
    batches = list(iterate_batched(seqs, cursors=cursors))
    assert [b.active.tolist() for b in batches] == [[True, False]] * 3
    assert batches[0].index.tolist() == [0, -1] and not batches[0].rgb[1].any() and not batches[0].depth[1].any()
    assert cursors[1].failure.startswith(f"{seqs[1].rgb_paths[0]}: ") and cursors[1].dropped == []
