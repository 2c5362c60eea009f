"""Host synchronisations in ``Tracker.step``: none per feature, on the compiled path and on the references.

On a GPU every read of a tensor's value on the host (``.item()``, ``bool(t)``, ``nonzero`` and other ops whose output
shape depends on the data) stalls the stream. The step may sync a bounded number of times per frame (a re-selection
decision, a loop's stop test), never once per feature. Counted here on the CPU with a dispatch mode that sees every
aten call, so no GPU is needed: the same step with ~3.5x more features must sync no more often, and the steady frames
stay below the smaller run's feature count (a per-feature sync would exceed it). The references are the path that
runs on devices without the compiled operators.
"""

from __future__ import annotations

from collections import Counter

import pytest
from reference import references
from torch.utils._python_dispatch import TorchDispatchMode

from torchtrack.cli import compose_config
from torchtrack.data.batching import iterate_batched
from torchtrack.factory import build_sequences, build_tracker

# aten ops that read device memory on the host (their result is a Python value or a data-dependent shape)
SYNCING = ("_local_scalar_dense", "item", "is_nonzero", "nonzero", "count_nonzero", "masked_select", "unique")


class SyncCounter(TorchDispatchMode):
    def __init__(self) -> None:
        super().__init__()
        self.count: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name.lstrip("_") in SYNCING or name in SYNCING:
            self.count[name] += 1
        return func(*args, **(kwargs or {}))


def syncs_per_frame(grid: tuple[int, int], use_references: bool) -> tuple[list[int], int]:
    """Host syncs of each step of a 6-frame render with a ``grid`` of selection patches, and the features tracked."""
    cfg = compose_config("config", ["data.scene.frames=6", "data.scene.width=320", "data.scene.height=240",
                                    f"select.grid=[{grid[0]},{grid[1]}]", "select.roi_fraction=null"])  # fmt: skip
    tracker, counts, features = build_tracker(cfg), [], 0  # features: the most tracked in a frame
    frames = list(iterate_batched(build_sequences(cfg.data), prefetch=False))
    for frame in frames:
        with SyncCounter() as counter:
            if use_references:
                with references():
                    result = tracker.step(frame)
            else:
                result = tracker.step(frame)
        counts.append(sum(counter.count.values()))
        features = max(features, int(result.n_features.sum()))
    return counts, features


@pytest.mark.parametrize("use_references", [False, True], ids=["compiled", "references"])
def test_the_step_syncs_per_frame_not_per_feature(use_references):
    few, n_few = syncs_per_frame((8, 10), use_references)
    many, n_many = syncs_per_frame((16, 20), use_references)
    assert n_many >= 3 * n_few > 0, (n_few, n_many)
    # frame 0 selects, frame 1 adds the first keyframe to the map: one-off work; from frame 2 on the steady step
    assert max(many[2:]) <= max(few[2:]) * 1.2 + 4, (few, many)
    assert max(many) <= max(few) * 1.2 + 4, (few, many)
    if not use_references:
        assert max(few[2:]) < n_few, (few, n_few)
