"""RANSAC before the update (``pipeline.ransac_threshold_m``): tracks corrupted on purpose are exactly the ones
removed (oracle: the corruption is known; the synthetic sequence is noise-free)."""

from __future__ import annotations

import torch
from test_tracker import make_tracker, synth  # noqa: F401  (fixture)

from torchtrack.data import iterate_batched
from torchtrack.filter.models import measure_points

# the landmarks' re-tracking from keyframes (pipeline.landmarks) calls the flow too: only the tracking is corrupted here
NO_LANDMARKS = ("pipeline.landmarks=false",)


class CorruptingFlow:
    """The tracker's flow, then every 4th tracked feature moved 60 px sideways (a gross LK slip; another quarter in
    each call, as the tracker drops the ones it caught)."""

    def __init__(self, flow) -> None:
        self.flow, self.corrupted, self.tracked = flow, [], []

    def __call__(self, *args, **kwargs):
        r = self.flow(*args, **kwargs)
        bad = r.valid & (torch.arange(r.valid.shape[1]) % 4 == len(self.corrupted) % 4)
        points = torch.where(bad[..., None], r.points + torch.tensor([60.0, 0.0]), r.points)
        self.corrupted.append(bad)
        self.tracked.append(r._replace(points=points))
        return self.tracked[-1]


def test_ransac_removes_exactly_the_corrupted_tracks(synth):  # noqa: F811
    seq = synth(seed=2, frames=4)
    tracker = make_tracker("data=tum", "pipeline.ransac_threshold_m=0.02", *NO_LANDMARKS)
    flow = tracker.flow = CorruptingFlow(tracker.flow)
    checked = 0
    for frame in iterate_batched([seq], prefetch=False):
        res = tracker.step(frame)
        if res.observation is None:
            continue
        track = flow.tracked[-1]
        _, has_depth = measure_points(tracker.state.prev.depth, frame.K, frame.T_color_depth, track.points)
        before = track.valid & has_depth
        bad = flow.corrupted[-1] & before
        assert bad.any()
        assert torch.equal(res.observation.valid, before & ~bad)
        checked += 1
    assert checked == len(seq) - 1


def test_ransac_only_under_large_motion(synth):  # noqa: F811
    """Below ``ransac_min_motion_px`` of median displacement the corrupted tracks reach the back end."""
    seq = synth(seed=2, frames=3)
    tracker = make_tracker(
        "data=tum", "pipeline.ransac_threshold_m=0.02", "pipeline.ransac_min_motion_px=1000", *NO_LANDMARKS
    )
    flow = tracker.flow = CorruptingFlow(tracker.flow)
    for frame in iterate_batched([seq], prefetch=False):
        res = tracker.step(frame)
        if res.observation is not None:
            assert (res.observation.valid & flow.corrupted[-1]).any()
