"""Tracking from the model frame (``pipeline.track_from_model``): every frame's LK runs from the frame where the
current model was taken, at the features' pixels there; oracles are the tracker's own re-selection frames and
the looped run of each sequence."""

from __future__ import annotations

import pytest
import torch
from hydra import compose, initialize_config_dir
from test_tracker import make_tracker, synth, track  # noqa: F401  (fixture)
from tolerances import TRAJ

from torchtrack.config import CONF_DIR
from torchtrack.data import iterate_batched

ON = ("data=tum", "pipeline.track_from_model=true", "pipeline.reselect_fraction=0.9")


class SpyFlow:
    """Wraps the tracker's flow and records the source images and start points of every call."""

    def __init__(self, flow) -> None:
        self.flow, self.calls = flow, []

    def __call__(self, prev, next, points, valid, **kwargs):
        self.calls.append((prev.images[0].clone(), points.clone(), valid.clone()))
        return self.flow(prev, next, points, valid, **kwargs)


def fast(synth, seed=5, frames=9):  # noqa: F811
    return synth(seed=seed, frames=frames, trans_step_m=0.03, rot_step_deg=2.5)


@pytest.mark.parametrize("landmarks", ["true", "false"])
def test_lk_starts_in_the_model_frame_at_the_model_pixels(synth, landmarks):  # noqa: F811
    """After a frame that took a model, every LK call until the next one tracks from that frame's grey image and
    from the model's pixels there (re-selections, survivors and re-acquired landmarks included)."""
    tracker = make_tracker(*ON, f"pipeline.landmarks={landmarks}")
    spy = tracker.flow = SpyFlow(tracker.flow)
    model_gray = model_pixels = None
    checked, models = 0, 0
    for frame in iterate_batched([fast(synth)], prefetch=False):
        n_calls = len(spy.calls)
        res = tracker.step(frame)
        if model_gray is not None:
            gray, points, valid = spy.calls[n_calls]  # the frame's tracking call (landmarks call it later)
            assert torch.equal(gray, model_gray)
            assert torch.equal(points[valid], model_pixels[valid[0]])
            checked += 1
        if res.reselected[0]:
            models += 1
            model_gray = tracker.state.prev.flow.images[0].clone()
            model_pixels = tracker.state.pixels[0].clone()
            assert torch.equal(tracker.state.model_pixels[0], model_pixels)
    assert checked == 8 and models >= 3  # the property held across re-selections


def test_off_tracks_from_the_previous_frame(synth):  # noqa: F811
    """The paper's (and the switch off): the source is the previous frame and the start its tracked pixels."""
    tracker = make_tracker("data=tum", "pipeline.reselect_fraction=0.9", "pipeline.landmarks=false")
    spy = tracker.flow = SpyFlow(tracker.flow)
    prev_gray = prev_pixels = None
    for frame in iterate_batched([fast(synth, frames=5)], prefetch=False):
        n_calls = len(spy.calls)
        tracker.step(frame)
        if prev_gray is not None:
            gray, points, _ = spy.calls[n_calls]
            assert torch.equal(gray, prev_gray) and torch.equal(points, prev_pixels)
        prev_gray = tracker.state.prev.flow.images[0].clone()
        prev_pixels = tracker.state.pixels.clone()
    assert tracker.state.model_flow is None


@pytest.mark.equivalence
def test_batched_equals_looped(synth):  # noqa: F811
    """Two sequences that re-select at different frames (each keeps its own model frame in the batch's merged
    model images) give the poses they give alone."""
    seqs = [fast(synth, seed=5), fast(synth, seed=8)]
    batched, results = track(make_tracker(*ON), seqs)
    reselected = torch.stack([r.reselected for r in results[1:]])  # F-1,B
    assert (reselected[:, 0] != reselected[:, 1]).any()  # one re-selected without the other
    for i, seq in enumerate(seqs):
        alone, _ = track(make_tracker(*ON), [seq])
        torch.testing.assert_close(batched[i], alone[0], atol=TRAJ, rtol=0)


def test_default_off_and_paper_off_and_exclusive_with_landmark_every():
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
        assert compose("config").pipeline.track_from_model is False
        assert compose("config", overrides=["+experiment=paper"]).pipeline.track_from_model is False
    with pytest.raises(Exception, match="landmark_every"):  # Hydra wraps the ValueError
        make_tracker(*ON, "pipeline.landmark_every=5")
