"""Structured configs: one dataclass schema per configurable stage, registered in one ConfigStore.

Each YAML file under ``conf/<group>/`` starts from its schema (``defaults: [/schema/<group>@_here_: <name>]``) and
only changes values, so Hydra checks types when the config is composed (``data.depth_scale=abc`` fails there) and the
schema's ``__post_init__`` checks ranges when :func:`validate` turns a node into its dataclass.

Defaults. The schemas hold torchtrack's defaults (the improvements on); the classes and functions they configure take
the same values as literals in their signatures, so that the kernels need no Hydra (``tests/test_config.py`` and
``tests/test_defaults.py`` keep the two equal). The paper's values are one file, ``conf/experiment/paper.yaml``
(``+experiment=paper``). The data group's schemas are in :mod:`torchtrack.data.schema`. Derived knobs are resolved in
one place, :func:`torchtrack.factory.build_tracker`: the front end's pyramid levels are the LK tracker's
(``flow.levels``). The measurement variances belong to the weighting, not to the filter.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

from torchtrack.data.errors import DataError
from torchtrack.data.schema import SyntheticDataConfig, TumDataConfig

# The Hydra configs: the top-level conf/ of a checkout (also an editable install's); a built wheel carries that folder
# inside the package as torchtrack/conf (setup.py), which a checkout never has.
_PACKAGED_CONF = Path(__file__).resolve().parent / "conf"
CONF_DIR = _PACKAGED_CONF if _PACKAGED_CONF.is_dir() else Path(__file__).resolve().parents[1] / "conf"
EKF_BACKEND = "torchtrack.filter.backend.EKFBackend"
VIEW_SIZE = (480, 640)  # the map views' [H, W] (MappingConfig.view_size; a list there, as OmegaConf needs)
REGISTRATION_BACKEND = "torchtrack.estimators.backends.RegistrationBackend"


# --- data: torchtrack/data/schema.py; front end -----------------------------------------------------------------------


@dataclass
class RegionConfig:
    """:class:`torchtrack.image.object_model.ObjectRegion`: the model's region of interest."""

    _target_: str = "torchtrack.image.object_model.ObjectRegion"
    whole_frame: bool = False  # true: every pixel with depth (scene tracking)
    near: float | None = None  # m; null: from the depth histogram (nearest mode)
    far: float | None = None
    largest_component: bool = False
    erode_px: int = 0  # px: keep the model's features this far inside the region (LK windows off the silhouette)


@dataclass
class SelectConfig:
    """:func:`torchtrack.image.select.select_features` (eq. 9), bound to its keyword arguments."""

    _target_: str = "torchtrack.image.select.select_features"
    _partial_: bool = True
    lam: float = 0.5  # lambda of eq. (9); 1 = intensity only
    patch_size: int = 32  # pixels (32 -> 15 x 20 = 300 patches on 640 x 480)
    grid: list[int] | None = None  # [rows, cols] instead of patch_size
    spread: bool = True  # false = global top-N by cornerness, no patches (ablation EKF-1)
    max_features: int | None = None
    border: int = 12  # keep features this far from the image edge (LK window)
    nms_radius: int = 2  # non-maximum suppression radius when spread is false
    min_cornerness: float = 0.05
    require_sim: bool = False  # true: with lam < 1 only pixels with a defined (non-planar) shape index
    roi_fraction: float | None = 0.5  # improvement (null = paper): a region whose box covers less of the image (inside
    # the border) gets patches shrunk so that the box holds as many as this fraction of the image would
    min_patch: int = 8  # ... patches no smaller than this (px)


@dataclass
class FlowConfig:
    """:class:`torchtrack.image.flow.CombinedTracker`: LK on intensity and SIM with the TIM check (eq. 10)."""

    _target_: str = "torchtrack.image.flow.CombinedTracker"
    mode: str = "combined"  # combined | intensity (ablation EKF-2) | sim
    tim_threshold: float = 1.0  # px
    window: int = 21  # px, LK window (odd)
    levels: int = 3  # pyramid levels (the front end builds this many)
    iters: int = 30  # max iterations per level
    eps: float = 0.01  # px, convergence
    min_eig: float = 1.0e-4  # minimum eigenvalue of the 2x2 gradient matrix (normalised, as OpenCV)
    ic_iters: int = 3  # inverse-compositional iterations before Newton steps
    policy: str = "fallback"  # improvement (paper: min_tim): the SIM tracker only where the intensity tracker failed


