"""experiments/eval/eval_weighting.py end to end on a tiny rendered sequence: the table holds the numbers of the runs'
metrics.json (read back here independently), the RESULTS section is replaced and nothing else, a missing learned
model is said and left out."""

from __future__ import annotations

import json
from pathlib import Path

import eval_weighting as ew  # experiments/, on pytest's pythonpath
import pytest

from torchtrack.data.synthetic import SyntheticConfig, ensure_sequence

pytestmark = pytest.mark.slow  # the weighting evaluation script end to end

OTHER = "# Results\n\nintro\n\n## Other section\n\nkeep me\n\n### sub\n\nme too\n"
TAIL = "## Generated report\n\nlast\n"


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ew")
    seq = ensure_sequence(SyntheticConfig(width=320, height=240, frames=6, seed=3, noise="none"), tmp / "data")
    results = tmp / "RESULTS.md"
    results.write_text(OTHER + f"\n{ew.HEADING}\n\nold table\n\n### old sub\n\nold\n\n" + TAIL)
    argv = ["--data", str(seq.parent), "--variants", "reversed", "--weightings", "fixed,paper", "--runs", "1"]
    argv += ["--out", str(tmp / "out"), "--cache", str(tmp / "cache")]
    assert ew.main(argv + ["--results", str(results)]) == 0
    return seq, tmp, argv, results


def metrics(tmp: Path, label: str, name: str) -> dict:
    return json.loads((tmp / "out" / label / name / "metrics.json").read_text())


def table_rows(text: str, name: str) -> dict[str, list[str]]:
    """variant -> the cells of the main table's row of sequence ``name``."""
    rows = [line.strip("|").split("|") for line in text.splitlines() if line.startswith(f"| {name} |")]
    return {cells[1].strip(): [c.strip() for c in cells] for cells in rows if len(cells) > 5}


def test_table_holds_the_numbers_of_every_runs_metrics_json(evaluated):
    seq, tmp, _, _ = evaluated
    text = (tmp / "out" / "weighting.md").read_text()
    rows = table_rows(text, seq.name)
    assert set(rows) == {"real", "reversed"}
    folders = {"real": seq.name, "reversed": f"{seq.name}-reversed"}
    for variant, cells in rows.items():
        ates = {}
        for k, label in enumerate(("fixed", "paper")):
            m = metrics(tmp, label, folders[variant])
            assert cells[2] == str(m["frames"]) == "6"
            expected = [f"{m['ate_rmse_m'] * 1e3:.2f}", f"{m['rpe_trans_m'] * 1e3:.2f}"]
            expected += [f"{m['rpe_rot_deg']:.3f}", f"{m['mean_reprojection_px']:.3f}"]
            assert cells[3 + 4 * k : 7 + 4 * k] == expected
            ates[label] = m["ate_rmse_m"]
        assert cells[11] == f"{ates['paper'] / ates['fixed']:.2f}"  # no learned model: paper / fixed
    header = next(line for line in text.splitlines() if line.startswith("| sequence |"))
    assert "fixed ATE mm" in header and "paper reproj px" in header and "ATE paper/fixed" in header
    real = {label: metrics(tmp, label, seq.name)["ate_rmse_m"] * 1e3 for label in ("fixed", "paper")}
    assert f"| real sequences | 1 | {real['fixed']:.2f} | {real['paper']:.2f} |" in text
    jitter = {label: metrics(tmp, label, f"{seq.name}-jitter-s1")["ate_rmse_m"] * 1e3 for label in real}
    for label in real:  # the spread row: mean of the unperturbed and the jittered run
        assert f"{(real[label] + jitter[label]) / 2:.2f} ± " in text
    assert "paper vs fixed (ATE): real sequences" in text


def test_results_section_is_replaced_and_the_rest_kept(evaluated):
    seq, tmp, argv, results = evaluated
    text = results.read_text()
    assert text.startswith(OTHER) and text.endswith(TAIL)
    assert text.count(ew.HEADING) == 1 and "old table" not in text and "old sub" not in text
    section = text[text.index(ew.HEADING) : text.index(TAIL)]
    assert " ".join(argv) in section and "commit " in section and seq.name in section
    assert section == ew.HEADING + "\n\n" + (tmp / "out" / "weighting.md").read_text().split("\n\n", 1)[1] + "\n"


