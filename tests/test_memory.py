"""Long runs hold their memory: the per-frame work leaves no tensors that only Python's cycle collector frees.

Python frees an object caught in a reference cycle only at a collection of the cycle collector, and a full collection
runs rarely in a process with many long-lived objects (Python 3.11: when the objects promoted since the last one
reach a quarter of the long-lived ones). A frame's buffers in a cycle (an LK pyramid referenced by its own sampler
cache did it) then pile up for thousands of frames: ``experiments/bench/bench_long_run.py`` measured +80 MiB over 9,000
frames before the fix. The tracker must free every frame's tensors by reference counting alone.
"""

from __future__ import annotations

import gc
import weakref

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.config import CONF_DIR
from torchtrack.data import TumSequence, iterate_batched
from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.factory import build_tracker
from torchtrack.image.lk import pyramidal_lk
from torchtrack.image.pyramid import build_pyramid


def cyclic_tensors() -> int:
    """Tensors among the objects the cycle collector finds unreachable now (they are freed)."""
    gc.set_debug(gc.DEBUG_SAVEALL)
    try:
        gc.collect()
        found = sum(isinstance(o, torch.Tensor) for o in gc.garbage)
    finally:
        gc.set_debug(0)
        gc.garbage.clear()
        gc.collect()
    return found


@pytest.mark.slow
def test_tracking_leaves_no_tensors_in_reference_cycles(tmp_path):
    cfg = SyntheticConfig(width=160, height=120, frames=40, seed=1, noise="none", trans_step_m=0.03, rot_step_deg=3.0)
    seq = TumSequence(ensure_sequence(cfg, tmp_path))
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        tracker = build_tracker(compose("config"))  # the default: landmarks, relocaliser, front end's thread
    reselected = 0
    enabled = gc.isenabled()
    try:
        with torch.inference_mode():
            for i, frame in enumerate(tracker.frontend.prepared_ahead(iterate_batched([seq]))):
                if i == 2:  # after the first frames' one-time set-up
                    cyclic_tensors()
                    gc.disable()
                reselected += int(tracker.step(frame).reselected.sum())
        assert reselected >= 2, "the sequence must exercise re-selections (new pyramids, landmark keyframes)"
        assert cyclic_tensors() == 0
    finally:
        if enabled:
            gc.enable()


def test_pyramid_freed_without_the_cycle_collector():
    """A pyramid LK has sampled (its samplers cached in ``Pyramid.samplers``) is freed as soon as it is dropped."""
    img = torch.rand(2, 1, 48, 64, generator=torch.Generator().manual_seed(0))
    prev, next = build_pyramid(img[:1], 3), build_pyramid(img[1:], 3)
    pyramidal_lk(prev, next, torch.full((1, 5, 2), 24.0))
    assert prev.samplers and next.samplers
    refs = [weakref.ref(prev), weakref.ref(next), *(weakref.ref(s) for s in prev.samplers.values())]
    enabled = gc.isenabled()
    gc.disable()
    try:
        del prev, next
        assert all(r() is None for r in refs)
    finally:
        if enabled:
            gc.enable()
