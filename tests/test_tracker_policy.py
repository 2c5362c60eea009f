"""The re-selection policy (pipeline.reselect_coverage): image coverage of the features against hand-counted cells, and
the decision it changes."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.errors import InstantiationException

from torchtrack.config import CONF_DIR
from torchtrack.factory import build_tracker
from torchtrack.tracker import TrackerState, coverage


def compose_cfg(*overrides: str):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def test_coverage_counts_occupied_cells():
    H, W = 480, 640  # 4x4 cells of 160 x 120 px
    pixels = torch.tensor([[[0.0, 0.0], [639.0, 479.0], [170.0, 10.0], [171.0, 11.0], [300.0, 300.0], [5.0, 400.0]]])
    valid = torch.tensor([[True, True, True, True, True, False]])
    # cells (row, col): (0, 0), (3, 3), (0, 1) twice, (2, 1); the last feature is not valid
    assert coverage(pixels, valid, (H, W), 4).tolist() == [4 / 16]
    assert coverage(pixels, valid, (H, W), 1).tolist() == [1.0]
    assert coverage(pixels, torch.zeros_like(valid), (H, W), 4).tolist() == [0.0]
    batched = coverage(pixels.expand(2, -1, -1), torch.stack([valid[0], ~valid[0]]), (H, W), 4)
    assert batched.tolist() == [4 / 16, 1 / 16]


def spread_state(n: int, n_model: int, spread: bool) -> TrackerState:
    """n valid features on a 640 x 480 image, all in one corner or spread over the whole view."""
    g = torch.Generator().manual_seed(0)
    scale = torch.tensor([640.0, 480.0]) if spread else torch.tensor([100.0, 100.0])
    pixels = torch.rand(1, n, 2, generator=g) * (scale - 1)
    return TrackerState(pixels=pixels, valid=torch.ones(1, n, dtype=torch.bool), n_model=torch.tensor([n_model]))


@pytest.mark.parametrize(
    ("n", "spread", "paper", "policy"),
    [
        (100, True, False, False),  # more than half survive: no re-selection either way
        (40, True, True, False),  # fewer than half, but they span the view: the policy keeps the model
        (40, False, True, True),  # fewer than half, all in one corner: both re-select
        (10, True, True, True),  # below min_features: always
    ],
)
def test_policy_keeps_a_model_whose_features_span_the_view(n, spread, paper, policy):
    active = torch.ones(1, dtype=torch.bool)
    for overrides, expected in (((), paper), (("pipeline.reselect_coverage=0.75",), policy)):
        tracker = build_tracker(compose_cfg(*overrides))
        tracker.state = spread_state(n, 120, spread)
        assert tracker._needs_model(active, (480, 640)).tolist() == [expected]


def test_policy_off_by_default_and_in_paper_and_checked():
    assert compose_cfg().pipeline.reselect_coverage is None
    assert compose_cfg("+experiment=paper").pipeline.reselect_coverage is None
    with pytest.raises(InstantiationException, match="reselect_coverage must be in"):
        build_tracker(compose_cfg("pipeline.reselect_coverage=1.5"))
