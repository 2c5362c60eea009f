"""Landmark identities across keyframes (torchtrack/pipeline/landmark_window.py) on small exact cases."""

from __future__ import annotations

import torch

from torchtrack.pipeline.landmark_window import Identities

F64 = torch.float64


def test_survivors_and_reacquired_keep_their_identities_new_features_get_new_ones():
    ids = Identities(B=1, S=3, P=4, device="cpu")
    eye = torch.eye(4, dtype=F64)[None]
    world0 = torch.tensor([[[0.0, 0, 2], [1, 0, 2], [0, 1, 2], [5, 5, 5]]], dtype=F64)
    px0 = torch.tensor([[[10.0, 10], [20, 10], [10, 20], [0, 0]]])
    ok0 = torch.tensor([[True, True, True, False]])
    ids.assign(torch.tensor([0]), torch.tensor([0]), px0, ok0, world0, eye)  # first keyframe: three new landmarks
    assert ids.ident[0, 0].tolist() == [0, 1, 2, -1] and ids.has_xyz[0, 0].tolist() == [True, True, True, False]
    # next model: survivors are landmarks 1 and 2 (same world positions, to float32), one landmark of slot 0 re-acquired
    tracked = torch.tensor([[[30.0, 30], [40, 40], [50, 50]]])
    tracked_world = torch.tensor([[[1.0, 0, 2.0000005], [0, 1, 2], [9, 9, 9]]], dtype=F64)
    sid = ids.note(tracked, tracked_world, torch.tensor([[True, True, True]]), world0[0:1], ids.ident[:, 0],
                   ok0, torch.tensor([[[60.0, 60]]]), torch.tensor([[0]]), torch.tensor([[True]]))  # fmt: skip
    assert sid.tolist() == [[1, 2, -1]]  # the third survivor is nowhere in the keyframe
    px1 = torch.tensor([[[40.0, 40], [60, 60], [30, 30], [70, 70]]])  # the merge reorders: pixels identify
    ids.assign(torch.tensor([0]), torch.tensor([1]), px1, torch.ones(1, 4, dtype=torch.bool),
               torch.zeros(1, 4, 3, dtype=F64), eye)  # fmt: skip
    assert ids.ident[0, 1].tolist() == [2, 0, 1, 3]  # survivor 2, re-acquired 0, survivor 1, a new landmark 3
    assert ids.has_xyz[0, 1].tolist() == [False, False, False, True]  # only the new one was measured here
    assert ids.pending is None and int(ids.next_id[0]) == 4
