"""experiments/eval/ and experiments/paper/: the resumable sweep (skip-finished logic, real Hydra multirun with the joblib launcher on a
stand-in app) and the report's tables on fake run folders with known numbers (the oracle), eq. (17) use."""

from __future__ import annotations

import ast
import json
import math
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import report
import sweep
import torch
from tolerances import TIM_PX

from torchtrack.data.tum_io import write_tum_trajectory
from torchtrack.geometry import T_inv, euler_to_matrix, make_T

EXPERIMENTS = (
    Path(__file__).resolve().parents[1] / "experiments" / "eval"
)  # sweep.py and report.py (test_sweep_launchers too)


# ----------------------------------------------------------------------------------------------- fixtures


def make_data(root: Path, seqs=("s1", "s2"), frames: int = 5) -> Path:
    """Sequence folders with rgb.txt/depth.txt (discovery) and a static ground truth (identity poses)."""
    for s in seqs:
        d = root / s
        d.mkdir(parents=True)
        ts = np.arange(frames) / 30.0
        (d / "rgb.txt").write_text("".join(f"{t:.6f} rgb/{i}.png\n" for i, t in enumerate(ts)))
        (d / "depth.txt").write_text("".join(f"{t:.6f} depth/{i}.png\n" for i, t in enumerate(ts)))
        write_tum_trajectory(d / "groundtruth.txt", ts, np.tile(np.eye(4), (frames, 1, 1)))
    return root


def fake_run(sweep_dir: Path, data: Path, method: str, seq: str, *, scale: float = 1.0, frames_csv=None,
             metrics=None, frames: int = 5, overrides=None) -> Path:  # fmt: skip
    """A finished job in the sweep layout. Its trajectory is T_world_cam(t) = inv(E) for t >= 1 with
    E = (Euler (1, 2, 3) mrad, translation (4, 5, 6) mm) * scale, so that with the identity ground truth the
    per-axis errors are exactly scale * (1, 2, 3, 4, 5, 6) * (F - 1) / F (mrad, mm)."""
    job = sweep.job_dir(sweep_dir, method, seq)
    res = sweep.result_dir(sweep_dir, method, seq)
    res.mkdir(parents=True)
    E = make_T(euler_to_matrix(torch.tensor([1e-3, 2e-3, 3e-3], dtype=torch.float64) * scale),
               torch.tensor([4e-3, 5e-3, 6e-3], dtype=torch.float64) * scale)  # fmt: skip
    T = np.stack([np.eye(4)] + [T_inv(E).numpy()] * (frames - 1))
    write_tum_trajectory(res / "trajectory.txt", np.arange(frames) / 30.0, T)
    (res / "metrics.json").write_text(json.dumps({"sequence": seq, "frames": frames, **(metrics or {})}))
    if frames_csv is not None:
        lines = ["frame,timestamp,features,sim_wins,reprojection_px,mean_tim_px,reselected"]
        lines += [f"{i},{i / 30},{n},0,{e},{tim},{i == 0}" for i, (n, e, tim) in enumerate(frames_csv)]
        (res / "frames.csv").write_text("\n".join(lines) + "\n")
    (job / ".hydra").mkdir()
    (job / ".hydra" / "config.yaml").write_text(f"seq: {seq}\ndata:\n  root: {data}/${{seq}}\n")
    ov = overrides if overrides is not None else sweep.job_overrides(sweep.METHODS[method], seq, data, [])
    (job / ".hydra" / "overrides.yaml").write_text("".join(f"- {o}\n" for o in ov))
    return res


# ----------------------------------------------------------------------------------------------- sweep


def test_plan_skips_finished_and_lists_the_rest(tmp_path):
    data = make_data(tmp_path / "data")
    out = tmp_path / "sweep"
    fake_run(out, data, "horn", "s1")
    assert sweep.discover_sequences(data) == ["s1", "s2"]
    plan = sweep.plan_sweep(out, ["horn", "fusion_ekf"], ["s1", "s2"], data, [])
    assert plan.done == [("horn", "s1")]
    assert plan.todo == {"horn": ["s2"], "fusion_ekf": ["s1", "s2"]}
    assert plan.changed == []


