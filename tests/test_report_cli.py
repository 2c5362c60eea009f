"""``torchtrack-report``: a fake multirun with numbers written here (the oracle) tabulated into its medians, as
markdown and CSV and bars; the settings told apart from the sequence and the seeds; one-line errors; and a real
two-setting multirun of the CLI."""

from __future__ import annotations

import csv
import io
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from torchtrack import report

SETTINGS = ("1", "2")  # filter.iterations
SEQUENCES = ("desk", "room")
SEEDS = (0, 1, 2)  # three, so that a median is not a mean


def ate_m(it: str, seq: str, seed: int) -> float:
    """Run (setting, sequence, seed) -> ATE RMSE (m); per cell the seeds give x1, x2, x6 (median x2, mean x3)."""
    return 1e-3 * int(it) * (1 + 10 * SEQUENCES.index(seq)) * (1, 2, 6)[seed]


def fps(it: str, seq: str, seed: int) -> float:
    return 10.0 * (seed + 1) + int(it)


def write_job(job: Path, overrides: list[str], metrics: dict) -> None:
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in overrides))
    (job / metrics["sequence"]).mkdir()
    (job / metrics["sequence"] / "metrics.json").write_text(json.dumps(metrics))


def fake_multirun(root: Path, seed_key: str = "data.scene.seed") -> Path:
    """2 settings x 2 sequences x 3 seeds, one Hydra job folder each (as ``torchtrack -m`` lays them out)."""
    n = 0
    for it in SETTINGS:
        for seq in SEQUENCES:
            for seed in SEEDS:
                overrides = [f"filter.iterations={it}", f"data.root=/data/{seq}", f"{seed_key}={seed}", "plots=false"]
                metrics = {"sequence": seq, "complete": True, "frames": 5, "ate_rmse_m": ate_m(it, seq, seed),
                           "rpe_trans_m": 1e-3 * seed, "rpe_rot_deg": 0.1, "fps": fps(it, seq, seed)}  # fmt: skip
                write_job(root / str(n), overrides, metrics)
                n += 1
    (root / "multirun.yaml").write_text("hydra: {}\n")
    return root


def test_the_table_holds_the_medians_of_each_setting_and_sequence(tmp_path, capsys):
    root = fake_multirun(tmp_path / "mr")
    assert report.main([str(root), "--csv", str(tmp_path / "t.csv")]) == 0
    md = capsys.readouterr().out
    lines = md.splitlines()
    assert lines[0] == (
        "| filter.iterations | sequence | runs | frames | ATE RMSE (mm) | RPE trans (mm/frame) | RPE rot (deg/frame) | fps |"
    )
    rows = [ln for ln in lines[2:] if ln.startswith("| ")]
    assert len(rows) == len(SETTINGS) * len(SEQUENCES)
    for it in SETTINGS:
        for seq in SEQUENCES:
            ate = 1e3 * statistics.median(ate_m(it, seq, s) for s in SEEDS)
            f = statistics.median(fps(it, seq, s) for s in SEEDS)
            assert f"| {it} | {seq} | 3 | 5 | {ate:.2f} | 1.00 | 0.100 | {f:.1f} |" in rows
    assert "`data.scene.seed`" in md and "Following the sequence: `data.root`" in md
    assert "Every run: `plots=false`" in md
    table = list(csv.DictReader(io.StringIO((tmp_path / "t.csv").read_text())))
    assert [(r["filter.iterations"], r["sequence"]) for r in table] == [(i, s) for i in SETTINGS for s in SEQUENCES]
    for r in table:
        it, seq = r["filter.iterations"], r["sequence"]
        assert float(r["ate_rmse_mm"]) == pytest.approx(1e3 * statistics.median(ate_m(it, seq, s) for s in SEEDS))
        assert float(r["fps"]) == pytest.approx(statistics.median(fps(it, seq, s) for s in SEEDS))
        assert r["runs"] == "3" and r["frames"] == "5" and float(r["rpe_trans_mm"]) == pytest.approx(1.0)


def test_the_plot_draws_one_bar_per_setting_and_sequence_at_the_median(tmp_path, monkeypatch):
    figures = []
    import torchtrack.viz.plots as plots

    monkeypatch.setattr(plots, "save_atomic", lambda fig, path, dpi=100: figures.append(fig) or Path(path))
    table = report.tabulate(report.load_runs(fake_multirun(tmp_path / "mr")))
    report.plot_ate(table, tmp_path / "ate.png")
    ax = figures[0].axes[0]
    heights = sorted(round(p.get_height(), 9) for p in ax.patches)
    want = sorted(round(1e3 * statistics.median(ate_m(i, s, k) for k in SEEDS), 9) for i in SETTINGS for s in SEQUENCES)
    assert heights == want
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["filter.iterations=1", "filter.iterations=2"]


