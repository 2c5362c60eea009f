"""Image stage: Shape Index Map (eq. 8), Harris, spatio-textural selection (eq. 9), object model,
batched pyramidal Lucas-Kanade with template inverse matching (eq. 10) and the combined tracker.

Note: the function ``shape_index`` shadows its submodule's name here; import module members with
``from torchtrack.image.shape_index import ...``.
"""

from torchtrack.image.corners import CornerDetector, harris, sobel, structure_tensor
from torchtrack.image.flow import CombinedTracker, FlowFrame, TrackResult, combined_track, prepare_frame
from torchtrack.image.lk import LKResult, forward_backward, pyramidal_lk
from torchtrack.image.object_model import (
    PCM,
    ObjectRegion,
    depth_range,
    feature_spread,
    keep_largest_component,
    object_mask,
    point_cloud_model,
)
from torchtrack.image.pyramid import Pyramid, build_pyramid
from torchtrack.image.select import (
    CornernessMaps,
    Features,
    cornerness_maps,
    patch_shape,
    select_features,
)
from torchtrack.image.shape_index import SIM, ShapeIndex, ShapeIndexMap, compute_sim, shape_index, sim_image

__all__ = [
    "PCM", "SIM", "CombinedTracker", "CornerDetector", "CornernessMaps", "Features",
    "FlowFrame", "LKResult", "ObjectRegion", "Pyramid", "ShapeIndex", "ShapeIndexMap", "TrackResult",
    "build_pyramid", "combined_track", "compute_sim", "cornerness_maps", "depth_range", "feature_spread",
    "forward_backward", "harris", "keep_largest_component", "object_mask", "patch_shape", "point_cloud_model",
    "prepare_frame", "pyramidal_lk", "select_features", "shape_index", "sim_image", "sobel", "structure_tensor",
]  # fmt: skip