def test_plan_unfinished_job_without_metrics_is_todo(tmp_path):
    data = make_data(tmp_path / "data")
    out = tmp_path / "sweep"
    res = fake_run(out, data, "icp", "s1")
    (res / "metrics.json").unlink()  # killed before the runner's last (atomic) write
    assert sweep.plan_sweep(out, ["icp"], ["s1"], data, []).todo == {"icp": ["s1"]}


def test_plan_detects_changed_overrides_in_any_spelling(tmp_path):
    data = make_data(tmp_path / "data")
    out = tmp_path / "sweep"
    ov = sweep.job_overrides(sweep.METHODS["ekf2"], "s1", data, ["data.max_frames=5", "plots=false"])
    # Hydra records plots=False and escapes ${seq}: the same job
    recorded = [o.replace("plots=false", "plots=False").replace("${seq}", "$\\{seq\\}") for o in ov]
    fake_run(out, data, "ekf2", "s1", overrides=recorded)
    same = sweep.plan_sweep(out, ["ekf2"], ["s1"], data, ["data.max_frames=5", "plots=false"])
    assert same.done == [("ekf2", "s1")] and same.changed == []
    other = sweep.plan_sweep(out, ["ekf2"], ["s1"], data, ["data.max_frames=6", "plots=false"])
    assert other.changed == [("ekf2", "s1")] and other.todo == {}
    redo = sweep.plan_sweep(out, ["ekf2"], ["s1"], data, ["data.max_frames=6"], rerun_changed=True)
    assert redo.todo == {"ekf2": ["s1"]}


def test_plan_rejects_unknown_method(tmp_path):
    with pytest.raises(ValueError, match="unknown method"):
        sweep.plan_sweep(tmp_path, ["nope"], ["s1"], tmp_path, [])


def test_hydra_command_sweeps_sequences_and_composes_ablations(tmp_path):
    extra = ["plots=false", "hydra.launcher.timeout_min=5"]  # launcher settings: passed, not part of the job's identity
    cmd = sweep.hydra_command(sweep.METHODS["ekf3"], ["a", "b"], tmp_path, tmp_path / "d", extra, "joblib", 3,
                              ["torchtrack"])  # fmt: skip
    assert "hydra.launcher.timeout_min=5" in cmd
    assert "hydra.launcher.timeout_min=5" not in sweep.job_overrides(sweep.METHODS["ekf3"], "a", tmp_path, extra)
    assert cmd[:3] == ["torchtrack", "-m", "+seq=a,b"]
    assert f"data.root={(tmp_path / 'd').resolve()}/${{seq}}" in cmd
    assert "+experiment=[ekf1,ekf2,ekf3]" in cmd and "estimator=fusion_ekf" in cmd and "plots=false" in cmd
    assert "hydra.sweep.subdir=${seq}" in cmd and f"hydra.sweep.dir={tmp_path.resolve() / 'ekf3'}" in cmd
    assert cmd[-2:] == ["hydra/launcher=joblib", "hydra.launcher.n_jobs=3"]
    assert sweep.launcher_overrides("submitit_slurm", 3) == ["hydra/launcher=submitit_slurm"]
    with pytest.raises(ValueError, match="peer"):
        sweep.hydra_command(sweep.METHODS["open3d_odometry"], ["a"], tmp_path, tmp_path, [], "basic", 1, ["x"])


def test_ray_launcher_leaves_the_object_store_to_a_cluster_it_attaches_to():
    """hydra-ray-launcher 1.2.2 sets object_store_memory, which ray.init refuses when attaching to a cluster."""
    assert sweep.launcher_overrides("ray", 2, []) == ["hydra/launcher=ray"]
    attach = ["hydra.launcher.ray.init.address=127.0.0.1:6379"]
    assert sweep.launcher_overrides("ray", 2, attach)[-1] == f"++{sweep.RAY_OBJECT_STORE}=null"
    mine = [*attach, f"{sweep.RAY_OBJECT_STORE}=1000000000"]
    assert sweep.launcher_overrides("ray", 2, mine) == ["hydra/launcher=ray"]  # the user's value stays


