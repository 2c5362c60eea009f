"""Property-based fuzzing of the text parsers (list files, intrinsics.txt, trajectories): any input either parses into
well-formed values or raises DataError with a one-line message naming the file; well-formed input round-trips."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchtrack.data import DataError, read_list_file, read_tum_trajectory, write_tum_trajectory
from torchtrack.data.tum_io import read_intrinsics_file
from torchtrack.geometry import make_T, so3_exp

FUZZ = settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)
names = st.text(st.characters(min_codepoint=33, max_codepoint=126, blacklist_characters="#,"), min_size=1, max_size=12)
# Arbitrary text, biased towards what the parsers look for: numbers, separators, comments, non-finite words.
tokens = st.one_of(
    st.text(max_size=8),
    finite.map(repr),
    st.sampled_from(["nan", "inf", "-inf", "#", ",", " ", "\n", "\t", "1e999", "x"]),
)
texts = st.lists(tokens, max_size=40).map("".join)


SCRATCH = tempfile.TemporaryDirectory(prefix="torchtrack-fuzz-")  # one file, rewritten per example, removed at exit


def write(text: str | bytes) -> Path:
    path = Path(SCRATCH.name) / "file.txt"
    path.write_bytes(text if isinstance(text, bytes) else text.encode("utf-8", "surrogatepass"))
    return path


def one_line_error_naming(path: Path, e: DataError) -> bool:
    return str(e).startswith(str(path)) and "\n" not in str(e)


@FUZZ
@given(st.one_of(texts, st.binary(max_size=200)))
def test_any_list_file_parses_or_fails_cleanly(text):
    path = write(text)
    try:
        t, files = read_list_file(path)
    except DataError as e:
        assert one_line_error_naming(path, e)
        return
    assert len(t) == len(files) >= 1 and np.isfinite(t).all() and (np.diff(t) > 0).all()
    assert all(f and not any(c.isspace() for c in f) for f in files)


@FUZZ
@given(st.lists(st.tuples(finite, names), min_size=1, max_size=30), st.randoms(use_true_random=False))
def test_list_file_rows_come_back_in_time_order_first_of_each_timestamp(rows, rnd):
    lines = [f"{t!r} {n}" for t, n in rows]
    for _ in range(rnd.randint(0, 3)):
        lines.insert(rnd.randint(0, len(lines)), rnd.choice(["# comment", "", "   "]))
    t, files = read_list_file(write("\n".join(lines) + "\n"))
    first: dict[float, str] = {}
    for ts, n in rows:
        first.setdefault(ts + 0.0, n)  # -0.0 == 0.0
    assert t.tolist() == sorted(first) and files == [first[k] for k in sorted(first)]


@FUZZ
@given(texts)
def test_any_intrinsics_file_parses_or_fails_cleanly(text):
    path = write(text)
    try:
        (fx, fy, cx, cy), scale = read_intrinsics_file(path)
    except DataError as e:
        assert one_line_error_naming(path, e)
        return
    assert fx > 0 and fy > 0 and math.isfinite(cx) and math.isfinite(cy) and (scale is None or scale > 0)


@FUZZ
@given(st.tuples(*[st.floats(0.1, 1e4)] * 2, finite, finite), st.one_of(st.none(), st.floats(1e-3, 1e6)))
def test_intrinsics_round_trip(k, scale):
    text = " ".join(repr(v) for v in k) + ("" if scale is None else f" {scale!r}")
    assert read_intrinsics_file(write(f"# fx fy cx cy depth_scale\n{text}\n")) == (k, scale)


@FUZZ
@given(texts)
def test_any_trajectory_parses_or_fails_cleanly(text):
    path = write(text)
    try:
        t, T = read_tum_trajectory(path)
    except DataError as e:
        assert one_line_error_naming(path, e)
        return
    R = T[:, :3, :3]
    assert np.isfinite(T).all() and (np.diff(t) > 0).all()
    assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-6) and np.allclose(np.linalg.det(R), 1.0)


@FUZZ
@given(
    st.lists(
        st.tuples(st.integers(0, 10**11), *[st.floats(-10, 10)] * 6), min_size=1, max_size=20, unique_by=lambda r: r[0]
    )
)
def test_trajectory_round_trip(rows):
    rows = [(us / 1e6, *r) for us, *r in sorted(rows)]  # TUM's microsecond timestamps
    v = torch.tensor(rows, dtype=torch.float64)
    T = make_T(so3_exp(v[:, 4:7]), v[:, 1:4]).numpy()
    path = write("")
    write_tum_trajectory(path, v[:, 0].numpy(), T)
    t, T_back = read_tum_trajectory(path)
    assert np.allclose(t, v[:, 0].numpy(), rtol=0, atol=1e-9) and np.allclose(T_back, T, atol=1e-7)
