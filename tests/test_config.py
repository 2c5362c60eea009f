"""Structured configs: every experiment composes with every estimator and weighting; types and ranges are checked
when composing; the estimator choice changes only the estimator; one set of defaults (schemas vs signatures); a key
is a user's choice (at most 90 of them), every stage builds from its schema, and the old group name still works."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import get_object, instantiate
from omegaconf import OmegaConf
from pointsets import random_cloud

from torchtrack.config import (
    CONF_DIR,
    SCHEMAS,
    CPDConfig,
    FilterConfig,
    FlowConfig,
    ICPConfig,
    PaperWeightingConfig,
    RegionConfig,
    RegistrationBackendConfig,
    validate,
)
from torchtrack.data.errors import DataError
from torchtrack.estimators.cpd import CPDEstimator
from torchtrack.estimators.horn import HornEstimator
from torchtrack.estimators.icp import ICPEstimator
from torchtrack.factory import build_mapper, build_tracker
from torchtrack.filter.backend import EKFBackend
from torchtrack.filter.fusion import FusionEKF
from torchtrack.filter.weighting import FixedWeighting, PaperWeighting, WeightingInputs
from torchtrack.frontend import FrontEnd
from torchtrack.image.flow import CombinedTracker, combined_track
from torchtrack.image.object_model import ObjectRegion, object_mask
from torchtrack.image.select import select_features
from torchtrack.learn.checkpoint import save_checkpoint
from torchtrack.learn.model import LearnedWeighting
from torchtrack.map import PanoramaMapper
from torchtrack.map.dense_map import DenseMap
from torchtrack.pipeline import Tracker
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.landmarks import LandmarkMap
from torchtrack.pipeline.outliers import ResidualDrop
from torchtrack.pipeline.relocalise import Relocaliser
from torchtrack.pipeline.reselect import Reselection

CONF = CONF_DIR
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
TRACKERS = sorted(p.stem for p in (CONF / "estimator").glob("*.yaml"))
WEIGHTINGS = ("fixed", "paper", "learned")


def config(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "untrained.pt", LearnedWeighting())


def test_the_groups_are_all_there():
    assert set(EXPERIMENTS) >= {"paper", "ekf1", "ekf2", "ekf3"} and set(TRACKERS) == {
        "cpd",
        "fusion_ekf",
        "horn",
        "icp",
    }


@pytest.mark.parametrize("weighting", WEIGHTINGS)
@pytest.mark.parametrize("tracker", TRACKERS)
@pytest.mark.parametrize(
    "experiment",
    [None, "paper"]
    + [pytest.param(e, marks=pytest.mark.slow) for e in EXPERIMENTS if e != "paper"]
    + [pytest.param(e, marks=pytest.mark.slow) for e in ("[ekf1,ekf2,ekf3]", "[paper,ekf1,ekf2,ekf3]")],
)
def test_every_experiment_composes_with_every_estimator_and_weighting(experiment, tracker, weighting, checkpoint):
    overrides = [f"estimator={tracker}", f"weighting={weighting}"]
    overrides += [f"+experiment={experiment}"] if experiment else []
    overrides += [f"weighting.checkpoint={checkpoint}"] if weighting == "learned" else []
    cfg = config(*overrides)
    validate(cfg)
    tracker_obj = build_tracker(cfg)
    assert isinstance(tracker_obj, Tracker)
    assert type(tracker_obj.backend).__name__ == ("EKFBackend" if tracker == "fusion_ekf" else "RegistrationBackend")
    if experiment and "paper" in experiment:  # the paper's policy whatever the estimator
        assert tracker_obj.outliers.max_residual_px is None and tracker_obj.reselect.edge_step is None
        assert not tracker_obj.reselect.keep_survivors and tracker_obj.landmarks is None
        if tracker == "fusion_ekf":
            assert tracker_obj.backend.ekf.gate is None and tracker_obj.backend.ekf.refit is None


@pytest.mark.parametrize("experiment", [None, "paper"])
@pytest.mark.parametrize("tracker", ["icp", "cpd", "horn"])
def test_the_estimator_choice_changes_only_the_estimator(tracker, experiment):
    extra = [f"+experiment={experiment}"] if experiment else []
    base = OmegaConf.to_container(config(*extra))
    other = OmegaConf.to_container(config(f"estimator={tracker}", *extra))
    assert base.pop("estimator") != other.pop("estimator")
    assert base == other


def test_paper_experiment_sets_the_paper_values():
    cfg = config("+experiment=paper")
    assert cfg.weighting.depth_var_exponent == 0.0 and cfg.weighting.sigma2_xyz == 1e-4
    assert cfg.flow.policy == "min_tim" and cfg.filter.gate is None and cfg.filter.refit is None
    assert config("+experiment=paper", "weighting=fixed").weighting == config("weighting=fixed").weighting


# The functions and classes each schema configures besides its ``_target_`` (the pure function behind a thin class, or
# the reverse): their signatures read the schema's defaults too.
PARTNERS = {
    FlowConfig: ("torchtrack.image.flow.combined_track",),
    RegionConfig: ("torchtrack.image.object_model.object_mask",),
    PaperWeightingConfig: ("torchtrack.filter.weighting.paper_variances",),
    ICPConfig: ("torchtrack.estimators.icp.icp",),
    CPDConfig: ("torchtrack.estimators.cpd.cpd_rigid",),
    FilterConfig: ("torchtrack.filter.frame.ekf_frame",),
}
KNOWN: set[tuple[str, str]] = set()  # known disagreements between a signature and its schema: none
# Not the schema's knob under the same name: ekf_frame takes the NoiseScale object itself (None: off, as false).
OTHER_MEANING = {("ekf_frame", "noise_scale")}


def differences(schema: type) -> dict[str, tuple]:
    """{"callable.field": (schema default, signature default)} where a schema's default differs from a default of its
    target or partners (a field they take without a default is fine: the caller must pass it)."""
    node = OmegaConf.structured(schema)
    if "_target_" not in node:
        return {}  # data: read by the factory
    out = {}
    for target in (node._target_, *PARTNERS.get(schema, ())):
        obj = get_object(target)
        for key, p in inspect.signature(obj).parameters.items():
            if key not in node or key.startswith("_") or p.default is inspect.Parameter.empty:
                continue
            if OmegaConf.is_interpolation(node, key):
                continue
            ours = OmegaConf.to_container(node, resolve=False)[key]
            default = list(p.default) if isinstance(p.default, tuple) else p.default
            if ours != default and (obj.__name__, key) not in KNOWN | OTHER_MEANING:
                out[f"{obj.__name__}.{key}"] = (ours, p.default)
    return out


@pytest.mark.parametrize("schema", [s for nodes in SCHEMAS.values() for s in nodes.values()], ids=lambda s: s.__name__)
def test_one_set_of_defaults(schema):
    """Every default lives in the schema: a signature default of what it configures equals the schema's."""
    assert differences(schema) == {}, f"{schema.__name__}: schema vs signature defaults"