@dataclass
class FrontendConfig:
    """:class:`torchtrack.frontend.FrontEnd`; its pyramid levels come from ``flow.levels`` (in the factory)."""

    _target_: str = "torchtrack.frontend.FrontEnd"
    use_sim: bool = True  # compute the SIM (SIM-assisted tracking, lambda < 1 selection)
    sim_kwargs: dict[str, Any] | None = None
    ahead: bool = True  # prepare the next frame (SIM, pyramids) in a thread while this one is tracked; same results


# --- back end ---------------------------------------------------------------------------------------------------


@dataclass
class FilterConfig:
    """:class:`torchtrack.filter.fusion.FusionEKF` (eqs. 2-7, 15): the fusion EKF's model, prior, gate, refit and
    online noise scale; variances per feature come from the weighting."""

    _target_: str = "torchtrack.filter.fusion.FusionEKF"
    sigma_ang_acc: float = 3.0  # rad/s^2, constant-velocity process noise (eqs. 3-4)
    sigma_lin_acc: float = 2.0  # m/s^2
    init_sigma_angle: float = 1.0e-3  # rad, pose std right after a (re-)selection
    init_sigma_trans: float = 1.0e-3  # m
    init_sigma_ang_vel: float = 1.0  # rad/s
    init_sigma_lin_vel: float = 0.5  # m/s
    iterations: int = 1  # 1 = the paper's EKF; > 1 = iterated EKF
    form: str = "information"  # information (fast) | gain (the paper's eq. 15, slow)
    jacobian: str = "analytic"  # analytic (closed form, ~10x faster, = autograd to 1e-10) | forward | reverse
    state: str = "se3"  # improvement: an error state on SE(3), regular everywhere | euler (the paper's eq. 2)
    gate: float | None = 0.999  # improvement (null = paper): chi-square gate on each feature's innovations
    refit: float | None = 0.999  # improvement (null = paper): re-update without features failing this quantile
    noise_scale: bool = True  # improvement (false = paper): online R scale per block (pix, 3D), from the residuals
    noise_forgetting: float = 0.98  # ... its forgetting factor per frame (a window of ~50 frames)
    noise_scale_min: float = 0.01  # ... bounds of the scale
    noise_scale_max: float = 100.0
    noise_clip: float | None = 0.9  # ... chi-square quantile winsorising each feature's residual (null: none)


@dataclass
class PaperWeightingConfig:
    """:class:`torchtrack.filter.weighting.PaperWeighting`: eqs. (11)-(14)."""

    _target_: str = "torchtrack.filter.weighting.PaperWeighting"
    sigma2_pix: float = 1.0  # px^2, mean 2D variance (kept by eq. 11)
    sigma2_xyz: float = 4.0e-6  # m^2, mean 3D variance at depth_ref (kept by eq. 14): (2 mm)^2 (paper: 1e-4)
    d_tim_floor: float = 0.01  # px; a perfect TIM match would otherwise get zero variance
    dist_floor: float = 1.0e-3  # m; guards eq. (13) at the centroid
    depth_var_exponent: float = 4.0  # improvement (0 = paper): 3D variance x (z / depth_ref)^4
    depth_ref: float = 1.0


@dataclass
class FixedWeightingConfig:
    """:class:`torchtrack.filter.weighting.FixedWeighting`: the same variances for every feature (EKF-3)."""

    _target_: str = "torchtrack.filter.weighting.FixedWeighting"
    sigma2_pix: float = 1.0
    sigma2_xyz: float = 1.0e-4


@dataclass
class LearnedWeightingConfig:
    """:func:`torchtrack.learn.checkpoint.learned_weighting`. The optional values are checks, not overrides: the
    factory raises when one differs from the checkpoint's (null: not checked)."""

    _target_: str = "torchtrack.learn.checkpoint.learned_weighting"
    checkpoint: str | None = None  # a .pt from torchtrack-train; null = the shipped default
    mode: str | None = None
    hidden: int | None = None
    sigma2_pix: float | None = None
    sigma2_xyz: float | None = None
    depth_var_exponent: float | None = None
    depth_ref: float | None = None


