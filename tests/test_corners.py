"""Harris / Shi-Tomasi cornerness against OpenCV and kornia on the same inputs."""

from __future__ import annotations

from pathlib import Path

import cv2
import kornia
import numpy as np
import pytest
import torch
from tolerances import F32_UNIT, F64_UNIT

from torchtrack.image.corners import CornerDetector, harris, sobel, structure_tensor

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEQUENCES = ["visp_rbt_sequence", "sun3d_fragment1", "7scenes_redkitchen", "visp_castle_simu"]
M = 4  # border pixels excluded from comparisons (border conventions differ)


def real_gray(seq: str, i: int = 0) -> np.ndarray:
    """(H, W) float32 gray in [0, 1] of frame i of a sequence in ../shared/data (skip when absent)."""
    folder = DATA / seq
    if not (folder / "rgb.txt").exists():
        pytest.skip(f"{folder} not available")
    names = [line.split()[1] for line in (folder / "rgb.txt").read_text().splitlines() if line and line[0] != "#"]
    bgr = cv2.imread(str(folder / names[i]))
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY).astype(np.float32) / 255.0


def textured(seed: int = 0, H: int = 120, W: int = 160) -> np.ndarray:
    """A well-posed synthetic image: smoothed random blocks (corners everywhere), float32 in [0, 1]."""
    rng = np.random.default_rng(seed)
    blocks = rng.random((H // 8, W // 8)).astype(np.float32)
    return cv2.GaussianBlur(cv2.resize(blocks, (W, H), interpolation=cv2.INTER_NEAREST), (0, 0), 1.0)


def t(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img)[None, None]


def local_maxima(R: np.ndarray, n: int, radius: int = 3) -> np.ndarray:
    """(n, 2) (row, col) of the n strongest 3x3... (2r+1)^2 local maxima of R (interior only)."""
    dil = cv2.dilate(R, np.ones((2 * radius + 1,) * 2, np.uint8))
    peak = (R == dil) & (R > 0)
    peak[:M] = peak[-M:] = False
    peak[:, :M] = peak[:, -M:] = False
    rc = np.argwhere(peak)
    order = np.argsort(-R[peak])[:n]
    return rc[order]


def maxima_agreement(ours: np.ndarray, ref: np.ndarray, n: int = 300, tol: float = 1.5) -> float:
    """Fraction of the reference's n strongest local maxima that have one of ours within tol pixels."""
    a, b = local_maxima(ours, n).astype(float), local_maxima(ref, n).astype(float)
    d = np.sqrt(((b[:, None] - a[None]) ** 2).sum(-1)).min(1)
    return float((d <= tol).mean())


def interior(x: np.ndarray) -> np.ndarray:
    return x[M:-M, M:-M]


# ---------------------------------------------------------------------------------------------- smoke/shape
def test_shapes_and_dtype():
    img = t(textured()).expand(2, 3, -1, -1)
    for method in ("harris", "shi_tomasi"):
        for window in ("binomial", "gaussian", "box"):
            R = harris(img, method=method, window=window)
            assert R.shape == img.shape and R.dtype == torch.float32
    dx, dy = sobel(img)
    assert dx.shape == dy.shape == img.shape


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(method="fast"), "method"), (dict(window="disk"), "window")],
)
def test_bad_options_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        harris(t(textured()), **kwargs)
    with pytest.raises(ValueError, match=match):
        CornerDetector(**kwargs)


def test_bad_shape_raises():
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        harris(torch.rand(10, 10))


# ---------------------------------------------------------------------------------------------- oracles
def test_gaussian_window_is_kornia_harris_response():
    img = t(textured(1))
    assert torch.allclose(
        harris(img, window="gaussian"), kornia.feature.harris_response(img, 0.04), atol=1e-9, rtol=1e-5
    )


def test_sobel_is_kornia_spatial_gradient():
    img = t(textured(2))
    g = kornia.filters.spatial_gradient(img, "sobel")
    dx, dy = sobel(img)
    assert torch.allclose(dx, g[:, :, 0], atol=1e-6) and torch.allclose(dy, g[:, :, 1], atol=1e-6)