def test_missing_launcher_plugin_is_one_line_with_the_install_command(tmp_path, monkeypatch, capsys):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if "hydra_ray" in n else find_spec(n, *a))
    data = make_data(tmp_path / "data")
    with pytest.raises(SystemExit) as e:
        sweep.main(["--data", str(data), "--out", str(tmp_path / "o"), "--launcher", "ray"])
    assert e.value.code == 2
    assert "needs its Hydra plugin" in capsys.readouterr().err and "hydra-ray-launcher" in sweep.PLUGINS["ray"][1]
    assert sweep.missing_plugin("basic") is None


STAND_IN_APP = """
import ast
import json
from pathlib import Path
import hydra
from hydra.core.hydra_config import HydraConfig

@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def app(cfg):
    out = Path(HydraConfig.get().runtime.output_dir) / Path(cfg.data.root).name
    out.mkdir(parents=True, exist_ok=True)
    (out / "metrics.json").write_text(json.dumps({"sequence": out.name, "estimator": cfg.estimator.name}))

app()
"""


@pytest.mark.slow
def test_sweep_end_to_end_with_joblib_resumes_only_missing_jobs(tmp_path):
    """A stand-in Hydra app with the CLI's contract, launched by the real joblib launcher; a 'killed' job is
    the only one re-run."""
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    app = tmp_path / "app"
    for group, files in {"data": {"tum": "root: null\n"}, "estimator": {"horn": "name: horn\n"}}.items():
        (app / "conf" / group).mkdir(parents=True)
        for name, text in files.items():
            (app / "conf" / group / f"{name}.yaml").write_text(text)
    (app / "conf" / "config.yaml").write_text(
        "defaults:\n  - data: tum\n  - estimator: horn\n  - _self_\nplots: true\n"
    )
    (app / "app.py").write_text(textwrap.dedent(STAND_IN_APP))
    data, out = make_data(tmp_path / "data"), tmp_path / "sweep"
    argv = ["--data", str(data), "--out", str(out), "--methods", "horn", "--program", f"{sys.executable} {app}/app.py"]
    assert sweep.main([*argv, "--", "plots=false"]) == 0
    for s in ("s1", "s2"):
        m = json.loads((sweep.result_dir(out, "horn", s) / "metrics.json").read_text())
        assert m == {"sequence": s, "estimator": "horn"}
    kept = sweep.result_dir(out, "horn", "s1") / "metrics.json"
    kept.write_text('{"sequence": "s1", "marker": 1}')  # must survive the resume untouched
    (sweep.result_dir(out, "horn", "s2") / "metrics.json").unlink()
    assert sweep.main([*argv, "--launcher", "basic", "--", "plots=false"]) == 0
    summary = json.loads((out / "sweep.json").read_text())
    assert summary["skipped_finished"] == [["horn", "s1"]]
    assert len(summary["commands"]) == 1 and "+seq=s2 " in summary["commands"][0]
    assert json.loads(kept.read_text())["marker"] == 1
    assert (sweep.result_dir(out, "horn", "s2") / "metrics.json").is_file()
    assert sweep.main([*argv, "--", "plots=true"]) == 2  # other settings into the same folder: refused


# ----------------------------------------------------------------------------------------------- report