def test_the_written_plot_is_a_png(tmp_path):
    root = fake_multirun(tmp_path / "mr")
    assert report.main([str(root), "--plot", str(tmp_path / "ate.png")]) == 0
    assert (tmp_path / "ate.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_seed_key_written_in_the_sequence_name_joins_the_seeds(tmp_path):
    for seed in (0, 1, 2):
        name = f"synthetic-scene-seed{seed}-kinect"
        metrics = {"sequence": name, "frames": 4, "ate_rmse_m": 0.001 * (seed + 1), "fps": 10.0}
        write_job(tmp_path / str(seed), [f"data.scene.seed={seed}"], metrics)
    table = report.tabulate(report.load_runs(tmp_path))
    assert [(r.sequence, len(r.runs), r.values["ate_rmse_mm"]) for r in table.rows] == [
        ("synthetic-scene-seed*-kinect", 3, pytest.approx(2.0))
    ]
    assert table.keys == [] and table.seed_keys == ["data.scene.seed"]


def test_another_seed_key_and_a_key_that_is_not_one(tmp_path, capsys):
    root = fake_multirun(tmp_path / "mr", seed_key="+rep")
    assert report.main([str(root), "--seed-key", "rep"]) == 0
    assert len([ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| 1 ")]) == 2
    table = report.tabulate(report.load_runs(root), seed_keys=("data.scene.seed",))  # rep is then a setting
    assert table.keys == ["filter.iterations", "rep"] and len(table.rows) == 2 * 2 * 3


def test_incomplete_runs_are_left_out_and_named(tmp_path, capsys):
    write_job(tmp_path / "0", ["tracker=icp"], {"sequence": "a", "frames": 3, "ate_rmse_m": 0.002, "fps": 5.0})
    write_job(tmp_path / "1", ["tracker=horn"], {"sequence": "a", "frames": 3, "ate_rmse_m": 0.004, "fps": 5.0})
    bad = {"sequence": "a", "complete": False, "error": "tracking failed at step 2", "frames": 2, "ate_rmse_m": 9.0}
    write_job(tmp_path / "2", ["tracker=horn"], bad)
    assert report.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| horn | a | 1 | 3 | 4.00 |" in out and "| icp | a | 1 | 3 | 2.00 |" in out
    assert "Left out, incomplete:" in out and "tracking failed at step 2" in out


def test_a_single_run_without_a_job_folder_is_one_row(tmp_path, capsys):
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "metrics.json").write_text(json.dumps({"sequence": "seq", "frames": 2, "fps": 3.0}))
    assert report.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| seq | 1 | 2 | – | – | – | 3.0 |" in out and "No override differs" in out


@pytest.mark.parametrize("case", ["missing", "empty", "bad_json", "bad_overrides"])
def test_errors_are_one_line(tmp_path, capsys, case):
    folder = tmp_path / "runs"
    if case != "missing":
        folder.mkdir()
    if case == "bad_json":
        (folder / "s").mkdir()
        (folder / "s" / "metrics.json").write_text("{not json")
    if case == "bad_overrides":
        write_job(folder / "0", ["a=1"], {"sequence": "s", "frames": 1})
        (folder / "0" / ".hydra" / "overrides.yaml").write_text("- [unclosed\n")
    assert report.main([str(folder), "--csv", str(tmp_path / "t.csv")]) == 2
    captured = capsys.readouterr()
    assert (
        captured.out == "" and captured.err.count("\n") == 1 and captured.err.startswith("torchtrack-report: error: ")
    )
    assert {"missing": "is not a folder", "empty": "no metrics.json below", "bad_json": "metrics.json",
            "bad_overrides": "overrides.yaml"}[case] in captured.err  # fmt: skip
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.slow
def test_a_real_two_setting_multirun_gives_two_rows(tmp_path, capsys):
    """The CLI's multirun over two trackers on a tiny synthetic scene: one table, one row per tracker, holding the
    numbers of the runs' own metrics.json."""
    sweep = tmp_path / "mr"
    cmd = [sys.executable, "-m", "torchtrack.cli", "-m", "tracker=fusion_ekf,horn", "data.scene.frames=4",
           "data.scene.width=160", "data.scene.height=120", "plots=false", f"hydra.sweep.dir={sweep}"]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # the usual cache: a fresh one would compile the LK operator
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert report.main([str(sweep), "--csv", str(tmp_path / "t.csv")]) == 0
    rows = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("| ") and "---" not in ln]
    assert len(rows) == 3 and rows[0].startswith("| tracker | sequence |")
    table = {r["tracker"]: r for r in csv.DictReader(io.StringIO((tmp_path / "t.csv").read_text()))}
    assert set(table) == {"fusion_ekf", "horn"}
    for path in sweep.glob("*/*/metrics.json"):
        tracker = next(o for o in (path.parents[1] / ".hydra" / "overrides.yaml").read_text().split() if "=" in o)
        metrics = json.loads(path.read_text())
        row = table[tracker.split("=")[1]]
        assert float(row["ate_rmse_mm"]) == pytest.approx(1e3 * metrics["ate_rmse_m"])
        assert int(row["frames"]) == metrics["frames"] == 4


def test_an_escaped_interpolation_reads_as_written():
    """Hydra records ``data.root=DATA/${seq}`` as ``DATA/$\\{seq\\}`` in overrides.yaml; the table shows what was typed."""
    from torchtrack.report import parse_override

    assert parse_override(r"data.root=/d/$\{seq\}") == ("data.root", "/d/${seq}")
    assert parse_override("+seed=3") == ("seed", "3") and parse_override("~landmarks") == ("landmarks", "<deleted>")
