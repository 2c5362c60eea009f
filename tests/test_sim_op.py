"""The compiled SIM operator (torch.ops.torchtrack.shape_index_map) against shape_index.py's reference (kornia's smoothing).

Oracles: analytic surfaces of known shape index (sphere, bowl, cylinder, pipe: test_shape_index.py's scenes and bound);
the reference (``compute_sim_reference``) on real depth frames, within tests/tolerances.py's SIM_OP_*;
batched equals one at a time; the fallback; torch.library.opcheck for the schema and the fake kernel.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from reference import requires_ops
from test_shape_index import K1, SURFACES, TOL, as_depth, interior
from tolerances import SIM_OP_FLIPS, SIM_OP_QUANTA, SIM_OP_SI, SIM_OP_SI_MEAN

from torchtrack import ops
from torchtrack.image.shape_index import compute_sim, compute_sim_reference

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
pytestmark = requires_ops


def assert_agree(ref, op):
    n = ref.valid.numel()
    assert (ref.valid != op.valid).sum() <= SIM_OP_FLIPS * n
    both = ref.valid & op.valid
    torch.testing.assert_close(op.si[both], ref.si[both], atol=SIM_OP_SI, rtol=0)
    assert float((op.si[both] - ref.si[both]).abs().mean()) <= SIM_OP_SI_MEAN
    assert ((op.image - ref.image).abs() > 1e-6).sum() <= SIM_OP_QUANTA * n
    assert ((op.image - ref.image)[both].abs() <= SIM_OP_SI + 1.0 / 255 + 1e-6).all()  # round(255 SI) / 255


@pytest.mark.parametrize("decimate", [1, 2])
@pytest.mark.parametrize("name", list(SURFACES))
def test_analytic_surfaces_known_answer(name, decimate):
    z, expected = SURFACES[name]
    z = z()
    op = compute_sim(as_depth(z), K1(), decimate=decimate)
    core = interior(z)
    assert op.valid[0, 0][core].float().mean() > 0.95
    assert float((op.si[0, 0] - expected).abs()[op.valid[0, 0]].max()) <= TOL
    assert_agree(compute_sim_reference(as_depth(z), K1(), decimate=decimate), op)


@pytest.mark.equivalence
@pytest.mark.skipif(not DATA.exists(), reason="needs ../shared/data")
@pytest.mark.parametrize("seq", ["sun3d_fragment1", "visp_rbt_sequence"])
def test_real_depth_agrees_with_reference_batched(seq):
    """Two depth frames as one batch: each equals the reference; other parameters (no smoothing, decimate 3) too."""
    folder = DATA / seq
    if not folder.exists():
        pytest.skip(f"{seq} not in ../shared/data")
    fx, fy, cx, cy, scale = map(float, [ln for ln in (folder / "intrinsics.txt").read_text().splitlines()
                                        if not ln.startswith("#")][0].split())  # fmt: skip
    names = [ln.split()[1] for ln in (folder / "depth.txt").read_text().splitlines() if ln.strip() and ln[0] != "#"]
    depth = torch.stack([torch.from_numpy(cv2.imread(str(folder / n), cv2.IMREAD_UNCHANGED).astype(np.float32) / scale)
                         for n in names[:2]])[:, None]  # fmt: skip
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]).expand(2, 3, 3)
    for kw in (dict(), dict(smooth_sigma=0.0, decimate=3, max_incidence=70.0)):
        ref, op = compute_sim_reference(depth, K, **kw), compute_sim(depth, K, **kw)
        assert ref.valid.sum() > 10000
        assert_agree(ref, op)
        one = compute_sim(depth[1:], K[1:], **kw)
        assert torch.equal(one.si[0], op.si[1]) and torch.equal(one.valid[0], op.valid[1])  # per image: the same code


def test_fallback_and_opcheck(monkeypatch):
    z = as_depth(SURFACES["sphere (convex cap)"][0]())
    ref = compute_sim_reference(z, K1())
    monkeypatch.setenv("TORCHTRACK_NO_BUILD", "1")
    monkeypatch.setattr(ops, "_state", {})
    with pytest.warns(RuntimeWarning, match="unavailable"):
        out = compute_sim(z, K1())
    assert torch.equal(out.si, ref.si) and torch.equal(out.image, ref.image)
    monkeypatch.undo()
    args = (z[..., :48, :64].contiguous(), K1(), 4.0, 5.0, 0.05, 0.9999, 60.0, 2, 0.5)
    torch.library.opcheck(torch.ops.torchtrack.shape_index_map.default, args)
    with pytest.raises(RuntimeError, match="float32"):
        torch.ops.torchtrack.shape_index_map(z.double(), K1(), 4.0, 5.0, 0.05, 0.9999, 60.0, 2, 0.5)