def test_report_tables_match_known_numbers(tmp_path):
    data = make_data(tmp_path / "data")
    out = tmp_path / "sweep"
    rows = [(10, 0.0, 0.0), (10, 1.0, 0.2), (30, 2.0, 0.4)]  # pooled: (10*1 + 30*2) / 40 = 1.75 px
    scales = {"fusion_ekf": 1.0, "icp": 2.0, "cpd": 4.0, "horn": 1.25, "ekf1": 1.5, "ekf2": 1.5, "ekf3": 1.5}
    for m, k in scales.items():
        metrics = {"ate_rmse_m": 0.01 * k, "rpe_trans_m": 0.002, "rpe_rot_deg": 0.1, "fps": 10.0 * k, "reselections": 1}
        fake_run(out, data, m, "s1", scale=k, metrics=metrics, frames_csv=[(n, e * k, t * k) for n, e, t in rows])
    fake_run(out, data, "fusion_ekf", "s2", scale=1.0, metrics={"mean_reprojection_px": 3.0})
    fake_run(out, data, "icp", "s2", scale=4.0, metrics={"mean_reprojection_px": 5.0})
    rep = report.build_report(out)
    n = rep.numbers
    assert n["table3"]["s1"] == pytest.approx({"fusion_ekf": 1.75, "icp": 3.5, "cpd": 7.0, "horn": 2.1875})
    assert n["table3"]["s2"] == {"fusion_ekf": 3.0, "icp": 5.0, "cpd": None, "horn": None}  # metrics.json fallback
    assert n["table5"]["s1"]["ekf3"] == pytest.approx(1.5 * 1.75)
    assert n["tim_runs"]["s1"] == pytest.approx({"fusion_ekf": 0.3, "ekf2": 0.45})
    per_axis = np.array(n["per_axis"]["s1"]["fusion_ekf"])
    assert per_axis == pytest.approx(np.arange(1, 7) * 4 / 5, rel=1e-6)  # frame 0 exact, 4 of 5 frames off
    # eq. (17): PI = (e_base - e_prop) / e_base * 100 on every axis; s1 gives 50 %, s2 75 % for ICP -> mean 62.5
    assert n["table6"]["icp"]["pi"] == pytest.approx([62.5] * 6, abs=1e-3)  # TUM files: 9 decimals
    assert n["table6"]["icp"]["sequences"] == ["s1", "s2"]
    assert n["table6"]["cpd"]["pi"] == pytest.approx([75.0] * 6, abs=1e-3)  # TUM files: 9 decimals
    assert n["table6"]["horn"]["pi"] == pytest.approx([20.0] * 6, abs=1e-3)  # TUM files: 9 decimals
    assert "open3d_odometry" not in n["table6"]
    md = rep.markdown
    assert "| s1 | 1.75 | 3.50 | 7.00 | 2.19 |" in md  # Table III row
    assert "| ICP | 62.5 | 62.5 | 62.5 | 62.5 | 62.5 | 62.5 | 2 |" in md  # Table VI row
    assert "| s1 | Proposed | 5 | 1.00 | 0.20 | 0.100 | 1.75 | 10.0 | 1 |" in md  # every-run row
    assert "Not computed: run `python experiments/paper/table1_spread.py" in md


def test_report_improvement_is_undefined_where_the_baseline_is_exact():
    pi = report._improvement(np.array([1.0, 2.0]), np.array([0.0, 4.0]))
    assert math.isnan(pi[0]) and pi[1] == pytest.approx(50.0)


def test_report_includes_table_scripts_and_plots(tmp_path):
    data = make_data(tmp_path / "data")
    out = tmp_path / "sweep"
    for m, k in (("fusion_ekf", 1.0), ("horn", 2.0)):
        fake_run(out, data, m, "s1", scale=k, frames_csv=[(10, 0.0, 0.0), (10, k, 0.1)], metrics={"ate_rmse_m": k})
    (out / "table2").mkdir()
    (out / "table2" / "table2_tim.md").write_text("| sequence | Intensity |\n|---|---|\n| s1 | 1.15 |\n")
    assert report.main([str(out), "--out", str(tmp_path / "rep")]) == 0
    md = (tmp_path / "rep" / "REPORT.md").read_text()
    assert "| s1 | 1.15 |" in md
    assert json.loads((tmp_path / "rep" / "report.json").read_text())["table6"]["horn"]["pi"] == pytest.approx(
        [50.0] * 6, abs=1e-3
    )
    for png in ("reprojection.png", "ate.png", "improvement.png", "frames_s1.png"):
        assert (tmp_path / "rep" / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_report_without_runs_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match="no run under"):
        report.build_report(tmp_path)