@dataclass
class EKFBackendConfig:
    """The fusion EKF as the pose estimator (``tracker=fusion_ekf``); the filter and its settings are the ``filter``
    node (present whatever the estimator, so that ``+experiment=paper`` sets them in one file)."""

    _target_: str = EKF_BACKEND
    ekf: Any = "${filter}"


@dataclass
class ICPConfig:
    _target_: str = "torchtrack.estimators.icp.ICPEstimator"
    max_iters: int = 50
    tol: float = 1.0e-6
    max_corr_dist: float | None = None


@dataclass
class CPDConfig:
    _target_: str = "torchtrack.estimators.cpd.CPDEstimator"
    w: float = 0.0
    max_iters: int = 100
    tol: float = 1.0e-5
    scale: bool = False


@dataclass
class HornConfig:
    _target_: str = "torchtrack.estimators.horn.HornEstimator"
    use_weights: bool = True


@dataclass
class RegistrationBackendConfig:
    """A registration baseline (``tracker=icp|cpd|horn``) on the tracked 3D-3D correspondences."""

    _target_: str = REGISTRATION_BACKEND
    weighted: bool = False  # weight points by the weighting's inverse 3D variances
    estimator: Any = None


# --- the pipeline and its stages ------------------------------------------------------------------------------
# The tracker (torchtrack.pipeline.Tracker) is composed of stage objects, each built by the factory from its own group:
# the per-frame stages above (region, select, flow, weighting, tracker = the back end) and the policy stages below
# (reselect, outliers, keyframes, landmarks, relocalise).


@dataclass
class PipelineConfig:
    """:class:`torchtrack.pipeline.Tracker` itself: what is not a stage of its own (see the factory)."""

    _target_: str = "torchtrack.pipeline.Tracker"
    predict_init: bool = True  # improvement (false = paper): LK starts at the constant-velocity prediction
    pixel_only: bool = True  # improvement (false = paper): a tracked feature without depth still measures its pixel
    record: bool = False  # compute every frame's per-feature cues (torchtrack-record)


@dataclass
class ReselectConfig:
    """:class:`torchtrack.pipeline.reselect.Reselection`: when and how the tracker takes a new model (paper §III)."""

    _target_: str = "torchtrack.pipeline.reselect.Reselection"
    fraction: float = 0.5  # new model when fewer than this fraction of the model's features survive
    min_features: int = 12  # ... or fewer than this many
    edge_step: float | None = 0.03  # improvement (null = paper): no features where depth jumps > 3% in 5x5 px
    keep_survivors: bool = True  # improvement (false = paper): a re-selection keeps the features still tracked
    min_separation_px: float = 8.0  # ... and adds new ones only this far from a survivor (or a re-acquired landmark)
    # improvement (off = paper: one depth sample): a model point is the information-weighted mean of its feature's
    # depth samples in the model frame; survivors carry it (torchtrack.pipeline.reselect.fuse_points)
    point_mean: str = "reselect"


@dataclass
class OutlierConfig:
    """:class:`torchtrack.pipeline.outliers.ResidualDrop`: which tracked features leave the model after the update."""

    _target_: str = "torchtrack.pipeline.outliers.ResidualDrop"
    max_residual_px: float | None = 3.0  # improvement (null = paper): drop features > 3 px from their reprojection


@dataclass
class KeyframeConfig:
    """:class:`torchtrack.pipeline.keyframes.KeyframeStore`: the one store of keyframes the landmarks and the
    relocaliser share (each attaches its own content per keyframe)."""

    _target_: str = "torchtrack.pipeline.keyframes.KeyframeStore"
    size: int = 8  # keyframes kept per sequence, a ring (the oldest is replaced)
    every: int = 10  # a keyframe at every model frame with a trusted pose, and at a trusted tracked frame this many
    # frames after the last keyframe (a model can last long: the store must stay recent); 0: model frames only


