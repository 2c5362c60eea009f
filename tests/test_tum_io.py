"""PNG decoding (torchtrack.data.tum_io.imread): the imagecodecs path gives OpenCV's pixels exactly (the oracle:
``cv2.imread(..., IMREAD_UNCHANGED)``), for every PNG kind it takes and those it hands to OpenCV."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from torchtrack.data import tum_io
from torchtrack.data.tum_io import load_depth, load_rgb

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _images(tmp: Path) -> dict[str, Path]:
    rng = np.random.default_rng(0)
    out = {}
    for name, img in {
        "gray8": rng.integers(0, 256, (17, 23), dtype=np.uint8),
        "gray16": rng.integers(0, 65536, (17, 23), dtype=np.uint16),
        "bgr8": rng.integers(0, 256, (17, 23, 3), dtype=np.uint8),
        "bgr16": rng.integers(0, 65536, (17, 23, 3), dtype=np.uint16),
        "bgra8": rng.integers(0, 256, (17, 23, 4), dtype=np.uint8),
    }.items():
        out[name] = tmp / f"{name}.png"
        cv2.imwrite(str(out[name]), img)
    pal = Image.fromarray(rng.integers(0, 256, (17, 23, 3), dtype=np.uint8)).convert("P", palette=Image.ADAPTIVE)
    out["palette"] = tmp / "palette.png"
    pal.save(out["palette"])
    out["gray_alpha"] = tmp / "gray_alpha.png"
    Image.fromarray(rng.integers(0, 256, (17, 23, 2), dtype=np.uint8), mode="LA").save(out["gray_alpha"])
    return out


@pytest.mark.skipif(tum_io.imagecodecs is None, reason="imagecodecs not installed")
def test_png_decoding_gives_opencvs_pixels(tmp_path):
    for name, path in _images(tmp_path).items():
        img, rgb_order = tum_io.imread(path)
        ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert rgb_order == (name not in ("palette", "gray_alpha")), name  # those two go to OpenCV
        if rgb_order and img.ndim == 3:
            img = np.concatenate([img[..., 2::-1], img[..., 3:]], -1)  # RGB(A) -> OpenCV's BGR(A)
        assert img.dtype == ref.dtype and np.array_equal(img, ref), name
        if name in ("gray8", "gray16", "bgr8", "bgr16", "bgra8"):
            assert torch.equal(load_rgb(path), load_rgb(path, decoder="opencv")), name
    assert torch.equal(
        load_depth(tmp_path / "gray16.png", 1000.0), load_depth(tmp_path / "gray16.png", 1000.0, "opencv")
    )
    assert tum_io.imread(tmp_path / "missing.png")[0] is None


@pytest.mark.data
@pytest.mark.skipif(
    not (DATA / "sun3d_fragment1").is_dir() or tum_io.imagecodecs is None,
    reason="needs ../shared/data/sun3d_fragment1 and the imagecodecs package",
)
def test_real_frames_decode_to_opencvs_pixels():
    for kind in ("rgb", "depth"):
        for path in sorted((DATA / "sun3d_fragment1" / kind).glob("*.png"))[:2]:
            img, _ = tum_io.imread(path)
            ref = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(img[..., ::-1] if img.ndim == 3 else img, ref), path