@pytest.mark.parametrize("sigma", [0.5, 1.0, 1.25, 1.5])
def test_binomial_window_is_kornia_pascal_passes(sigma):
    """The default window (shifted adds, paired passes) is round(2 sigma^2) [1, 2, 1] / 4 passes of kornia's
    separable correlation with reflect border, on kornia's Sobel products."""
    img = t(textured(5)).double()
    g = kornia.filters.spatial_gradient(img, "sobel")
    dx, dy = g[:, :, 0], g[:, :, 1]
    ref = torch.stack([dx * dx, dx * dy, dy * dy], 1).flatten(1, 2)
    k = kornia.filters.kernels.get_pascal_kernel_1d(3, norm=True, dtype=ref.dtype)[None]
    for _ in range(max(1, round(2 * sigma * sigma))):
        ref = kornia.filters.filter2d_separable(ref, k, k, border_type="reflect")
    torch.testing.assert_close(structure_tensor(img, sigma=sigma).flatten(1, 2), ref, atol=F64_UNIT, rtol=0)


def test_box_window_is_cv2_corner_harris_synthetic():
    img = textured(3)
    ours = harris(t(img), window="box", block_size=3)[0, 0].numpy()
    ref = cv2.cornerHarris(img, blockSize=3, ksize=3, k=0.04)
    # cv2 scales Sobel by 1/(4 * blockSize) and sums the box: its structure tensor is 4x ours, R 16x.
    np.testing.assert_allclose(interior(16 * ours), interior(ref), rtol=1e-4, atol=1e-4 * np.abs(ref).max())


def test_shi_tomasi_box_is_cv2_min_eigen_val():
    img = textured(4)
    ours = harris(t(img), method="shi_tomasi", window="box", block_size=3)[0, 0].numpy()
    ref = cv2.cornerMinEigenVal(img, blockSize=3, ksize=3)
    np.testing.assert_allclose(interior(4 * ours), interior(ref), rtol=1e-4, atol=1e-4 * np.abs(ref).max())


def test_corner_and_edge_signs():
    img = np.zeros((41, 41), np.float32)
    img[20:, 20:] = 1.0  # one corner at (20, 20), edges along row 20 and column 20
    R = harris(t(img))[0, 0].numpy()
    peak = np.unravel_index(np.argmax(R), R.shape)
    assert abs(peak[0] - 19.5) <= 1 and abs(peak[1] - 19.5) <= 1
    assert R[20, 35] < 0 and R[35, 20] < 0  # edges: negative Harris response
    assert abs(R[35, 35]) < 1e-12 and abs(R[5, 5]) < 1e-12  # flat: zero


@pytest.mark.parametrize("seq", SEQUENCES)
def test_against_cv2_on_real_frames(seq):
    """Box window: the same response as cv2.cornerHarris (x16); default binomial window: close to it."""
    img = real_gray(seq, 3)
    ref = cv2.cornerHarris(img, blockSize=3, ksize=3, k=0.04)
    box = harris(t(img), window="box", block_size=3)[0, 0].numpy()
    assert np.corrcoef(interior(box).ravel(), interior(ref).ravel())[0, 1] > 0.99999
    assert maxima_agreement(box, ref) >= 0.99  # (equal responses may rank differently)
    ours = harris(t(img))[0, 0].numpy()  # the default: 5x5 binomial window (Gaussian, sigma 1)
    assert np.corrcoef(interior(ours).ravel(), interior(ref).ravel())[0, 1] > 0.95
    if seq != "visp_castle_simu":  # a rendered image: many equally strong corners, the top-300 order is arbitrary
        assert maxima_agreement(ours, ref) > 0.8


# ---------------------------------------------------------------------------------------------- batching
@pytest.mark.equivalence
def test_batched_equals_looped():
    imgs = torch.stack([t(textured(s))[0] for s in range(3)])
    for kw in (dict(), dict(method="shi_tomasi", window="box", block_size=5), dict(window="gaussian", sigma=1.5)):
        batched = harris(imgs, **kw)
        looped = torch.cat([harris(imgs[b : b + 1], **kw) for b in range(3)])
        assert torch.allclose(batched, looped, atol=1e-10)


@pytest.mark.equivalence
def test_channels_are_independent():
    """Two channels at once equal each alone within F32_UNIT of the map's scale (other shapes, other kernels)."""
    a, b = t(textured(5)), t(textured(6))
    both = harris(torch.cat([a, b], dim=1))
    for got, alone in ((both[:, :1], harris(a)), (both[:, 1:], harris(b))):
        torch.testing.assert_close(got, alone, atol=F32_UNIT * float(alone.abs().max()), rtol=0)


def test_module_equals_function():
    img = t(textured(7))
    assert torch.equal(CornerDetector(k=0.06, window="box")(img), harris(img, k=0.06, window="box"))
