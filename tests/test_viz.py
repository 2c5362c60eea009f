"""Plots: files are valid PNGs of the promised size, written atomically, and draw exactly the given data."""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
import pytest
import torch

import torchtrack.viz.plots as plots
from torchtrack.geometry import make_T, so3_exp, transform_points
from torchtrack.metrics import ate, per_axis_errors
from torchtrack.viz import plot_errors, plot_per_axis_errors, plot_trajectory

F64 = torch.float64


def _trajectory(F: int = 60, plane: str = "xz") -> np.ndarray:
    """A loop in the given world plane with a small wobble on the third axis, (F, 4, 4) T_world_cam."""
    s = torch.linspace(0, 2 * math.pi, F, dtype=F64)
    p = torch.zeros(F, 3, dtype=F64)
    a, b = ("xyz".index(plane[0]), "xyz".index(plane[1]))
    p[:, a], p[:, b] = 2 * torch.cos(s), torch.sin(2 * s)
    p[:, 3 - a - b] = 0.05 * torch.sin(3 * s)
    omega = 0.3 * torch.stack([torch.sin(s), torch.cos(s), 0.5 * s], -1)
    return make_T(so3_exp(omega), p).numpy()


def _estimate(T_gt: np.ndarray, seed: int = 1) -> np.ndarray:
    g = torch.Generator().manual_seed(seed)
    T = torch.as_tensor(T_gt).clone()
    T[:, :3, 3] += 0.03 * torch.randn(T.shape[0], 3, generator=g, dtype=F64)
    offset = make_T(so3_exp(torch.tensor([0.0, 0.0, 0.4], dtype=F64)), torch.tensor([1.0, -0.5, 0.2], dtype=F64))
    return (offset @ T).numpy()


@pytest.fixture
def captured(monkeypatch):
    """Keep the figure handed to the saver (and still save it) so tests can read the drawn lines."""
    figs = []
    save = plots.save_atomic

    def keep(fig, path, dpi):
        figs.append(fig)
        return save(fig, path, dpi)

    monkeypatch.setattr(plots, "save_atomic", keep)
    return figs


def _png_shape(path) -> tuple[int, ...]:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, f"{path} is not a readable PNG"
    return img.shape


def test_plot_trajectory_with_gt_draws_aligned_estimate_and_ate(tmp_path, captured):
    T_gt = _trajectory()
    T_est = _estimate(T_gt)
    valid = np.arange(60) % 5 != 0
    T_gt_holes = T_gt.copy()
    T_gt_holes[~valid] = np.nan  # rows without ground truth must not be read
    out = plot_trajectory(
        tmp_path / "sub" / "traj.png", T_est, T_gt_holes, gt_valid=valid, timestamps=np.arange(60) / 30
    )
    assert out == tmp_path / "sub" / "traj.png"
    assert _png_shape(out)[:2] == (800, 1200)  # figsize (12, 8) at 100 dpi
    assert [p.name for p in out.parent.iterdir()] == ["traj.png"]  # no temporary left behind
    top, *_, err_ax = captured[0].axes
    res = ate(T_est[valid], T_gt[valid])
    p_aligned = transform_points(res.T_align, torch.as_tensor(T_est[:, :3, 3])).numpy()
    gt_line, est_line = top.lines[0], top.lines[1]
    assert "xz" in top.get_title()
    np.testing.assert_allclose(gt_line.get_xydata(), T_gt[valid][:, [0, 2], 3])
    np.testing.assert_allclose(est_line.get_xydata(), p_aligned[:, [0, 2]])
    np.testing.assert_allclose(err_ax.lines[0].get_ydata(), res.errors.numpy())
    np.testing.assert_allclose(err_ax.lines[0].get_xdata(), np.arange(60)[valid] / 30)
    assert f"{res.rmse_m:.4f}" in captured[0].get_suptitle()


