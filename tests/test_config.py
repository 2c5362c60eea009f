"""Structured configs: every experiment composes with every estimator and weighting; types and ranges are checked
when composing; the estimator choice changes only the estimator; one set of defaults (schemas vs signatures)."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from hydra.utils import get_object
from omegaconf import OmegaConf

from torchtrack.config import (
    CONF_DIR,
    SCHEMAS,
    EKFBackendConfig,
    FlowConfig,
    PaperWeightingConfig,
    PipelineConfig,
    RelocaliseConfig,
    SelectConfig,
    validate,
)
from torchtrack.data.errors import DataError
from torchtrack.factory import build_tracker
from torchtrack.learn.checkpoint import save_checkpoint
from torchtrack.learn.model import LearnedWeighting
from torchtrack.tracker import Tracker

CONF = CONF_DIR
EXPERIMENTS = sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))
TRACKERS = sorted(p.stem for p in (CONF / "tracker").glob("*.yaml"))
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
@pytest.mark.parametrize("experiment", [None, *EXPERIMENTS, "[ekf1,ekf2,ekf3]", "[paper,ekf1,ekf2,ekf3]"])
def test_every_experiment_composes_with_every_estimator_and_weighting(experiment, tracker, weighting, checkpoint):
    overrides = [f"tracker={tracker}", f"weighting={weighting}"]
    overrides += [f"+experiment={experiment}"] if experiment else []
    overrides += [f"weighting.checkpoint={checkpoint}"] if weighting == "learned" else []
    cfg = config(*overrides)
    validate(cfg)
    tracker_obj = build_tracker(cfg)
    assert isinstance(tracker_obj, Tracker)
    assert type(tracker_obj.backend).__name__ == ("EKFBackend" if tracker == "fusion_ekf" else "RegistrationBackend")
    if experiment and "paper" in experiment:  # the paper's policy whatever the estimator
        assert tracker_obj.max_residual_px is None and tracker_obj.edge_step is None and not tracker_obj.keep_survivors
        if tracker == "fusion_ekf":
            assert tracker_obj.backend.gate is None and tracker_obj.backend.refit is None


@pytest.mark.parametrize("experiment", [None, "paper"])
@pytest.mark.parametrize("tracker", ["icp", "cpd", "horn"])
def test_the_estimator_choice_changes_only_the_estimator(tracker, experiment):
    extra = [f"+experiment={experiment}"] if experiment else []
    base = OmegaConf.to_container(config(*extra))
    other = OmegaConf.to_container(config(f"tracker={tracker}", *extra))
    assert base.pop("tracker") != other.pop("tracker")
    assert base == other


def test_paper_experiment_sets_the_paper_values():
    cfg = config("+experiment=paper")
    assert cfg.weighting.depth_var_exponent == 0.0 and cfg.weighting.sigma2_xyz == 1e-4
    assert cfg.flow.policy == "min_tim" and cfg.tracker.gate is None and cfg.tracker.refit is None
    assert config("+experiment=paper", "weighting=fixed").weighting == config("weighting=fixed").weighting


def differences(schema: type) -> dict[str, tuple]:
    """{field: (schema default, signature default)} where a schema's default differs from its target's."""
    node = OmegaConf.structured(schema)
    if "_target_" not in node:
        return {}  # data: read by the factory
    params = inspect.signature(get_object(node._target_)).parameters
    out = {}
    for key in node:
        p = params.get(key)
        if (
            key.startswith("_")
            or p is None
            or p.default is inspect.Parameter.empty
            or OmegaConf.is_interpolation(node, key)
        ):
            continue
        if node[key] != p.default:
            out[key] = (node[key], p.default)
    return out


# Where +experiment=paper puts each schema's node (with the choices that use it).
PAPER_NODES = {
    PipelineConfig: ("pipeline", ()), FlowConfig: ("flow", ()), EKFBackendConfig: ("tracker", ()),
    PaperWeightingConfig: ("weighting", ("weighting=paper",)), RelocaliseConfig: ("relocalise", ()),
    SelectConfig: ("select", ()),
}  # fmt: skip


@pytest.mark.parametrize("schema", [s for nodes in SCHEMAS.values() for s in nodes.values()], ids=lambda s: s.__name__)
def test_one_set_of_defaults(schema):
    """A schema default that differs from its Python signature's is an improvement: +experiment=paper sets it back."""
    diff = differences(schema)
    if not diff:
        return
    assert schema in PAPER_NODES, f"{schema.__name__} differs from its signature: {diff}"
    name, choices = PAPER_NODES[schema]
    paper = config("+experiment=paper", *choices)
    for key, (ours, default) in diff.items():
        assert paper[name][key] == default, f"{name}.{key}: {ours!r} here, {default!r} in the signature and the paper"


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


@pytest.mark.parametrize("override", ["data.depth_scale=abc", "data.max_frames=x", "pipeline.keep_survivors=maybe"])
def test_types_are_checked_when_composing(override):
    with pytest.raises(ConfigCompositionException):
        config("data=tum", override)


def test_the_front_end_levels_are_the_flow_levels():
    assert build_tracker(config("flow.levels=2")).frontend.levels == 2
    with pytest.raises(ConfigCompositionException):
        config("frontend.levels=2")  # one place only