@pytest.mark.parametrize("folder", ["empty", "missing"])
def test_report_main_on_a_folder_without_a_sweep_says_so_in_one_line(tmp_path, capsys, folder):
    if folder == "empty":
        (tmp_path / folder).mkdir()
    assert report.main([str(tmp_path / folder)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("report.py: error: ") and "Traceback" not in err
    assert not (tmp_path / folder / "report").exists()  # nothing written into a folder that is not a sweep


# ----------------------------------------------------------------------------------------------- Table I


import table1_spread as table1  # noqa: E402


def test_table1_exact_measurements_recover_the_artificial_motion():
    """Noise-free eq. (6)/(7) measurements, near-zero variances, iterated EKF: the motion is recovered exactly."""
    from torchtrack.geometry import intrinsics_matrix
    from torchtrack.metrics import per_axis_errors

    g = torch.Generator().manual_seed(0)
    X = (torch.rand(2, 12, 3, generator=g, dtype=torch.float64) - 0.5) * 0.2
    K = intrinsics_matrix(525.0, 525.0, 320.0, 240.0).double()
    T = table1.artificial_motion(6, 30.0, math.radians(10), 0.03, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(T[0], make_T(torch.eye(3, dtype=torch.float64), torch.tensor([0.0, 0.0, 1.0]).double()))
    points_d, pixels = table1.measurements(T, X, K, 0.0, 0.0, g)
    T_est = table1.track(X, points_d, pixels, K, T[0], 30.0, sigma2_pix=1e-10, sigma2_xyz=1e-14, iterations=4,
                         jacobian="analytic")  # fmt: skip
    assert T_est.shape == (6, 2, 4, 4)
    for b in range(2):
        e = per_axis_errors(T_est[:, b], T)
        assert float(e.rot_mean_deg.max()) < 1e-6 and float(e.trans_mean_m.max()) < 1e-9


def test_table1_subsets_grow_in_spread():
    g = torch.Generator().manual_seed(1)
    P = torch.randn(2000, 3, generator=g, dtype=torch.float64) * torch.tensor([0.05, 0.03, 0.02]).double()
    assert float(table1.spread(P)) == pytest.approx(float(np.linalg.norm(P.numpy().std(0, ddof=1))), rel=1e-12)
    idx = table1.spread_subsets(P, 40, [0.2, 0.5, 1.0], 5, g)
    assert idx.shape == (15, 40)
    assert all(len(set(row.tolist())) == 40 for row in idx)  # no point twice in a subset
    d = P.norm(dim=-1)
    assert float(d[idx[:5]].max()) <= float(torch.quantile(d, 0.2))  # drawn from the 20 % pool
    s = table1.spread(P[idx]).reshape(3, 5).mean(1)
    assert bool((s[1:] > s[:-1]).all())
    with pytest.raises(ValueError, match="only"):
        table1.spread_subsets(P[:50], 40, [0.2], 1, g)


# ----------------------------------------------------------------------------------------------- Table II


import table2_tim as table2  # noqa: E402


@pytest.mark.equivalence
def test_table2_combined_tracker_takes_the_smaller_tim_per_feature():
    """Intensity moved by a known integer shift (LK exact, d_TIM ~ 0); a static SIM, flat on its left half
    (LK loses the feature there) and textured on its right half (zero motion: d_TIM = 0 exactly). The combined
    tracker takes, per feature, the smaller d_TIM; an invalid feature has none."""
    g = torch.Generator().manual_seed(0)
    tex = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 96, 96, generator=g), 5, 1, 2)  # smooth texture
    nxt = torch.roll(tex, shifts=(1, 2), dims=(2, 3))  # content moves by (x, y) = (2, 1) px
    sim = torch.nn.functional.avg_pool2d(torch.rand(1, 1, 96, 96, generator=g), 5, 1, 2)
    sim[..., :48] = 0.5
    pixels = torch.tensor([[[30.0, 30.0], [70.0, 40.0], [40.0, 60.0]]])
    valid = torch.tensor([[True, True, False]])
    from torchtrack.image.flow import combined_track, prepare_frame

    prev, next = prepare_frame(tex, sim, 2), prepare_frame(nxt, sim, 2)
    d = table2.tim_by_tracker(prev, next, pixels, valid, levels=2, window=11)
    for mode in ("intensity", "sim"):  # one combined call (both channels at once) == the single-tracker modes
        single = combined_track(prev, next, pixels, valid, mode=mode, levels=2, window=11).d_tim
        single = torch.where(valid, single, torch.full_like(single, float("inf")))
        torch.testing.assert_close(single, d[mode], atol=TIM_PX, rtol=0)  # other batch shapes: other roundings
    assert d["intensity"][0, :2].max() < 0.05
    assert torch.isinf(d["sim"][0, 0]) and d["sim"][0, 1] < 1e-6
    assert d["combined"][0, 0] == d["intensity"][0, 0] and d["combined"][0, 1] == d["sim"][0, 1]
    assert all(torch.isinf(d[m][0, 2]) for m in table2.MODES)
    s = table2._stats(d["combined"][valid].numpy())
    assert s["lost_fraction"] == 0.0 and s["features"] == 2 and s["mean_px"] < 0.05
    assert table2._stats(np.array([1.0, 3.0, np.inf, np.inf])) == {
        "mean_px": 2.0, "median_px": 2.0, "lost_fraction": 0.5, "features": 4
    }  # fmt: skip


def test_table2_markdown_has_the_papers_column_and_one_row_per_tracker():
    stats = {"intensity": (1.0, 0.5, 0.25), "sim": (30.0, 2.0, 0.5), "combined": (0.5, 0.25, 0.0)}
    seq = {m: {"mean_px": a, "median_px": b, "lost_fraction": c, "features": 40} for m, (a, b, c) in stats.items()}
    md = table2.markdown({"settings": {"pairs": 3, "levels": 3, "window": 21}, "sequences": {"s1": seq}})
    rows = [ln for ln in md.splitlines() if ln.startswith("| ")]
    assert rows == [
        "| tracker | paper | s1 |",
        f"| Intensity tracker | {table2.PAPER_TABLE2['intensity']:.2f} | 1.00 (0.50), 25% lost |",
        f"| SIM tracker | {table2.PAPER_TABLE2['sim']:.2f} | 30.00 (2.00), 50% lost |",
        f"| Combined tracker | {table2.PAPER_TABLE2['combined']:.2f} | 0.50 (0.25), 0% lost |",
        "| features | – | 40 |",
    ]


# ----------------------------------------------------------------------------------------------- every script


def _help_formatter_ok(tree: ast.Module, call: ast.Call) -> bool:
    """The parser's formatter_class is ArgumentDefaultsHelpFormatter or a class of the module derived from it."""
    fmt = next((k.value for k in call.keywords if k.arg == "formatter_class"), None)
    if fmt is None:
        return False
    if ast.unparse(fmt) == "argparse.ArgumentDefaultsHelpFormatter":
        return True
    classes = {c.name: c for c in ast.walk(tree) if isinstance(c, ast.ClassDef)}
    c = classes.get(ast.unparse(fmt))
    return c is not None and "argparse.ArgumentDefaultsHelpFormatter" in {ast.unparse(b) for b in c.bases}


@pytest.mark.parametrize(
    "script", sorted(p.relative_to(EXPERIMENTS.parent).as_posix() for p in EXPERIMENTS.parent.glob("*/*.py"))
)
def test_every_scripts_help_shows_its_defaults(script):
    """Static: each ArgumentParser shows defaults, and each option has a help text (argparse shows a default only
    beside a help text)."""
    tree = ast.parse((EXPERIMENTS.parent / script).read_text())
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)]
    parsers = [c for c in calls if ast.unparse(c.func).endswith("ArgumentParser")]
    assert all(_help_formatter_ok(tree, c) for c in parsers), script
    options = [c for c in calls if isinstance(c.func, ast.Attribute) and c.func.attr == "add_argument"]
    assert all(any(k.arg == "help" for k in c.keywords) for c in options), [ast.unparse(c)[:80] for c in options]
