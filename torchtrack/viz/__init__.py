"""Visualisation: trajectory and error plots (PNG), feature overlays.

The plots need matplotlib, which costs ~0.4 s to import; it is loaded on first use of a plot function, so a run
with ``plots=false`` (and the first frame of any run) never waits for it.
"""

from importlib import import_module

__all__ = ["plot_errors", "plot_per_axis_errors", "plot_trajectory"]


def __getattr__(name: str):
    if name in __all__:
        return getattr(import_module("torchtrack.viz.plots"), name)
    raise AttributeError(f"module 'torchtrack.viz' has no attribute {name!r}")