@dataclass
class LandmarkConfig:
    """:class:`torchtrack.pipeline.landmarks.LandmarkMap`: model points that outlive their model, re-acquired from the
    keyframes that saw them (the tracker's ``landmarks``; none when ``enabled`` is false)."""

    _target_: str = "torchtrack.pipeline.landmarks.LandmarkMap"
    enabled: bool = True  # improvement (false = paper): re-selections re-acquire old model points from keyframes
    per_keyframe: int = 128  # landmarks kept per keyframe
    max_candidates: int = 256  # at most this many re-tracked per sequence at once (oldest keyframe first)
    min_separation_px: float = "${reselect.min_separation_px}"  # not re-tracked this close to a tracked feature
    max_residual: float = 0.1  # largest LK photometric residual (mean absolute grey difference, [0, 1])
    max_shift_px: float = 30.0  # largest distance between the tracked pixel and the projection
    max_offset_m: float = 0.1  # largest distance of the measured from the predicted 3D point, x max(1, z^2)
    occlusion: float = 0.05  # occluded where the depth at the projection is nearer by this fraction
    correct: bool = True  # re-fit the camera pose to the re-acquired landmarks (and the model's features)
    inlier_m: float = 0.02  # ... the 3D residual's standard deviation in that fit, x max(1, z^2)
    min_inliers: int = 8  # ... when at least this many agree
    max_correction_m: float = 0.1  # ... a larger correction is not applied
    max_correction_deg: float = 5.0
    max_angle_deg: float = 15.0  # re-track only landmarks seen from within this angle (rotation, rays)
    max_scale: float = 1.25  # ... and whose depth changed by at most this ratio
    converge_px: float = 0.5  # a second LK started probe_px away must end within this of the first
    probe_px: float = 3.0


@dataclass
class DenseMapConfig:
    """:class:`torchtrack.map.dense_map.DenseMap`: the keyframes' depth as a map, the model's world pose aligned to
    it (the tracker's ``dense``; none when ``enabled`` is false)."""

    _target_: str = "torchtrack.map.dense_map.DenseMap"
    enabled: bool = True  # improvement (false = paper): the model placed on a dense map, not only chained
    voxel_size: float = 0.01  # m, the map's voxel edge (one point per occupied voxel)
    every: int = 1  # the camera aligned to the map every this many frames (and at every re-selection); 1: every frame
    max_voxels: int = 1_000_000  # a sequence's map beyond this is pruned (to 3/4), the least-supported voxels first


@dataclass
class RelocaliseConfig:
    """:class:`torchtrack.pipeline.relocalise.Relocaliser`: the loss check after each frame and relocalisation by ORB
    matches against recent model frames + PnP RANSAC (the tracker's ``relocaliser``)."""

    _target_: str = "torchtrack.pipeline.relocalise.Relocaliser"
    recover: bool = True  # improvement (false = paper: lost frames are only marked and warned about): relocalise
    min_survival: float = 0.25  # lost: fewer than this fraction of the previous frame's features tracked with depth
    max_rejected: float = 0.95  # ... or the filter rejected more than this fraction of them
    max_pos_std: float = 0.01  # m, ... or the posterior position std exceeds this
    orb_features: int = 1000
    ratio: float = 0.8  # Lowe's ratio test
    reprojection_px: float = 3.0  # RANSAC inlier threshold
    min_inliers: int = 30  # a relocalisation is accepted with at least this many inliers
    agree_m: float = 0.02  # a relocalised pose this close to the tracked one confirms it
    agree_deg: float = 2.0


# --- mapping ----------------------------------------------------------------------------------------------------