def test_the_front_end_levels_default_to_the_flow_levels():
    assert inspect.signature(FrontEnd).parameters["levels"].default == FlowConfig.levels


def test_paper_values_stay_reachable():
    """+experiment=paper is the one file of the paper's values (with the weighting option it selects): each value it
    sets differs from the default, and the composed config carries it."""
    ours, paper = config(), config("+experiment=paper")
    values = OmegaConf.load(CONF / "experiment" / "paper.yaml")
    weighting = OmegaConf.load(CONF / "weighting" / "paper_as_written.yaml")
    assert list(values.pop("defaults")) == [
        {"override /weighting": "paper_as_written"},
        {"override /landmarks": "none"},
        {"override /dense": "none"},
    ]
    weighting.pop("defaults")
    values.weighting = weighting
    assert len(values) == 8 and paper.filter.state == "euler"  # groups
    for group, node in values.items():
        for key, value in node.items():
            assert paper[group][key] == value and ours[group][key] != value, f"{group}.{key}"
    for stage in ("landmarks", "dense"):  # the paper has neither stage: its option is the empty node
        assert paper[stage] == {} and "_target_" in ours[stage], stage


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("data.max_frames=-1", "data.max_frames must be >= 1"),
        ("data.stride=0", "data.stride must be >= 1"),
        ("data.root=[]", "data.root must be a folder or a non-empty list"),
        ("data.depth_intrinsics=[525,525,320]", r"data.depth_intrinsics must be \[fx, fy, cx, cy\]"),
        ("data.T_color_depth=[[1,0],[0,1]]", "data.T_color_depth must be a 4x4 matrix"),
        ("data.depth_scale=-5", "data.depth_scale must be > 0"),
    ],
)
def test_ranges_are_checked_by_validate(override, message):
    cfg = config("data=tum", override)
    with pytest.raises(DataError, match=message):
        validate(cfg)


