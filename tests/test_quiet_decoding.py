"""A corrupt image is reported once, by us: OpenCV's own decoder log ("[ERROR...] readHeader ...") is silenced when
torchtrack.data.tum_io is imported, and our warning names the file. Checked at the file-descriptor level (OpenCV
writes to fd 2 from C++, which pytest's capsys cannot see), in a subprocess."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.slow  # subprocesses decoding corrupt files

# A PNG signature followed by garbage: libpng's header check fails, and OpenCV logs it unless silenced.
CORRUPT_PNG = b"\x89PNG\r\n\x1a\n" + b"not a PNG chunk at all" * 4


def tiny_sequence(root: Path, frames: int = 5, corrupt: int = 2) -> Path:
    """A TUM-layout folder of ``frames`` 32x24 frames whose colour image ``corrupt`` is a corrupt PNG."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rng = np.random.default_rng(0)
    rows = []
    for i in range(frames):
        name = f"{i / 30:.6f}.png"
        cv2.imwrite(str(root / "rgb" / name), rng.integers(0, 255, (24, 32, 3), dtype=np.uint8))
        cv2.imwrite(str(root / "depth" / name), np.full((24, 32), 5000, np.uint16))  # 1 m at scale 5000
        rows.append(f"{i / 30:.6f} {{}}/{name}")
    (root / "rgb" / f"{corrupt / 30:.6f}.png").write_bytes(CORRUPT_PNG)
    (root / "rgb.txt").write_text("\n".join(r.format("rgb") for r in rows) + "\n")
    (root / "depth.txt").write_text("\n".join(r.format("depth") for r in rows) + "\n")
    (root / "intrinsics.txt").write_text("30 30 16 12 5000\n")
    return root / "rgb" / f"{corrupt / 30:.6f}.png"


def test_corrupt_png_gives_our_warning_and_no_opencv_log(tmp_path):
    bad = tiny_sequence(tmp_path / "seq")
    code = textwrap.dedent(f"""
        import logging
        logging.basicConfig(level=logging.WARNING)
        from torchtrack.data import TumSequence
        from torchtrack.data.batching import FrameCursor
        cursor = FrameCursor(TumSequence({str(tmp_path / "seq")!r}))
        while cursor.read() is not None:
            pass
        print(len(cursor.dropped))
    """)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["1"]  # the corrupt frame is dropped, the others are read
    assert "[ERROR" not in done.stderr and "readHeader" not in done.stderr, done.stderr
    warnings = [ln for ln in done.stderr.splitlines() if "dropped" in ln]
    assert len(warnings) == 1 and str(bad) in warnings[0], done.stderr


def test_opencv_would_log_without_the_setting(tmp_path):
    """The oracle for the test above: the same decode without torchtrack does print OpenCV's line (so the test
    above checks the silencing, not a decoder that happens to be quiet)."""
    path = tmp_path / "bad.png"
    path.write_bytes(CORRUPT_PNG)
    code = f"import cv2; assert cv2.imread({str(path)!r}, cv2.IMREAD_UNCHANGED) is None"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "[ERROR" in done.stderr