def test_reuse_keeps_finished_runs_and_the_same_table(evaluated):
    seq, tmp, argv, _ = evaluated
    before = table_rows((tmp / "out" / "weighting.md").read_text(), seq.name)
    assert ew.main(argv + ["--reuse"]) == 0
    rows = json.loads((tmp / "out" / "weighting.json").read_text())["rows"]
    assert all(run.get("reused") for r in rows for run in r["runs"].values())
    assert table_rows((tmp / "out" / "weighting.md").read_text(), seq.name) == before


def test_missing_learned_model_is_said_and_left_out(evaluated, capsys, tmp_path):
    seq, tmp, _, _ = evaluated
    argv = ["--data", str(seq), "--variants", "none", "--weightings", "paper,learned", "--out", str(tmp_path)]
    assert ew.main(argv + ["--checkpoint", str(tmp_path / "nothing.pt"), "--max-frames", "3"]) == 0
    err = capsys.readouterr().err
    assert "missing" in err and "learned" in err
    text = (tmp_path / "weighting.md").read_text()
    assert "missing" in text and "learned ATE mm" not in text and "paper ATE mm" in text


def test_learned_checkpoint_pattern_per_sequence(tmp_path):
    m = ew.Method("loo", ["weighting=learned"], learned=True, checkpoint=str(tmp_path / "loo-{sequence}.pt"))
    assert m.checkpoint_for("sun3d") == tmp_path / "loo-sun3d.pt"
    assert ew.Method("paper", ["weighting=paper"]).checkpoint_for("x") is None
    with pytest.raises(SystemExit, match="NAME=PATH"):
        ew.resolve_methods(["paper"], None, ["nopath"])
    with pytest.raises(SystemExit, match="unknown weighting"):
        ew.resolve_methods(["papr"], None, [])


@pytest.mark.parametrize(
    "text, expected",
    [
        ("", "## Learned weighting: the evaluation table\n\nnew\n"),
        ("# R\n\nx\n", "# R\n\nx\n\n## Learned weighting: the evaluation table\n\nnew\n"),
        (
            "# R\n## Learned weighting: the evaluation table\nold\n### s\nold\n## Next\ny\n",
            "# R\n## Learned weighting: the evaluation table\n\nnew\n\n## Next\ny\n",
        ),
        (
            "a\n## Learned weighting: the evaluation table\n\nold\n",
            "a\n## Learned weighting: the evaluation table\n\nnew\n",
        ),
    ],
)
def test_replace_section(text, expected):
    assert ew.replace_section(text, ew.HEADING, "new\n") == expected


def test_target_is_the_geometric_mean_of_median_ratios():
    """Planted rows: the real row's ATE is its median over the jitter runs, the variant's its one run; the summary
    line has exp(mean log ratio) and names the rows above 1.05, marking a difference within the spread."""

    def run(x):
        return {"metrics": {"ate_rmse_m": x}}

    rows = [
        {"sequence": "a", "variant": "real", "runs": {"new": run(1.0), "paper": run(2.0)},
         "noise": {"new": [1.0, 3.0, 1.2], "paper": [2.0, 2.1, 1.9]}},  # medians 1.2 / 2.0
        {"sequence": "a", "variant": "skip3", "runs": {"new": run(3.0), "paper": run(2.0)}},
        {"sequence": "b", "variant": "real", "runs": {"new": run(1.1), "paper": run(1.0)},
         "noise": {"new": [1.1, 1.3, 0.9], "paper": [1.0, 1.2, 0.8]}},  # 1.1 / 1.0, within the spread
    ]  # fmt: skip
    assert ew.typical_ate(rows[0], "new") == 1.2 and ew.typical_ate(rows[1], "new") == 3.0
    gm = (0.6 * 1.5 * 1.1) ** (1 / 3)
    line = ew.target(rows, "new", "paper")
    assert f"geometric mean of the ATE ratio {gm:.3f} over 3 rows" in line
    assert "above 1.05: a/skip3 1.50, b/real 1.10 (within spread)" in line
