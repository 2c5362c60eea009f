"""torchtrack: model-free 3D rigid tracking from RGB-D video (Gedik & Alatan, FUSION 2013)."""

__version__ = "0.1.0"

from torchtrack import config as _config  # noqa: E402, F401  (registers the config schemas with Hydra)