@pytest.mark.parametrize("override", ["data.depth_scale=abc", "data.max_frames=x", "reselect.keep_survivors=maybe"])
def test_types_are_checked_when_composing(override):
    with pytest.raises(ConfigCompositionException):
        config("data=tum", override)


# ---------------------------------------------------------------------------------- a key is a user's choice
MAX_SETTINGS = 90


def settings(node) -> list[str]:
    """The dotted names of the leaf settings of ``node`` (a container), other than ``_target_`` and ``_partial_``."""
    if not isinstance(node, dict):
        return [""]
    keys = (k for k in node if k not in ("_target_", "_partial_"))
    return [f"{k}.{leaf}".rstrip(".") for k in keys for leaf in settings(node[k])]


def test_the_default_config_has_at_most_90_settings():
    names = settings(OmegaConf.to_container(config(), resolve=False))
    assert 0 < len(names) <= MAX_SETTINGS, names
    assert "reselect.point_mean" in names and "filter.gate" in names  # the counter sees the paper's switches


def _option_configs():
    """Every option of every group a user picks on the command line, composed (the learned weighting: its default)."""
    skip = {"data", "dataset", "train", "hydra", "experiment", "tracker"}
    for group in sorted(d.name for d in CONF.iterdir() if d.is_dir() and d.name not in skip):
        for option in sorted(p.stem for p in (CONF / group).glob("*.yaml")):
            yield group, option, config(f"{group}={option}")[group]


def test_no_implementation_form_and_no_double_switch_is_a_key():
    """Backends, the filter's form and Jacobian are arguments, not keys; a stage that can be off is a group option
    (``landmarks=none``), not an ``enabled`` key beside the group; a boolean is a boolean."""
    banned = {"enabled", "backend", "lk_backend", "sim_backend", "form", "jacobian"}
    for group, option, node in _option_configs():
        names = settings(OmegaConf.to_container(node, resolve=False))
        assert not {n.rsplit(".", 1)[-1] for n in names} & banned, f"{group}={option}: {names}"
    for cfg in (config(), config("+experiment=paper")):
        flat = OmegaConf.to_container(cfg, resolve=True)
        for name in settings({k: v for k, v in flat.items() if k != "hydra"}):
            value = OmegaConf.select(cfg, name)
            assert not (isinstance(value, str) and value.lower() in {"on", "off", "true", "false"}), name
    assert config("+experiment=paper").reselect.point_mean is False and config().reselect.point_mean is True


# What the factory wires into a stage besides its node: the objects other groups build (never a user's value).
WIRING = {
    "ReselectConfig": {"region", "select"},
    "PipelineConfig": {"frontend", "flow", "weighting", "backend", "reselect"},
    "EKFBackendConfig": {"ekf"},
    "RegistrationBackendConfig": {"estimator"},
}


def _wired(name: str) -> dict:
    region, select = ObjectRegion(), select_features
    reselect = Reselection(region=region, select=select)
    objects = dict(region=region, select=select, frontend=FrontEnd(), flow=CombinedTracker(),
                   weighting=PaperWeighting(), backend=EKFBackend(FusionEKF()), reselect=reselect,
                   ekf=FusionEKF(), estimator=HornEstimator())  # fmt: skip
    return {k: objects[k] for k in WIRING.get(name, ())}