def test_plot_trajectory_without_gt_and_plane_choice(tmp_path, captured):
    T = _trajectory(plane="xy")
    out = plot_trajectory(tmp_path / "traj.png", T, title="raw")
    assert _png_shape(out)[:2] == (600, 1200)
    top = captured[0].axes[0]
    assert "xy" in top.get_title() and len(captured[0].axes) == 4  # top view + x, y, z; no ATE panel
    np.testing.assert_allclose(top.lines[0].get_xydata(), T[:, :2, 3])  # drawn unaligned


def test_plot_trajectory_all_gt_invalid_falls_back_to_estimate_only(tmp_path, captured):
    T = _trajectory()
    plot_trajectory(tmp_path / "t.png", T, np.full_like(T, np.nan), gt_valid=np.zeros(60, bool))
    assert len(captured[0].axes) == 4


def test_atomic_save_replaces_and_keeps_old_file_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "e.png"
    plot_errors(path, {"a": np.ones(10)})
    first = path.read_bytes()
    plot_errors(path, {"a": np.arange(10.0), "b": np.full(10, np.nan)})
    assert path.read_bytes() != first
    second = path.read_bytes()

    def boom(self, *args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(plots.Figure, "savefig", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        plot_errors(path, {"a": np.zeros(10)})
    assert path.read_bytes() == second and [p.name for p in tmp_path.iterdir()] == ["e.png"]


def test_plot_errors_and_per_axis_draw_the_data(tmp_path, captured):
    y = {"proposed": torch.linspace(0, 1, 20), "ICP": np.linspace(1, 3, 20)}
    plot_errors(tmp_path / "e.png", y, ylabel="reprojection error [px]")
    ax = captured[0].axes[0]
    np.testing.assert_allclose(ax.lines[1].get_ydata(), y["ICP"])
    assert "mean 2" in ax.get_legend().get_texts()[1].get_text()
    T_gt = _trajectory()
    errs = per_axis_errors(_estimate(T_gt), T_gt)
    out = plot_per_axis_errors(tmp_path / "a.png", errs)
    assert _png_shape(out)[:2] == (600, 1000)
    rot_ax, trans_ax = captured[1].axes
    np.testing.assert_allclose(rot_ax.lines[2].get_ydata(), errs.rot_deg[:, 2].numpy())
    np.testing.assert_allclose(trans_ax.lines[0].get_ydata(), 1000 * errs.trans_m[:, 0].numpy())


def test_plot_errors_legend_means_skip_gaps_and_an_empty_series_says_so(tmp_path, captured):
    a = np.array([1.0, np.nan, 3.0, np.inf, 8.0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's "Mean of empty slice" on an all-NaN series
        plot_errors(tmp_path / "e.png", {"a": a, "b": np.full(5, np.nan)})
    labels = [t.get_text() for t in captured[0].axes[0].get_legend().get_texts()]
    assert labels == [f"a (mean {np.mean([1.0, 3.0, 8.0]):.3g})", "b (no value)"]


def test_bad_input_raises(tmp_path):
    T = _trajectory()
    with pytest.raises(ValueError, match="T_est"):
        plot_trajectory(tmp_path / "x.png", T[:, :3])
    with pytest.raises(ValueError, match="T_gt"):
        plot_trajectory(tmp_path / "x.png", T, T[:10])
    with pytest.raises(ValueError, match="timestamps"):
        plot_trajectory(tmp_path / "x.png", T, timestamps=np.arange(5.0))
    with pytest.raises(ValueError, match="gt_valid"):
        plot_trajectory(tmp_path / "x.png", T, T, gt_valid=np.ones(3, bool))
    with pytest.raises(ValueError, match="one length"):
        plot_errors(tmp_path / "x.png", {"a": np.ones(3), "b": np.ones(4)})
    with pytest.raises(ValueError, match="no series"):
        plot_errors(tmp_path / "x.png", {})
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------------------------- overlay (features.png)


def test_draw_frame_puts_markers_where_the_features_and_the_reprojected_model_are():
    """A uniform 640x480 image, identity pose: the model point (X, Y, Z) projects to K (X/Z, Y/Z); the panel is
    the image halved (x' = (x + 0.5) / 2 - 0.5), under a white caption band."""
    from torchtrack.viz import overlay

    H, W, f, c = 480, 640, 500.0, (319.5, 239.5)
    K = torch.tensor([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1]])
    rgb = torch.tensor([0.2, 0.4, 0.6])[:, None, None].expand(3, H, W)
    pixels = torch.tensor([[100.5, 60.5], [500.5, 400.5], [300.5, 200.5]])
    points = torch.cat([(pixels - torch.tensor(c)) / f * 2.0, torch.full((3, 1), 2.0)], -1)  # project to pixels
    valid, winner = torch.tensor([True, True, False]), torch.tensor([0, 1, 0])
    tile = overlay.draw_frame(rgb, pixels, valid, winner, K, torch.eye(4), points, "frame 7")
    band, h, w = overlay.BAND, H // 2, W // 2
    assert tile.shape == (2 * (band + h), w, 3)
    tracks, model = tile[band : band + h], tile[2 * band + h :]
    for p, colour in ((pixels[0], overlay.INTENSITY_BGR), (pixels[1], overlay.SIM_BGR)):
        x, y = (round(v) for v in ((p + 0.5) / 2 - 0.5).tolist())
        assert tuple(tracks[y, x]) == colour
        assert tuple(model[y, x + overlay.RING]) == overlay.MODEL_BGR  # on the ring around the reprojection
    dimmed = tuple(np.round(overlay.DIM * np.array([153, 102, 51]) + (1 - overlay.DIM) * 128).astype(int))
    x, y = (round(v) for v in ((pixels[2] + 0.5) / 2 - 0.5).tolist())
    assert tuple(tracks[y, x]) == dimmed and tuple(model[y, x]) == dimmed  # an invalid feature is not drawn
    assert tuple(tracks[-1, -1]) == dimmed and tuple(model[0, 0]) == dimmed  # no text over the image
    caption = tile[:band]
    assert (caption == caption[..., :1]).all() and (caption < 128).any()  # black text on white, above the image


def test_save_strip_lays_out_snapshots_with_title_and_legend(tmp_path):
    from torchtrack.viz import overlay

    tiles = [np.full((100, 80, 3), v, np.uint8) for v in (10, 20, 30, 40, 50)]
    overlay.save_strip(tmp_path / "f.png", tiles, columns=4, title="seq")
    img = cv2.imread(str(tmp_path / "f.png"))
    assert img.shape == (overlay.BAND + 2 * 100 + 6 + 2 * overlay.BAND, 4 * 80 + 3 * 6, 3)
    assert (img[overlay.BAND + 106 : overlay.BAND + 206, :80] == 50).all()  # fifth snapshot: second row, first column
    overlay.save_strip(tmp_path / "none.png", [])
    assert not (tmp_path / "none.png").exists()


def test_draw_frame_trail_is_drawn_in_the_winner_colour_and_other_sizes_are_left_out():
    from torchtrack.viz import overlay

    H, W, f = 480, 640, 500.0
    K = torch.tensor([[f, 0, 319.5], [0, f, 239.5], [0, 0, 1]])
    rgb = torch.full((3, H, W), 0.5)
    pixels = torch.tensor([[300.5, 200.5]])
    points = torch.cat([(pixels - torch.tensor([319.5, 239.5])) / f, torch.ones(1, 1)], -1)
    trail = [torch.zeros(4, 2), pixels - torch.tensor([60.0, 0.0]), pixels]  # (4, 2): another N, left out
    tile = overlay.draw_frame(rgb, pixels, torch.tensor([True]), torch.tensor([1]), K, torch.eye(4), points, "f", trail)
    tracks = tile[overlay.BAND : overlay.BAND + H // 2]
    x, y = (round(v) for v in ((pixels[0] - torch.tensor([40.0, 0.0]) + 0.5) / 2 - 0.5).tolist())
    assert tuple(tracks[y, x]) == overlay.SIM_BGR  # on the track, 40 image px (20 panel px) behind the feature
    assert tuple(tracks[y + 6, x]) != overlay.SIM_BGR
