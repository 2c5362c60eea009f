"""Per-frame preparation (torchtrack.frontend): the occlusion-boundary mask of the selection, preparing ahead in a
thread."""

from __future__ import annotations

import threading

import pytest
import torch
import torch.nn.functional as F

from torchtrack.data.frame import FrameBatch
from torchtrack.frontend import FrontEnd, PreparedFrame, _window_max, smooth_depth_mask


@pytest.mark.parametrize("shape", [(2, 1, 7, 9), (1, 1, 1, 5), (1, 1, 3, 3), (3, 1, 40, 33)])
@pytest.mark.parametrize("radius", [1, 2, 3])
def test_window_max_equals_max_pool(shape, radius):
    x = torch.randn(shape, generator=torch.Generator().manual_seed(0))
    assert torch.equal(_window_max(x, radius), F.max_pool2d(x, 2 * radius + 1, 1, radius))


def test_smooth_depth_mask_against_max_pool_oracle():
    """The definition: no hole in the 5x5 window and max - min of its depth within 3% of the pixel's depth."""
    g = torch.Generator().manual_seed(1)
    depth = 1.0 + 0.01 * torch.rand(2, 1, 48, 64, generator=g)
    depth[:, :, 20:30, 30:] += 0.5  # an occlusion boundary
    depth[torch.rand(depth.shape, generator=g) < 0.02] = 0.0  # holes
    hi = F.max_pool2d(depth, 5, 1, 2)
    lo = -F.max_pool2d(torch.where(depth > 0, -depth, -1e9), 5, 1, 2)
    holes = F.max_pool2d((depth <= 0).float(), 5, 1, 2) > 0
    expected = ~holes & (hi - lo <= 0.03 * depth)
    mask = smooth_depth_mask(depth, 0.03)
    assert mask.shape == depth.shape and mask.dtype == torch.bool
    assert torch.equal(mask, expected)
    assert not mask[:, :, 18:32, 28:32].any() and mask[:, :, 24, 40:].float().mean() > 0.5


def _frames(n: int, H: int = 48, W: int = 64) -> list[FrameBatch]:
    """n FrameBatches (B=2) of random colour and a smooth bowl of depth (a defined SIM)."""
    g = torch.Generator().manual_seed(n)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    bowl = 1.0 + 1e-4 * ((xx - W / 2) ** 2 + (yy - H / 2) ** 2)
    K = torch.tensor([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]]).expand(2, 3, 3)
    return [
        FrameBatch(rgb=torch.rand(2, 3, H, W, generator=g), depth=(bowl + 0.01 * t).expand(2, 1, H, W).clone(), K=K,
                   K_depth=K, T_color_depth=torch.eye(4).expand(2, 4, 4), timestamp=torch.full((2,), t / 30.0,
                   dtype=torch.float64), T_world_color_gt=torch.eye(4, dtype=torch.float64).expand(2, 4, 4),
                   gt_valid=torch.ones(2, dtype=torch.bool), active=torch.ones(2, dtype=torch.bool),
                   index=torch.full((2,), t))
        for t in range(n)
    ]  # fmt: skip


def _same(a: PreparedFrame, b: PreparedFrame) -> bool:
    pairs = [
        (a.gray, b.gray),
        (a.depth, b.depth),
        (a.flow.pyramid.flat, b.flow.pyramid.flat),
        *zip(a.sim, b.sim, strict=True),
    ]
    return all(torch.equal(x, y) for x, y in pairs)


@pytest.mark.parametrize("ahead", [True, False])
def test_prepared_ahead_yields_the_frames_prepared_as_now(ahead):
    """The frames come through in order, and the front end returns for each what preparing it now gives (made in the
    front end's thread when ``ahead``), in the caller's inference mode."""
    frames, front = _frames(5), FrontEnd(levels=2, ahead=ahead)
    threads = []
    prepare = front.prepare
    front.prepare = lambda f: threads.append(threading.current_thread().name) or prepare(f)
    with torch.inference_mode():
        got = [(f, front(f)) for f in front.prepared_ahead(iter(frames))]
    assert [f for f, _ in got] == frames
    assert all(_same(p, prepare(f)) and p.sim.si.is_inference() for f, p in got)
    assert threads == (["torchtrack-frontend"] * 5 if ahead else ["MainThread"] * 5)
    assert not any(t.name == "torchtrack-frontend" for t in threading.enumerate())


def test_prepared_ahead_errors_arrive_at_their_frame():
    """A preparation error is raised when the front end is called on that frame (the tracker's step fails, as without
    the thread); an error of the frame source is raised by the iteration after the frames before it; stopping early
    ends the thread."""
    frames, front = _frames(4), FrontEnd(levels=2)
    frames[2].depth = torch.zeros(2, 1, 3)  # not (B, 1, H, W): its preparation fails

    def source():
        yield from frames
        raise RuntimeError("decoder gone")

    it, seen = front.prepared_ahead(source()), []
    for f in it:
        if f is frames[2]:
            with pytest.raises(ValueError):
                front(f)
        else:
            seen.append(front(f))
        if len(seen) == 3:
            break
    with pytest.raises(RuntimeError, match="decoder gone"):
        list(front.prepared_ahead(source()))
    it = front.prepared_ahead(iter(frames))
    next(it)
    it.close()
    assert len(seen) == 3 and not any(t.name == "torchtrack-frontend" for t in threading.enumerate())


def test_the_front_ends_sim_is_compute_sims(kernels):
    """The front end's SIM is :func:`compute_sim`'s on the same depth with the same arguments (the same computation
    run twice: exactly), on the compiled operator and on its reference."""
    from test_shape_index import K1, SURFACES, as_depth

    from torchtrack.image.shape_index import compute_sim

    (frame,) = _frames(1, 480, 640)
    frame.depth = as_depth(SURFACES["sphere (convex cap)"][0]()).expand(2, 1, 480, 640)
    frame.K = frame.K_depth = K1().expand(2, 3, 3)
    kw = dict(smooth_sigma=3.0)
    sim = FrontEnd(levels=2, sim_kwargs=kw).prepare(frame).sim
    assert sim.valid.sum() > 10000 and torch.equal(sim.si, compute_sim(frame.depth, frame.K, **kw).si)