@pytest.mark.parametrize(
    "schema",
    [s for group, nodes in SCHEMAS.items() if group != "data" for s in nodes.values()],
    ids=lambda s: s.__name__,
)
def test_every_target_builds_from_its_schema_with_no_hidden_argument(schema, checkpoint):
    """Each schema's ``_target_`` is built from the schema's defaults alone (plus the stages the factory wires in,
    :data:`WIRING`), and every argument it requires is a schema key or such a stage: none a user would need to pass."""
    node = OmegaConf.to_container(OmegaConf.structured(schema), resolve=False)
    target = get_object(node["_target_"])
    params = inspect.signature(target).parameters.values()
    kinds = (
        (inspect.Parameter.KEYWORD_ONLY,)
        if node.get("_partial_")
        else (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    )  # a partial's positionals: its inputs
    required = {p.name for p in params if p.default is inspect.Parameter.empty and p.kind in kinds}
    wiring = WIRING.get(schema.__name__, set())
    assert required <= (set(node) | wiring), f"{schema.__name__}: {required - set(node) - wiring} not in the schema"
    kwargs = {k: v for k, v in node.items() if k not in wiring}
    if schema.__name__ == "LearnedWeightingConfig":
        kwargs["checkpoint"] = str(checkpoint)  # null is the shipped file: a fresh one keeps the test self-contained
    built = instantiate(kwargs, **_wired(schema.__name__))
    if node.get("_partial_"):
        assert built.func is target
    elif inspect.isclass(target):
        assert isinstance(built, target)


@pytest.mark.parametrize("name", TRACKERS)
def test_the_old_group_name_selects_the_same_estimator(name):
    assert config(f"tracker={name}") == config(f"estimator={name}")
    assert config(f"tracker={name}", "+experiment=paper") == config(f"estimator={name}", "+experiment=paper")


def test_the_old_group_name_in_a_key_or_a_users_folder_is_one_line_naming_the_new(tmp_path):
    from torchtrack.cli import check_overrides

    assert "the tracker= group is now estimator=" in check_overrides("config", ["tracker.weighted=true"])
    (tmp_path / "tracker").mkdir()
    (tmp_path / "tracker" / "mine.yaml").write_text("_target_: torchtrack.estimators.horn.HornEstimator\n")
    error = check_overrides("config", [f"conf_dir={tmp_path}", "tracker=mine"])
    assert error.startswith("the tracker= group is now estimator=") and "\n" not in error


@pytest.mark.parametrize(
    "overrides, use_sim",
    [((), True), (("flow.mode=intensity",), True), (("select.lam=1.0",), True), (("+experiment=ekf2",), True),
     (("+experiment=[ekf1,ekf2]",), False), (("+experiment=[ekf1,ekf2]", "weighting=learned"), True),
     (("flow.mode=sim", "select.lam=1.0"), True)],
)  # fmt: skip
def test_the_sim_is_computed_where_a_stage_reads_it(overrides, use_sim):
    """SIM-assisted tracking, lambda < 1 selection (eq. 9) or a weighting's cues: no key, derived in one place."""
    assert build_tracker(config(*overrides)).frontend.use_sim is use_sim
    with pytest.raises(ConfigCompositionException):
        config("frontend.use_sim=false")


def test_the_front_end_levels_are_the_flow_levels():
    assert build_tracker(config("flow.levels=2")).frontend.levels == 2
    with pytest.raises(ConfigCompositionException):
        config("frontend.levels=2")  # one place only


# ------------------------------------------------------------------- direct builds behave as the CLI's -----------
# Each stage built by the CLI (build_tracker / build_mapper on the composed config) and built directly with no
# arguments: equal behaviour on a small input, or equal state where the state is the behaviour. Where a default is an
# improvement, the paper's value is also run on the same input, to show that the input tells the two apart.
H_, W_ = 96, 128


def _texture(x: torch.Tensor, y: torch.Tensor, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    f, phase = 0.05 + 0.25 * torch.rand(12, 2, generator=g), 6.3 * torch.rand(12, generator=g)
    out = sum(torch.sin(f[k, 0] * x + f[k, 1] * y + phase[k]) for k in range(12))
    return (0.5 + out / 24).clamp(0, 1)


def _frame(dx: float = 0.0, dy: float = 0.0):
    """(gray, depth, K, sim): a textured plane at 1 m, shifted by (dx, dy) px; its SIM image another texture."""
    y, x = torch.meshgrid(torch.arange(H_, dtype=torch.float32), torch.arange(W_, dtype=torch.float32), indexing="ij")
    gray, sim = _texture(x - dx, y - dy, 0)[None, None], _texture(x - dx, y - dy, 7)[None, None]
    depth = (1.0 + 0.05 * torch.sin(x / 9) * torch.cos(y / 7))[None, None]
    K = torch.tensor([[[120.0, 0.0, W_ / 2], [0.0, 120.0, H_ / 2], [0.0, 0.0, 1.0]]])
    return gray, depth, K, sim


def _state(obj, depth: int = 0):
    """A comparable picture of an object's state (attributes, recursively; tensors as lists)."""
    if isinstance(obj, torch.Tensor):
        return ("tensor", obj.dtype, obj.tolist())
    if isinstance(obj, dict):
        return {k: _state(v, depth + 1) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_state(v, depth + 1) for v in obj)
    if hasattr(obj, "__dict__") and not callable(getattr(obj, "__func__", None)) and depth < 4:
        return (type(obj).__name__, {k: _state(v, depth + 1) for k, v in vars(obj).items() if k != "_ready"})
    return obj


def _same(a, b) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a, b, strict=True))


