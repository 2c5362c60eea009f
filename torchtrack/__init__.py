"""torchtrack: model-free 3D rigid tracking from RGB-D video (Gedik & Alatan, FUSION 2013).

Importing the package loads nothing else: the kernels (geometry, image, filter, estimators) are plain torch, and the
application layer registers its Hydra configs where it composes them (:mod:`torchtrack.config`, on import).
"""

__version__ = "0.1.0"
