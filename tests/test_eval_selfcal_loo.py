"""experiments/eval/eval_selfcal_loo.py's pieces: the unlabelled copy of a sequence folder (every entry linked but the
ground truth) and the held-out NLL per window, whose pooled value must equal training's own validation NLL
(torchtrack.learn.train.evaluate) on the same windows."""

from __future__ import annotations

import eval_selfcal_loo as loo  # experiments/, on pytest's pythonpath
import pytest
import torch

from torchtrack.filter import FixedWeighting, PaperWeighting
from torchtrack.filter.fusion import FusionEKF
from torchtrack.learn.oracle import oracle_windows
from torchtrack.learn.train import TrainConfig, evaluate


def test_unlabelled_copy_links_everything_but_the_ground_truth(tmp_path):
    src = tmp_path / "seq"
    (src / "rgb").mkdir(parents=True)
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt"):
        (src / name).write_text(name)
    dst = loo.unlabelled_copy(src, tmp_path / "unlabelled")
    assert sorted(p.name for p in dst.iterdir()) == ["depth.txt", "intrinsics.txt", "rgb", "rgb.txt"]
    assert all(p.is_symlink() and p.resolve() == (src / p.name).resolve() for p in dst.iterdir())
    assert loo.unlabelled_copy(src, tmp_path / "unlabelled") == dst  # again: kept


@pytest.mark.parametrize("weighting", ["fixed", "paper"])
def test_window_nll_pools_to_the_validation_nll(weighting):
    oracle = oracle_windows(B=10, T=4, N=20, seed=3)
    ekf = FusionEKF(jacobian="analytic")
    w = FixedWeighting() if weighting == "fixed" else PaperWeighting()
    tc = TrainConfig(window=4, batch=4, loss="nll", gate=0.999, refit=0.999)
    sums, counts = loo.window_nll(ekf, w, oracle.windows, tc)
    assert sums.shape == counts.shape == (10,) and bool((counts > 0).all())
    assert float(sums.sum() / counts.sum()) == pytest.approx(evaluate(ekf, w, oracle.windows, tc)["nll"], rel=1e-9)
    one = loo.window_nll(ekf, w, loo.select_windows(oracle.windows, torch.tensor([7])), tc)
    assert float(one[0][0]) == pytest.approx(float(sums[7]), rel=1e-9) and float(one[1][0]) == float(counts[7])