@pytest.fixture(scope="module")
def cli():
    """The CLI's stages: the default config, with the object region (the default is the scene: whole_frame=true)."""
    return build_tracker(config("region=object"))


def test_select_direct_equals_cli(cli):
    gray, depth, K, _ = _frame()
    roi = torch.zeros_like(depth, dtype=torch.bool)
    roi[..., 30:70, 40:100] = True  # a small region: roi_fraction (an improvement) shrinks the patches
    ours = cli.reselect.select(gray, depth, K, roi=roi)
    assert _same(ours, select_features(gray, depth, K, roi=roi))
    assert not _same(ours, select_features(gray, depth, K, roi=roi, roi_fraction=None))  # the paper's differs


def test_flow_direct_equals_cli(cli):
    (g0, _, _, s0), (g1, _, _, s1) = _frame(), _frame(0.9, 0.3)
    f0, f1 = cli.flow.prepare(g0, s0), cli.flow.prepare(g1, s1)
    y, x = torch.meshgrid(torch.linspace(24, H_ - 24, 5), torch.linspace(24, W_ - 24, 6), indexing="ij")
    pts = torch.stack([x, y], -1).reshape(1, -1, 2)
    ours = cli.flow(f0, f1, pts)
    assert _same(ours, combined_track(f0, f1, pts)) and _same(ours, CombinedTracker()(f0, f1, pts))
    assert CombinedTracker().kwargs == cli.flow.kwargs
    assert not _same(ours, combined_track(f0, f1, pts, policy="min_tim"))  # the paper's differs


