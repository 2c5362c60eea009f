"""Visualisation: trajectory and error plots (PNG)."""

from torchtrack.viz.plots import plot_errors, plot_per_axis_errors, plot_trajectory

__all__ = ["plot_errors", "plot_per_axis_errors", "plot_trajectory"]
