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

Keys. A key is a user's choice or one of the paper's switches. Internal thresholds (the landmarks', the relocaliser's,
the map's, the selection's border and suppression, the LK iterations) are the documented defaults of the classes they
tune; implementation forms (the filter's gain form and autograd Jacobian, LK and SIM references) are arguments that
the tests reach, not keys. A stage that can be off is a group option (``landmarks=none``, ``dense=none``,
``mapping=none``: an empty node, and the factory builds no stage), not an ``enabled`` key beside it.
"""

from __future__ import annotations

from dataclasses import dataclass
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
    roi_fraction: float | None = 0.5  # improvement (null = paper): a region whose box covers less of the image (inside
    # the border) gets patches shrunk so that the box holds as many as this fraction of the image would


@dataclass
class FlowConfig:
    """:class:`torchtrack.image.flow.CombinedTracker`: LK on intensity and SIM with the TIM check (eq. 10)."""

    _target_: str = "torchtrack.image.flow.CombinedTracker"
    mode: str = "combined"  # combined | intensity (ablation EKF-2) | sim
    tim_threshold: float = 1.0  # px
    window: int = 21  # px, LK window (odd)
    levels: int = 3  # pyramid levels (the front end builds this many)
    policy: str = "fallback"  # improvement (paper: min_tim): the SIM tracker only where the intensity tracker failed


@dataclass
class FrontendConfig:
    """:class:`torchtrack.frontend.FrontEnd`; its pyramid levels come from ``flow.levels`` (in the factory)."""

    _target_: str = "torchtrack.frontend.FrontEnd"
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
    state: str = "se3"  # improvement: an error state on SE(3), regular everywhere | euler (the paper's eq. 2)
    gate: float | None = 0.999  # improvement (null = paper): chi-square gate on each feature's innovations
    refit: float | None = 0.999  # improvement (null = paper): re-update without features failing this quantile
    noise_scale: bool = True  # improvement (false = paper): online R scale per block (pix, 3D), from the residuals


@dataclass
class PaperWeightingConfig:
    """:class:`torchtrack.filter.weighting.PaperWeighting`: eqs. (11)-(14)."""

    _target_: str = "torchtrack.filter.weighting.PaperWeighting"
    sigma2_pix: float = 1.0  # px^2, mean 2D variance (kept by eq. 11)
    sigma2_xyz: float = 4.0e-6  # m^2, mean 3D variance at depth_ref (kept by eq. 14): (2 mm)^2 (paper: 1e-4)
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
    """The fusion EKF as the pose estimator (``estimator=fusion_ekf``); the filter and its settings are the ``filter``
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
    """A registration baseline (``estimator=icp|cpd|horn``) on the tracked 3D-3D correspondences."""

    _target_: str = REGISTRATION_BACKEND
    weighted: bool = False  # weight points by the weighting's inverse 3D variances
    estimator: Any = None


# --- the pipeline and its stages ------------------------------------------------------------------------------
# The tracker (torchtrack.pipeline.Tracker) is composed of stage objects, each built by the factory from its own group:
# the per-frame stages above (region, select, flow, weighting, estimator = the back end) and the policy stages below
# (reselect, outliers, keyframes, landmarks, relocalise).


@dataclass
class PipelineConfig:
    """:class:`torchtrack.pipeline.Tracker` itself: what is not a stage of its own (see the factory)."""

    _target_: str = "torchtrack.pipeline.Tracker"
    predict_init: bool = True  # improvement (false = paper): LK starts at the constant-velocity prediction
    pixel_only: bool = True  # improvement (false = paper): a tracked feature without depth still measures its pixel


@dataclass
class ReselectConfig:
    """:class:`torchtrack.pipeline.reselect.Reselection`: when and how the tracker takes a new model (paper §III)."""

    _target_: str = "torchtrack.pipeline.reselect.Reselection"
    fraction: float = 0.5  # new model when fewer than this fraction of the model's features survive
    min_features: int = 12  # ... or fewer than this many
    edge_step: float | None = 0.03  # improvement (null = paper): no features where depth jumps > 3% in 5x5 px
    keep_survivors: bool = True  # improvement (false = paper): a re-selection keeps the features still tracked
    # improvement (false = paper: one depth sample): a model point is the information-weighted mean of its feature's
    # depth samples in the model frame; survivors carry it (torchtrack.pipeline.reselect.fuse_points)
    point_mean: bool = True


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
    keyframes that saw them (the tracker's ``landmarks``; ``landmarks=none`` builds none). Its thresholds are the
    class's documented defaults."""

    _target_: str = "torchtrack.pipeline.landmarks.LandmarkMap"


@dataclass
class DenseMapConfig:
    """:class:`torchtrack.map.dense_map.DenseMap`: the keyframes' depth as a map, the model's world pose aligned to
    it (the tracker's ``dense``; ``dense=none`` builds none)."""

    _target_: str = "torchtrack.map.dense_map.DenseMap"
    voxel_size: float = 0.01  # m, the map's voxel edge (one point per occupied voxel)
    every: int = 1  # the camera aligned to the map every this many frames (and at every re-selection); 1: every frame


@dataclass
class RelocaliseConfig:
    """:class:`torchtrack.pipeline.relocalise.Relocaliser`: the loss check after each frame and relocalisation by ORB
    matches against recent model frames + PnP RANSAC (the tracker's ``relocaliser``); its thresholds are the class's
    documented defaults."""

    _target_: str = "torchtrack.pipeline.relocalise.Relocaliser"
    recover: bool = True  # improvement (false = paper: lost frames are only marked and warned about): relocalise


# --- mapping ----------------------------------------------------------------------------------------------------


@dataclass
class MappingConfig:
    """:class:`torchtrack.map.PanoramaMapper` (paper §IV): coloured voxel-grid map per sequence (``mapping=panorama``
    or ``mapping=tsdf``; ``mapping=none``, the default, builds none: :func:`torchtrack.factory.build_mapper`). Its depth
    range, pixel stride, flying-pixel filter and TSDF truncation are the class's documented defaults."""

    _target_: str = "torchtrack.map.PanoramaMapper"
    voxel_size: float = 0.01  # m, one point per voxel
    every: int | None = None  # also fuse every k-th frame; null: the first and the model (key) frames only
    tsdf: bool = False  # also fuse the same frames with Open3D's TSDF (tensor VoxelBlockGrid) -> mesh.ply
    views: bool = True  # map.png: perspective view from the first camera and top-down view

    def __post_init__(self) -> None:
        if self.voxel_size <= 0:
            raise DataError(f"mapping.voxel_size must be > 0, got {self.voxel_size}")
        if self.every is not None and self.every < 1:
            raise DataError(f"mapping.every must be >= 1, got {self.every}")


SCHEMAS: dict[str, dict[str, type]] = {
    "data": {"tum": TumDataConfig, "synthetic": SyntheticDataConfig},
    "region": {"region": RegionConfig},
    "select": {"select": SelectConfig},
    "flow": {"flow": FlowConfig},
    "frontend": {"frontend": FrontendConfig},
    "filter": {"ekf": FilterConfig},
    "weighting": {"paper": PaperWeightingConfig, "fixed": FixedWeightingConfig, "learned": LearnedWeightingConfig},
    "estimator": {"ekf": EKFBackendConfig, "registration": RegistrationBackendConfig},
    "registration": {"icp": ICPConfig, "cpd": CPDConfig, "horn": HornConfig},
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


# Groups renamed: a config folder of the old name is named in one line (the shipped options of ``tracker=`` still
# select the estimator: conf/tracker/).
RENAMED_GROUPS = {"tracker": "estimator"}


def validate(cfg: DictConfig) -> None:
    """Range checks that types cannot express: build the data and mapping nodes' dataclasses (``__post_init__``).

    Raises :class:`~torchtrack.data.errors.DataError` with a one-line message.
    """
    for old, new in RENAMED_GROUPS.items():
        if cfg.get(old):
            raise DataError(f"the {old}= group is now {new}=: use {new}=NAME (a config of your own: {new}/NAME.yaml)")
    OmegaConf.to_object(cfg.data)
    if "mapping" in cfg:
        OmegaConf.to_object(cfg.mapping)


register()
