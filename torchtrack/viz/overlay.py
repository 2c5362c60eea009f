"""Feature overlays like the paper's Figs. 6 and 7: the tracks coloured by the tracker that won (intensity or SIM
LK, Fig. 6) and the model points reprojected with the estimated pose next to the tracked pixels (Fig. 7).

Each snapshot is a column of two panels, drawn at the size they are written (markers stay legible after the
image is shrunk) on a dimmed image, with their captions on white bands above them, never over the image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.geometry import project, transform_points
from torchtrack.io import write_atomic

INTENSITY_BGR = (40, 200, 40)  # green: the intensity tracker won
SIM_BGR = (220, 40, 220)  # magenta: the SIM tracker won
NEW_BGR = (0, 160, 255)  # orange: freshly selected (model frame), no tracker yet
MODEL_BGR = (255, 170, 0)  # light blue: model points reprojected with the estimated pose
LINK_BGR = (0, 240, 255)  # yellow: reprojected model point -> tracked pixel (the eq. (16) residual)
PANEL_W = 320  # a panel's width: 640 x 480 images are halved, small ones enlarged (at most x2)
BAND = 22  # caption band height, px
DIM = 0.55  # image contrast kept under the markers
FONT = cv2.FONT_HERSHEY_SIMPLEX
DOT, RING = 3, 4  # radii in panel pixels: a tracked feature (filled), a reprojected model point (ring)
TRAIL = 8  # frames of track drawn behind each feature (Fig. 6)


def draw_frame(
    rgb: Tensor,
    pixels: Tensor,
    valid: Tensor,
    winner: Tensor,
    K: Tensor,
    T_color_obj: Tensor,
    points_obj: Tensor,
    label: str,
    trail: list[Tensor] | None = None,
) -> np.ndarray:
    """One snapshot of one sequence as two stacked panels -> BGR uint8 (2 (BAND + h), w, 3), h, w = s (H, W) with
    s = :func:`panel_scale` (W).

    rgb (3, H, W) in [0, 1]; pixels (N, 2) tracked pixels; valid (N,); winner (N,) 0 intensity, 1 SIM, -1 new;
    K (3, 3) colour intrinsics; T_color_obj (4, 4) the estimated pose; points_obj (N, 3) model points;
    trail: the same features' pixels (N, 2) in the last frames, oldest first, the last = pixels (entries of another
    N, from padding changed by another sequence of the batch, are left out), or None. A picture is drawn on the
    host: the inputs come to the CPU whatever their device.
    """
    if pixels.shape[-1] != 2 or points_obj.shape[-1] != 3 or valid.shape != pixels.shape[:1]:
        raise ValueError(f"draw_frame: pixels (N, 2), points_obj (N, 3), valid (N,); got {tuple(pixels.shape)}, "
                         f"{tuple(points_obj.shape)}, {tuple(valid.shape)}")  # fmt: skip
    rgb, pixels, valid, winner, K, T_color_obj, points_obj = (
        x.cpu() for x in (rgb, pixels, valid, winner, K, T_color_obj, points_obj)
    )
    scale = panel_scale(rgb.shape[-1])
    base = _dimmed(rgb, scale)
    ok = valid.bool()
    win = winner.long()
    at = _to_panel(pixels.float(), scale)
    tracks = base.copy()
    trail = [t.cpu() for t in trail or [] if t.shape == pixels.shape]
    if len(trail) > 1:
        lines = _to_panel(torch.stack(trail).float(), scale).permute(1, 0, 2)[ok]  # N_ok,T,2
        colours = [_colour(int(w)) for w in win[ok].tolist()]
        for line, colour in zip(lines.round().int().numpy(), colours, strict=True):
            cv2.polylines(tracks, [line.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
    for p, w in zip(at[ok].tolist(), win[ok].tolist(), strict=True):
        _dot(tracks, p, _colour(w), DOT)
    n_int, n_sim = int((win[ok] == 0).sum()), int((win[ok] == 1).sum())
    n_new = int(ok.sum()) - n_int - n_sim
    head = f"{label}: {n_int} intensity, {n_sim} SIM" + (f", {n_new} new" if n_new else "")
    if n_int + n_sim == 0:
        head = f"{label}: {n_new} new model features"

    proj_full = project(K.float(), transform_points(T_color_obj.float(), points_obj.float()))  # N,2 colour image
    fine = ok & torch.isfinite(proj_full).all(-1)
    resid = (proj_full - pixels.float()).norm(dim=-1)[fine]
    model = base.copy()
    for q, p in zip(_to_panel(proj_full, scale)[fine].tolist(), at[fine].tolist(), strict=True):
        cv2.line(model, _pt(q), _pt(p), LINK_BGR, 1, cv2.LINE_AA)
        cv2.circle(model, _pt(q), RING, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.circle(model, _pt(q), RING, MODEL_BGR, 2, cv2.LINE_AA)
    mean = f"{float(resid.mean()):.2f} px" if len(resid) else "-"
    foot = f"model reprojected: {int(fine.sum())} points, mean {mean}"
    w = base.shape[1]
    return np.vstack([_band(head, w), tracks, _band(foot, w), model])


def legend(width: int) -> np.ndarray:
    """A white band naming the colours, (2 BAND, width, 3)."""
    bar = np.full((2 * BAND, width, 3), 255, np.uint8)
    items = [
        ("intensity LK won", INTENSITY_BGR),
        ("SIM LK won", SIM_BGR),
        ("new model feature", NEW_BGR),
        ("model point reprojected", MODEL_BGR),
        ("-> tracked pixel", LINK_BGR),
    ]
    x = 10
    for text, colour in items:
        if text.startswith("->"):
            cv2.line(bar, (x - 6, BAND), (x + 10, BAND), colour, 2, cv2.LINE_AA)
        else:
            _dot(bar, (x, BAND), colour, 6)
        cv2.putText(bar, text, (x + 14, BAND + 5), FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        x += 34 + cv2.getTextSize(text, FONT, 0.5, 1)[0][0]
    return bar


def save_strip(path: Path, tiles: list[np.ndarray], columns: int = 4, title: str = "") -> None:
    """Lay the snapshots (from :func:`draw_frame`, all one size) out in ``columns`` under ``title`` with a legend;
    write a PNG atomically. Nothing is written for no tiles."""
    if not tiles:
        return
    h, w = tiles[0].shape[:2]
    rows = -(-len(tiles) // columns)
    gap = 6
    grid = np.full((rows * (h + gap) - gap, min(columns, len(tiles)) * (w + gap) - gap, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        grid[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = t
    parts = [_band(title, grid.shape[1])] if title else []
    grid = np.vstack([*parts, grid, legend(grid.shape[1])])
    write_atomic(path, lambda tmp: _imwrite(tmp, grid))


def snapshot_indices(length: int, count: int = 4) -> set[int]:
    """Evenly spaced frame indices (first and last included) for an image strip."""
    return {int(round(i)) for i in torch.linspace(0, max(length - 1, 0), min(count, length), device="cpu").tolist()}


def panel_scale(width: int) -> float:
    """Panel size / image size: PANEL_W px wide, within [0.5, 2] (large images stay at half size)."""
    return min(max(PANEL_W / width, 0.5), 2.0)


def _dimmed(rgb: Tensor, scale: float) -> np.ndarray:
    """rgb (3, H, W) -> BGR uint8 (scale H, scale W, 3), contrast DIM around mid-grey so the markers stand out."""
    img = np.round(rgb.permute(1, 2, 0).clamp(0, 1).numpy()[..., ::-1] * 255).astype(np.uint8)
    small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA).astype(np.float32)
    return np.ascontiguousarray(np.round(DIM * small + (1 - DIM) * 128)).astype(np.uint8)


def _to_panel(pixels: Tensor, scale: float) -> Tensor:
    """Pixel centres (..., 2) in the image -> in the panel: x' = (x + 0.5) scale - 0.5."""
    return (pixels + 0.5) * scale - 0.5


def _colour(winner: int) -> tuple[int, int, int]:
    return {0: INTENSITY_BGR, 1: SIM_BGR}.get(winner, NEW_BGR)


def _pt(p) -> tuple[int, int]:
    return round(p[0]), round(p[1])


def _dot(img: np.ndarray, p, colour, radius: int) -> None:
    """A filled disc with a dark rim: visible on bright and dark pixels alike."""
    cv2.circle(img, _pt(p), radius + 1, (0, 0, 0), -1, cv2.LINE_AA)
    cv2.circle(img, _pt(p), radius, colour, -1, cv2.LINE_AA)


def _band(text: str, width: int) -> np.ndarray:
    """A white caption band (BAND, width, 3); the font shrinks until the text fits."""
    band = np.full((BAND, width, 3), 255, np.uint8)
    size = min(0.45, 0.45 * (width - 12) / max(cv2.getTextSize(text, FONT, 0.45, 1)[0][0], 1))
    cv2.putText(band, text, (6, BAND - 7), FONT, size, (0, 0, 0), 1, cv2.LINE_AA)
    return band


def _imwrite(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cv2.imwrite could not write {path}")
