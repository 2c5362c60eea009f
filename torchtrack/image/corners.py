"""Harris and Shi-Tomasi cornerness, batched (paper §III-B: the cornerness of intensity and of the SIM).

The structure tensor ``M = sum_W w (Ix^2, IxIy; IxIy, Iy^2)`` is built from Sobel gradients
(normalised by 1/8 and replicate-padded, as ``kornia.filters.spatial_gradient``) and one of three
windows ``W``:

    "binomial"  (default) [1, 2, 1]/4 filters applied round(2 sigma^2) times per axis: a Gaussian of
                std ``sigma`` (sigma = 1: the 5x5 binomial), computed with shifted adds (fast on CPU)
    "gaussian"  ``kornia.filters.gaussian_blur2d`` with a (2 ceil(3 sigma) + 1)^2 kernel: for sigma = 1
                this is exactly ``kornia.feature.harris_response``
    "box"       ``kornia.filters.box_blur`` over ``block_size`` x ``block_size`` (reflect border): the window
                of ``cv2.cornerHarris``, whose response is 16x this one for ``ksize=3`` and a float32 image

Harris: ``R = det M - k tr(M)^2`` (positive at corners, negative on edges). Shi-Tomasi: the smaller
eigenvalue of ``M``. Both scale with the fourth (Harris) or second (Shi-Tomasi) power of the
image contrast; :func:`torchtrack.image.select.select_features` normalises them per frame.

References:
    C. Harris, M. Stephens, "A combined corner and edge detector", Alvey Vision Conference 1988.
    J. Shi, C. Tomasi, "Good features to track", CVPR 1994.
"""

from __future__ import annotations

import math

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

_WINDOWS = ("binomial", "gaussian", "box")
_METHODS = ("harris", "shi_tomasi")


# Hand-written, not kornia.filters.spatial_gradient (tests/test_corners.py holds them equal): kornia's convolution is
# ~5x slower on the CPU for a 640x480 frame (6 ms against 32), and the selection computes these gradients on every new
# model frame.
def sobel(image: Tensor) -> tuple[Tensor, Tensor]:
    """Sobel gradients (Ix, Iy) of (B, C, H, W), each (B, C, H, W), scaled by 1/8, replicate border."""
    p = F.pad(image, (1, 1, 1, 1), mode="replicate")
    hx = p[..., :, 2:] - p[..., :, :-2]  # B,C,H+2,W
    dx = hx[..., 1:-1, :] * 0.25
    dx.add_(hx[..., :-2, :], alpha=0.125).add_(hx[..., 2:, :], alpha=0.125)
    hy = p[..., 2:, :] - p[..., :-2, :]  # B,C,H,W+2
    dy = hy[..., 1:-1] * 0.25
    dy.add_(hy[..., :-2], alpha=0.125).add_(hy[..., 2:], alpha=0.125)
    return dx, dy


# Hand-written, not kornia.filters.filter2d_separable with Pascal kernels (tests/test_corners.py holds them equal):
# kornia's depthwise convolution is ~3x slower on the CPU for the selection's products of a 640x480 frame (17 ms
# against 56, one thread).
def _binomial_window(x: Tensor, passes: int) -> Tensor:
    """``passes`` [1, 2, 1] / 4 filters per axis with reflect border, pairs of them as one [1, 4, 6, 4, 1] / 16
    filter (the same result: reflection commutes with symmetric filters). ``x`` is a temporary of the caller
    and is overwritten: the passes ping-pong between it and one more buffer (few large allocations; the
    stage is memory-bound)."""
    y = torch.empty_like(x)
    for dim in (-1, -2):
        n = x.shape[dim]
        for taps in [5] * (passes // 2) + [3] * (passes % 2):
            if taps == 5:
                torch.mul(x, 0.375, out=y)
                y.narrow(dim, 2, n - 2).add_(x.narrow(dim, 0, n - 2), alpha=0.0625)
                y.narrow(dim, 0, n - 2).add_(x.narrow(dim, 2, n - 2), alpha=0.0625)
                # reflect: x[-1] = x[1], x[-2] = x[2], x[n] = x[n-2], x[n+1] = x[n-3]
                y.narrow(dim, 0, 1).add_(x.narrow(dim, 2, 1), alpha=0.0625)
                y.narrow(dim, 1, 1).add_(x.narrow(dim, 1, 1), alpha=0.0625)
                y.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 3, 1), alpha=0.0625)
                y.narrow(dim, n - 2, 1).add_(x.narrow(dim, n - 2, 1), alpha=0.0625)
            else:
                torch.mul(x, 0.5, out=y)
            y.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1), alpha=0.25)
            y.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1), alpha=0.25)
            y.narrow(dim, 0, 1).add_(x.narrow(dim, 1, 1), alpha=0.25)
            y.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 2, 1), alpha=0.25)
            x, y = y, x
    return x