@dataclass
class MappingConfig:
    """:class:`torchtrack.map.PanoramaMapper` (paper §IV): coloured voxel-grid map per sequence; off unless
    ``enabled`` (``mapping=panorama`` or ``mapping=tsdf``; read by :func:`torchtrack.factory.build_mapper`)."""

    _target_: str = "torchtrack.map.PanoramaMapper"
    enabled: bool = False
    voxel_size: float = 0.01  # m, one point per voxel
    every: int | None = None  # also fuse every k-th frame; null: the first and the model (key) frames only
    pixel_stride: int = 2  # back-project every n-th pixel in x and y
    min_depth: float = 0.1  # m
    max_depth: float = 4.0  # m
    edge_step: float | None = 0.05  # drop pixels at depth steps above this fraction (flying pixels); null: off
    tsdf: bool = False  # also fuse the same frames with Open3D's TSDF (tensor VoxelBlockGrid) -> mesh.ply
    tsdf_voxel_size: float = 0.01  # m
    tsdf_trunc: float = 0.04  # m
    views: bool = True  # map.png: perspective view from the first camera and top-down view
    view_size: list[int] = field(default_factory=lambda: list(VIEW_SIZE))  # [H, W] of each view

    def __post_init__(self) -> None:
        for key in ("voxel_size", "tsdf_voxel_size", "tsdf_trunc", "max_depth"):
            if getattr(self, key) <= 0:
                raise DataError(f"mapping.{key} must be > 0, got {getattr(self, key)}")
        if self.pixel_stride < 1 or (self.every is not None and self.every < 1):
            raise DataError(f"mapping.pixel_stride and mapping.every must be >= 1, got {self.pixel_stride}, "
                            f"{self.every}")  # fmt: skip
        if not 0 <= self.min_depth < self.max_depth or len(self.view_size) != 2 or min(self.view_size) < 16:
            raise DataError(f"mapping: need 0 <= min_depth < max_depth and view_size [H, W] >= 16, got "
                            f"{self.min_depth}, {self.max_depth}, {self.view_size}")  # fmt: skip


SCHEMAS: dict[str, dict[str, type]] = {
    "data": {"tum": TumDataConfig, "synthetic": SyntheticDataConfig},
    "region": {"region": RegionConfig},
    "select": {"select": SelectConfig},
    "flow": {"flow": FlowConfig},
    "frontend": {"frontend": FrontendConfig},
    "filter": {"ekf": FilterConfig},
    "weighting": {"paper": PaperWeightingConfig, "fixed": FixedWeightingConfig, "learned": LearnedWeightingConfig},
    "tracker": {"ekf": EKFBackendConfig, "registration": RegistrationBackendConfig},
    "estimator": {"icp": ICPConfig, "cpd": CPDConfig, "horn": HornConfig},
    "pipeline": {"pipeline": PipelineConfig},
    "reselect": {"reselect": ReselectConfig},
    "outliers": {"outliers": OutlierConfig},
    "keyframes": {"keyframes": KeyframeConfig},
    "landmarks": {"landmarks": LandmarkConfig},
    "dense": {"dense": DenseMapConfig},
    "relocalise": {"relocalise": RelocaliseConfig},
    "mapping": {"mapping": MappingConfig},
}


def register() -> None:
    """Store every schema as ``schema/<group>/<name>`` (YAML files extend them; idempotent)."""
    cs = ConfigStore.instance()
    for group, nodes in SCHEMAS.items():
        for name, node in nodes.items():
            cs.store(group=f"schema/{group}", name=name, node=node)


def load_option(group: str, name: str) -> DictConfig:
    """``conf/<group>/<name>.yaml`` on its schema, without composing the whole config (usable inside a running app).

    Only the schema entries of its defaults list are followed (``/schema/<group>@_here_`` or ``@<key>``).
    """
    node = OmegaConf.load(CONF_DIR / group / f"{name}.yaml")
    out = OmegaConf.create()
    for entry in node.pop("defaults", []):
        if not isinstance(entry, DictConfig):
            continue  # _self_
        ((key, choice),) = entry.items()
        path, _, package = key.partition("@")
        schema = OmegaConf.structured(SCHEMAS[path.rsplit("/", 1)[-1]][choice])
        out = OmegaConf.merge(out, schema if package == "_here_" else {package: schema})
    return OmegaConf.merge(out, node)


def validate(cfg: DictConfig) -> None:
    """Range checks that types cannot express: build the data and mapping nodes' dataclasses (``__post_init__``).

    Raises :class:`~torchtrack.data.errors.DataError` with a one-line message.
    """
    OmegaConf.to_object(cfg.data)
    if "mapping" in cfg:
        OmegaConf.to_object(cfg.mapping)


register()