def test_frontend_and_region_direct_equal_cli(cli):
    assert _state(FrontEnd()) == _state(cli.frontend)
    _, depth, _, _ = _frame()
    depth = depth * (1 + (torch.arange(W_) > W_ // 2))  # two depth layers: the object is the near one
    region = cli.reselect.region
    assert torch.equal(ObjectRegion()(depth), region(depth)) and torch.equal(object_mask(depth), region(depth))


@pytest.mark.parametrize("weighting", ["paper", "fixed"])
def test_weighting_direct_equals_cli(weighting):
    g = torch.Generator().manual_seed(3)
    inp = WeightingInputs(
        torch.rand(2, 9, generator=g, dtype=torch.float64), 0.5 + 2 * torch.rand(2, 9, generator=g, dtype=torch.float64),
        torch.randn(2, 9, 3, generator=g, dtype=torch.float64), torch.ones(2, 9, dtype=torch.bool),
        torch.tensor([500.0, 520.0], dtype=torch.float64),
    )  # fmt: skip
    ours = build_tracker(config(f"weighting={weighting}")).weighting(inp)
    direct = {"paper": PaperWeighting, "fixed": FixedWeighting}[weighting]()(inp)
    assert _same(ours, direct)
    if weighting == "paper":
        assert not _same(ours, PaperWeighting(depth_var_exponent=0.0, sigma2_xyz=1e-4)(inp))  # the paper's differs


def test_filter_direct_equals_cli(cli):
    assert _state(FusionEKF()) == _state(cli.backend.ekf)


def test_ekf_backend_direct_equals_cli(cli):
    assert _state(EKFBackend(FusionEKF())) == _state(cli.backend)


@pytest.mark.parametrize("name", ["icp", "cpd", "horn"])
def test_estimators_direct_equal_cli(name):
    backend = build_tracker(config(f"estimator={name}")).backend
    direct = {"icp": ICPEstimator, "cpd": CPDEstimator, "horn": HornEstimator}[name]()
    assert _state(direct) == _state(backend.estimator) and backend.weighted is RegistrationBackendConfig.weighted
    src = random_cloud(2, 30, seed=5)
    T = torch.eye(4, dtype=src.dtype).repeat(2, 1, 1)
    T[:, :3, 3] = torch.tensor([0.02, -0.01, 0.03], dtype=src.dtype)
    dst, valid = src @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3], torch.ones(2, 30, dtype=torch.bool)
    eye = torch.eye(4, dtype=src.dtype).repeat(2, 1, 1)
    assert torch.equal(direct(src, dst, valid, eye, None), backend.estimator(src, dst, valid, eye, None))


def test_pipeline_stages_and_mapper_direct_equal_cli(cli):
    """Every policy stage built directly equals the CLI's, and so does the tracker composed of the CLI's per-frame
    stages with its policy stages left to their defaults."""
    per_frame = dict(region=cli.reselect.region, select=cli.reselect.select)
    stages = dict(frontend=cli.frontend, flow=cli.flow, weighting=cli.weighting, backend=cli.backend,
                  reselect=Reselection(**per_frame), landmarks=cli.landmarks, relocaliser=cli.relocaliser, dense=cli.dense)  # fmt: skip
    assert _state(Tracker(**stages)) == _state(cli)
    assert _state(Reselection(**per_frame)) == _state(cli.reselect)
    assert _state(ResidualDrop()) == _state(cli.outliers) and _state(KeyframeStore()) == _state(cli.keyframes)
    assert _state(LandmarkMap()) == _state(cli.landmarks) and _state(DenseMap()) == _state(cli.dense)
    assert _state(Relocaliser()) == _state(cli.relocaliser)
    assert _state(PanoramaMapper()) == _state(build_mapper(config("mapping=panorama")))


def test_policy_stages_direct_equal_cli_in_behaviour(cli):
    """The re-selection and outlier stages decide as the CLI's do on one input, and the paper's values decide
    otherwise on it (so the input tells the two apart)."""
    g = torch.Generator().manual_seed(1)
    valid = torch.rand(3, 40, generator=g) < torch.tensor([[0.2], [0.4], [0.9]])
    n_model, active = torch.full((3,), 40), torch.ones(3, dtype=torch.bool)
    stages = dict(region=cli.reselect.region, select=cli.reselect.select)
    ours = cli.reselect.needed(valid, n_model, active)
    assert torch.equal(ours, Reselection(**stages).needed(valid, n_model, active))
    assert not torch.equal(ours, Reselection(**stages, fraction=0.1, min_features=1).needed(valid, n_model, active))
    residuals = 6 * torch.rand(3, 40, generator=g)
    assert torch.equal(cli.outliers(residuals, valid), ResidualDrop()(residuals, valid))
    assert not torch.equal(cli.outliers(residuals, valid), ResidualDrop(max_residual_px=None)(residuals, valid))
    _, depth, _, _ = _frame()
    depth = depth * (1 + (torch.arange(W_) > W_ // 2))  # a depth step: the edge rule removes its neighbourhood
    assert torch.equal(cli.reselect.roi(depth), Reselection(**stages).roi(depth))
    assert not torch.equal(cli.reselect.roi(depth), Reselection(**stages, edge_step=None).roi(depth))
