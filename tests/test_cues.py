"""The image-window cues of cue version 2 (torchtrack/filter/cues.py) against their definitions on planted inputs.

Oracles: a float64 loop over the window written out here (depth step and holes); the closed-form gradient matrix
of I = alpha x + beta y^2 (Scharr is exact on quadratics: gx = alpha, gy = 2 beta y, so over a window of half
width r at row y0: mean gy = 2 beta y0, mean gy^2 = 4 beta^2 (y0^2 + r (r + 1) / 3)); a ramp has a zero eigenvalue.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from torchtrack.filter.cues import DEPTH_WINDOW, depth_window_cues, min_eigenvalue, window_cues


def loop_depth_cues(depth: np.ndarray, u: float, v: float) -> tuple[float, float]:
    H, W = depth.shape
    r, cu, cv = DEPTH_WINDOW // 2, int(round(u)), int(round(v))
    vals = [depth[y, x] if 0 <= y < H and 0 <= x < W else 0.0
            for y in range(cv - r, cv + r + 1) for x in range(cu - r, cu + r + 1)]  # fmt: skip
    ok = [z for z in vals if z > 0]
    return (max(ok) - min(ok) if ok else 0.0), 1.0 - len(ok) / len(vals)


def test_depth_step_and_holes_follow_the_window_definition():
    g = torch.Generator().manual_seed(0)
    depth = 1.0 + 0.01 * torch.rand(1, 1, 30, 40, generator=g, dtype=torch.float64)
    depth[..., :, 20:] += 0.7  # a step edge at x = 19.5
    depth[torch.rand(depth.shape, generator=g) < 0.2] = 0.0  # holes
    pts = torch.tensor([[[5.0, 5.0], [19.4, 10.0], [20.6, 12.2], [0.0, 0.0], [39.0, 29.0], [-3.0, 4.0], [7.5, 2.5]]],
                       dtype=torch.float64)  # fmt: skip
    step, holes = depth_window_cues(depth, pts)
    for n, (u, v) in enumerate(pts[0].tolist()):
        s, h = loop_depth_cues(depth[0, 0].numpy(), u, v)
        assert step[0, n].item() == s and holes[0, n].item() == h, (u, v)
    assert step[0, 1] > 0.69 and step[0, 0] < 0.011  # across the edge / on the plane


def test_depth_cues_without_depth_and_outside():
    depth = torch.zeros(2, 1, 10, 10)
    depth[1] = 2.0
    pts = torch.tensor([[[5.0, 5.0]], [[0.0, 0.0]]])
    step, holes = depth_window_cues(depth, pts)
    assert step.tolist() == [[0.0], [0.0]] and holes[0, 0] == 1.0
    assert math.isclose(holes[1, 0].item(), 16 / 25, rel_tol=1e-6)  # a corner sees 3 x 3 of its 5 x 5 window


def test_min_eigenvalue_closed_form_on_a_quadratic():
    alpha, beta, w = 0.01, 0.0005, 21
    y, x = torch.meshgrid(torch.arange(80.0, dtype=torch.float64), torch.arange(90.0, dtype=torch.float64),
                          indexing="ij")  # fmt: skip
    gray = (alpha * x + beta * y**2)[None, None]
    pts = torch.tensor([[[40.0, 30.0], [45.2, 41.7], [50.0, 55.0]]], dtype=torch.float64)
    got = min_eigenvalue(gray, pts, w)
    r = w // 2
    for n, (_, v) in enumerate(pts[0].tolist()):
        y0 = round(v)
        a, b, c = alpha**2, alpha * 2 * beta * y0, 4 * beta**2 * (y0**2 + r * (r + 1) / 3)
        lam = (a + c) / 2 - math.sqrt(((a - c) / 2) ** 2 + b**2)
        assert math.isclose(got[0, n].item(), lam, rel_tol=1e-9), (n, got[0, n].item(), lam)
    ramp = (alpha * x + 3 * alpha * y)[None, None]
    assert min_eigenvalue(ramp, pts, w).abs().max() < 1e-15  # rank one: an aperture problem


def test_min_eigenvalue_against_a_loop_with_zeros_outside():
    g = torch.Generator().manual_seed(1)
    gray = torch.rand(2, 1, 20, 24, generator=g, dtype=torch.float64)
    pts = torch.tensor([[[3.0, 2.0], [10.4, 10.6]], [[22.0, 18.0], [12.0, 0.0]]], dtype=torch.float64)
    w = 7
    k = np.array([[-3, 0, 3], [-10, 0, 10], [-3, 0, 3]], dtype=np.float64) / 32
    got = min_eigenvalue(gray, pts, w)
    for b in range(2):
        img = np.pad(gray[b, 0].numpy(), w)  # zeros outside
        for n, (u, v) in enumerate(pts[b].tolist()):
            cu, cv, G = round(u) + w, round(v) + w, np.zeros((2, 2))
            for yy in range(cv - w // 2, cv + w // 2 + 1):
                for xx in range(cu - w // 2, cu + w // 2 + 1):
                    patch = img[yy - 1 : yy + 2, xx - 1 : xx + 2]
                    gv = np.array([(patch * k).sum(), (patch * k.T).sum()])
                    G += np.outer(gv, gv) / w**2
            assert math.isclose(got[b, n].item(), np.linalg.eigvalsh(G)[0], rel_tol=1e-9, abs_tol=1e-15)


def test_window_cues_are_stack_cues_keywords():
    depth, gray = torch.ones(1, 1, 12, 12), torch.zeros(1, 1, 12, 12)
    pts = torch.tensor([[[6.0, 6.0]]])
    out = window_cues(depth, pts, gray, pts, 5)
    assert set(out) == {"depth_step", "depth_holes", "lk_min_eig"} and all(v.shape == (1, 1) for v in out.values())