def structure_tensor(image: Tensor, *, window: str = "binomial", sigma: float = 1.0, block_size: int = 3) -> Tensor:
    """Windowed structure tensor entries (B, 3, C, H, W): Ix^2, IxIy, Iy^2 (see the module docstring)."""
    if window not in _WINDOWS:
        raise ValueError(f"structure_tensor: window must be one of {_WINDOWS}, got {window!r}")
    dx, dy = sobel(image)
    B, C, H, W = image.shape
    prods = torch.empty(B, 3, C, H, W, dtype=dx.dtype, device=dx.device)
    torch.mul(dx, dx, out=prods[:, 0])
    torch.mul(dx, dy, out=prods[:, 1])
    torch.mul(dy, dy, out=prods[:, 2])
    prods = prods.view(B, 3 * C, H, W)
    if window == "binomial":
        prods = _binomial_window(prods, max(1, round(2.0 * sigma * sigma)))
    elif window == "gaussian":
        ks = 2 * math.ceil(3.0 * sigma) + 1
        prods = kornia.filters.gaussian_blur2d(prods, (ks, ks), (sigma, sigma))
    else:
        prods = kornia.filters.box_blur(prods, (block_size, block_size), border_type="reflect")
    return prods.reshape(B, 3, C, H, W)


# Not kornia.feature.harris_response: that is the "gaussian" window here (equal to 2e-7), ~2.4x slower than the
# default binomial window by shifted adds, which is the selection's (changing it would move the features).
def harris(
    image: Tensor,
    *,
    k: float = 0.04,
    method: str = "harris",
    window: str = "binomial",
    sigma: float = 1.0,
    block_size: int = 3,
) -> Tensor:
    """Cornerness of every pixel of every channel.

    Args:
        image: (B, C, H, W) float (intensity or SIM image in [0, 1]).
        k: Harris free parameter.
        method: "harris" (``det M - k tr(M)^2``) or "shi_tomasi" (smaller eigenvalue of M).
        window: "binomial", "gaussian" or "box" (module docstring).
        sigma: std (pixels) of the binomial / Gaussian window.
        block_size: side of the box window.

    Returns:
        (B, C, H, W) cornerness, same dtype as ``image``.
    """
    if image.dim() != 4:
        raise ValueError(f"harris: image must be (B, C, H, W), got {tuple(image.shape)}")
    if method not in _METHODS:
        raise ValueError(f"harris: method must be one of {_METHODS}, got {method!r}")
    m = structure_tensor(image, window=window, sigma=sigma, block_size=block_size)
    a, b, c = m.unbind(1)
    if method == "harris":
        tr = a + c
        return (a * c).addcmul_(b, b, value=-1.0).addcmul_(tr, tr, value=-k)
    half_diff = 0.5 * (a - c)
    return 0.5 * (a + c) - (half_diff * half_diff).addcmul_(b, b).sqrt_()


class CornerDetector:
    """Holds the cornerness parameters; ``__call__(image)`` delegates to :func:`harris`."""

    def __init__(
        self, k: float = 0.04, method: str = "harris", window: str = "binomial", sigma: float = 1.0, block_size: int = 3
    ) -> None:
        if method not in _METHODS or window not in _WINDOWS:
            raise ValueError(f"CornerDetector: method in {_METHODS}, window in {_WINDOWS}; got {method!r}, {window!r}")
        self.kwargs = dict(k=k, method=method, window=window, sigma=sigma, block_size=block_size)

    def __call__(self, image: Tensor) -> Tensor:
        return harris(image, **self.kwargs)
