"""Feature overlays like the paper's Figs. 6 and 7: tracked features and the model reprojected."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.geometry import project, transform_points
from torchtrack.io import write_atomic

INTENSITY_BGR = (60, 220, 60)  # green: the intensity tracker won
SIM_BGR = (230, 60, 230)  # magenta: the SIM tracker won
NEW_BGR = (0, 200, 255)  # orange: freshly selected
MODEL_BGR = (255, 160, 0)  # blue-ish: model points reprojected with the estimated pose


def draw_frame(
    rgb: Tensor,
    pixels: Tensor,
    valid: Tensor,
    winner: Tensor,
    K: Tensor,
    T_color_obj: Tensor,
    points_obj: Tensor,
    label: str,
) -> np.ndarray:
    """One sequence's frame: rgb (3,H,W), pixels (N,2), valid (N,), winner (N,), K (3,3), T (4,4), points (N,3) -> BGR uint8."""
    img = (rgb.permute(1, 2, 0).clamp(0, 1).numpy()[..., ::-1] * 255).astype(np.uint8).copy()
    proj = project(K, transform_points(T_color_obj.float(), points_obj.float()))
    for p, ok in zip(proj.tolist(), valid.tolist(), strict=True):
        if ok and np.isfinite(p).all():
            cv2.circle(img, (round(p[0]), round(p[1])), 5, MODEL_BGR, 1, cv2.LINE_AA)
    colours = {0: INTENSITY_BGR, 1: SIM_BGR}
    for p, ok, w in zip(pixels.tolist(), valid.tolist(), winner.tolist(), strict=True):
        if ok:
            cv2.circle(img, (round(p[0]), round(p[1])), 2, colours.get(int(w), NEW_BGR), -1, cv2.LINE_AA)
    cv2.putText(img, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA)
    cv2.putText(img, label, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def legend(width: int) -> np.ndarray:
    bar = np.full((28, width, 3), 255, np.uint8)
    items = [
        ("intensity LK", INTENSITY_BGR),
        ("SIM LK", SIM_BGR),
        ("new model", NEW_BGR),
        ("model reprojected", MODEL_BGR),
    ]
    x = 8
    for text, colour in items:
        cv2.circle(bar, (x + 5, 14), 5, colour, -1)
        cv2.putText(bar, text, (x + 14, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        x += 30 + 8 * len(text)
    return bar


def save_strip(path: Path, tiles: list[np.ndarray], columns: int = 3, scale: float = 0.5) -> None:
    """Tile BGR images into a grid (with a legend) and write a PNG atomically."""
    if not tiles:
        return
    small = [cv2.resize(t, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) for t in tiles]
    h, w = small[0].shape[:2]
    rows = -(-len(small) // columns)
    grid = np.full((rows * h, columns * w, 3), 255, np.uint8)
    for i, t in enumerate(small):
        r, c = divmod(i, columns)
        grid[r * h : (r + 1) * h, c * w : (c + 1) * w] = t
    grid = np.vstack([grid, legend(grid.shape[1])])
    write_atomic(path, lambda tmp: _imwrite(tmp, grid))


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cv2.imwrite could not write {path}")


def snapshot_indices(length: int, count: int = 6) -> set[int]:
    """Evenly spaced frame indices (first and last included) for an image strip."""
    return {int(round(i)) for i in torch.linspace(0, max(length - 1, 0), min(count, length)).tolist()}
