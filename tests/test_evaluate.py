"""experiments/eval/evaluate.py and experiments/eval/peers.py: the peers against exact synthetic ground truth, the table's
numbers against the run folders, the cache, the variants and the results section."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence
from torchtrack.data.tum import TumSequence
from torchtrack.data.tum_io import read_tum_trajectory
from torchtrack.metrics import shared_error, trajectory_metrics

pytest.importorskip("open3d")
import evaluate  # noqa: E402  (experiments/eval/, on pytest's pythonpath)
import peers  # noqa: E402

pytestmark = pytest.mark.slow  # the evaluation scripts end to end, peers included

FAST = "o3d_t_p2plane,cv2_rgbd"


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    cfg = SyntheticConfig(width=320, height=240, frames=6, seed=3, noise="none")
    return ensure_sequence(cfg, tmp_path_factory.mktemp("data"))


@pytest.mark.parametrize("name", list(peers.PEERS))
def test_every_peer_follows_the_true_motion(seq, name):
    """On a noise-free rendered sequence every peer's per-frame motion error (RPE) is well under the motion itself
    (the RPE of a camera that never moves); a peer chained in the wrong direction would score about twice it.
    The geometric dense ones are exact to a millimetre."""
    s = TumSequence(seq)
    T, fps = peers.PEERS[name](s, progress=False)
    assert T.shape == (len(s), 4, 4) and fps > 0
    np.testing.assert_allclose(T[0], s.groundtruth[0], atol=1e-12)
    frozen = np.repeat(s.groundtruth[:1], len(s), 0)
    rpe = trajectory_metrics(s.timestamps, T, s.groundtruth)["rpe_trans_m"]
    assert rpe < 0.5 * trajectory_metrics(s.timestamps, frozen, s.groundtruth)["rpe_trans_m"]
    if name in FAST.split(","):
        assert np.linalg.norm(T[:, :3, 3] - s.groundtruth[:, :3, 3], axis=1).max() < 1e-3


def test_end_to_end_best_peer_ratio_cache_and_shared_error(seq, tmp_path):
    """Ours and two peers: the best is the smaller ATE of the two metrics.json, the ratio is ours over it, the
    shared error is recomputed from the trajectories, and a second run takes the peers from the cache."""
    out = tmp_path / "eval"
    argv = ["--roots", str(seq), "--out", str(out), "--no-plots", "--peers", FAST]
    assert evaluate.main(argv) == 0
    (row,) = json.loads((out / "evaluation.json").read_text())["rows"]
    ours = json.loads((out / "ours" / seq.name / "metrics.json").read_text())
    ates = {
        p: json.loads((out / "peers" / p / seq.name / "metrics.json").read_text())["ate_rmse_m"]
        for p in FAST.split(",")
    }
    best = min(ates, key=ates.get)
    assert row["best"] == best and row["ratio"]["ate_rmse_m"] == pytest.approx(ours["ate_rmse_m"] / ates[best])
    trajectories = [
        read_tum_trajectory(out / d / seq.name / "trajectory.txt").T_world_cam for d in ("ours", f"peers/{best}")
    ]
    expected = shared_error(*map(torch.as_tensor, trajectories), torch.as_tensor(TumSequence(seq).groundtruth))
    assert row["shared"]["ate_m"] == pytest.approx(expected.ate_m, rel=1e-12)
    text = (out / "evaluation.md").read_text()
    assert seq.name in text and "What ours and the best peer have in common" in text
    assert evaluate.main(argv) == 0
    (again,) = json.loads((out / "evaluation.json").read_text())["rows"]
    assert all(again["peers"][p]["cached"] for p in FAST.split(","))


def test_variants_ablation_column_and_results_section(seq, tmp_path):
    """--variants skip2 adds the row of every other frame; --compare shows another run's ours; --results replaces
    only this script's section."""
    first = tmp_path / "first"
    base = ["--roots", str(seq), "--no-plots", "--peers", "cv2_rgbd", "--cache", str(tmp_path / "cache")]
    assert evaluate.main([*base, "--out", str(first), "--variants", "skip2"]) == 0
    rows = json.loads((first / "evaluation.json").read_text())["rows"]
    assert [(r["variant"], r["frames"]) for r in rows] == [("real", 6), ("skip2", 3)]
    results = tmp_path / "RESULTS.md"
    results.write_text("# Results\n\n## Other\n\nkeep me\n")
    argv = [*base, "--out", str(tmp_path / "second"), "--variants", "skip2", "--results", str(results)]
    assert evaluate.main([*argv, f"--compare=before={first / 'evaluation.json'}"]) == 0
    text = results.read_text()
    assert "keep me" in text and text.count(evaluate.HEADING) == 1 and "before ATE" in text
    ate = json.loads((first / "evaluation.json").read_text())["rows"][1]["ours"]["ate_rmse_m"]
    assert f"{ate * 1e3:.1f} / " in text.split("| skip2 |", 1)[1].splitlines()[0]
    rendered = tmp_path / "R.md"
    runs = [str(d / "evaluation.json") for d in (first, tmp_path / "second")]
    assert evaluate.main(["--render", *runs, "--results", str(rendered)]) == 0
    assert rendered.read_text().count("| skip2 |") == 2 and "--variants skip2" in rendered.read_text()


def test_unknown_peer_or_variant_is_refused():
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--peers", "nope"])
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--variants", "skip9"])
    with pytest.raises(SystemExit):
        evaluate.parse_args(["--seeds", "1,x"])


def test_seeds_median_over_the_plain_and_jittered_runs(seq, tmp_path):
    """--seeds 1,2 runs ours on two jitter variants too: the row's median and range are those of the three
    metrics.json files, the jittered inputs differ from the plain ones, and the ratio uses the median."""
    out = tmp_path / "eval"
    argv = ["--roots", str(seq), "--out", str(out), "--no-plots", "--peers", "cv2_rgbd", "--cache", str(tmp_path / "c")]
    assert evaluate.main([*argv, "--seeds", "1,2"]) == 0
    (row,) = json.loads((out / "evaluation.json").read_text())["rows"]
    folders = [out / "ours" / seq.name] + sorted((out / "ours_jitter").glob("s*/*"))
    assert [f.parent.name for f in folders[1:]] == ["s1", "s2"]
    ates = [json.loads((f / "metrics.json").read_text())["ate_rmse_m"] for f in folders]
    assert row["ours_median"]["runs"] == 3
    assert row["ours_median"]["ate_rmse_m"] == pytest.approx(float(np.median(ates)), rel=1e-12)
    assert row["ours_median"]["ate_rmse_m_range"] == pytest.approx([min(ates), max(ates)], rel=1e-12)
    peer = json.loads((out / "peers" / "cv2_rgbd" / seq.name / "metrics.json").read_text())["ate_rmse_m"]
    assert row["ratio"]["ate_rmse_m"] == pytest.approx(np.median(ates) / peer, rel=1e-12)
    jitter = sorted((tmp_path / "c").glob("*jitter-s1*"))
    assert jitter, "the jitter variant is built in the cache"
    import cv2

    plain, noisy = (cv2.imread(str(TumSequence(f).rgb_paths[0])) for f in (seq, jitter[0]))
    assert plain.shape == noisy.shape and 0 < np.abs(plain.astype(int) - noisy).max() <= 3  # the same frame, noisy
    assert "ours median ATE [range]" in (out / "evaluation.md").read_text()
