"""experiments/eval/sweep.py through Hydra's launcher plugins, on the real tracker: Ray (a local cluster started here and
attached by address) and Submitit (``submitit_local``) give the same metrics.json values as the joblib sweep of the
same jobs; a Ray sweep whose driver is killed mid-way finishes only the missing jobs when run again.

2 methods x 2 synthetic sequences of 6 frames at 160x120. Each test skips when its plugin is not installed
(``pip install -e ".[ray]"`` plus the plugin with ``--no-deps``, ``pip install -e ".[submitit]"``; .ci/run installs
both). Time on the 2-core machine: about a minute for the module, most of it interpreter and Ray start-ups."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import sweep  # experiments/, on pytest's pythonpath
from test_experiments import EXPERIMENTS

from torchtrack.data.synthetic import SyntheticConfig, render_sequence

pytestmark = pytest.mark.slow  # integration: whole runs of the console scripts (pytest -m 'not slow' skips them)

METHODS, SEQUENCES = ("fusion_ekf", "horn"), ("s1", "s2")
JOBS = [(m, s) for m in METHODS for s in SEQUENCES]


def sweep_argv(data: Path, out: Path, launcher: str, *extra: str) -> list[str]:
    methods = ",".join(METHODS)
    return ["--data", str(data), "--out", str(out), "--methods", methods, "--launcher", launcher, "--", "plots=false", *extra]  # fmt: skip


def metrics(out: Path) -> dict[tuple[str, str], dict]:
    """metrics.json of every finished job, without fps (a timing, not a result)."""
    found = {}
    for m, s in JOBS:
        path = sweep.result_dir(out, m, s) / "metrics.json"
        if path.is_file():
            found[(m, s)] = {k: v for k, v in json.loads(path.read_text()).items() if k != "fps"}
    return found


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sweep_data")
    for i, s in enumerate(SEQUENCES):
        render_sequence(SyntheticConfig(width=160, height=120, frames=6, seed=i + 1), root / s)
    return root


@pytest.fixture(scope="module")
def joblib_metrics(data, tmp_path_factory) -> dict:
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher")
    out = tmp_path_factory.mktemp("joblib") / "sweep"
    assert sweep.main(sweep_argv(data, out, "joblib")) == 0
    found = metrics(out)
    assert set(found) == set(JOBS) and all(m["frames"] == 6 and "ate_rmse_m" in m for m in found.values())
    return found


@contextlib.contextmanager
def ray_head(ray: Path):
    """A Ray head on 127.0.0.1 with 2 CPUs, its own temp folder and a free port -> its address; stopped at the end
    (``ray start --block`` stops the processes it started on SIGTERM; its process group is killed after that)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    temp = Path(tempfile.mkdtemp(prefix="tt-ray-", dir="/tmp"))  # short: Ray's socket paths must fit 107 bytes
    log = (temp / "ray-start.log").open("w")
    cmd = [str(ray), "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={port}", "--num-cpus=2",
           "--object-store-memory=100000000", "--include-dashboard=false", "--disable-usage-stats",
           f"--temp-dir={temp}"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while "Ray runtime started" not in (temp / "ray-start.log").read_text():
            assert proc.poll() is None and time.monotonic() < deadline, (temp / "ray-start.log").read_text()[-2000:]
            time.sleep(0.5)
        yield f"127.0.0.1:{port}"
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            pass
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # anything of the cluster still alive in its process group
        except ProcessLookupError:
            pass
        log.close()
        shutil.rmtree(temp, ignore_errors=True)


@pytest.fixture(scope="module")
def ray_address() -> str:
    pytest.importorskip("hydra_plugins.hydra_ray_launcher")
    ray = Path(sys.executable).with_name("ray")
    if not ray.is_file():
        pytest.skip("the ray command is not installed beside this Python")
    with pytest.MonkeyPatch.context() as mp:
        # Ray 2.60 starts `ray start` with token authentication when ~/.ray/auth_token exists (a local ray.init()
        # writes one), while a driver attaching by address stays without: one mode for the cluster and its drivers.
        mp.setenv("RAY_AUTH_MODE", "disabled")
        with ray_head(ray) as address:
            yield address


def test_ray_sweep_killed_mid_way_resumes_only_missing_jobs_and_equals_joblib(
    data, joblib_metrics, ray_address, tmp_path
):
    out = tmp_path / "sweep"
    argv = sweep_argv(data, out, "ray", f"hydra.launcher.ray.init.address={ray_address}")
    cmd = [sys.executable, str(EXPERIMENTS / "sweep.py"), *argv]
    log = tmp_path / "driver.log"
    with log.open("w") as f:
        driver = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.monotonic() + 300
    while not metrics(out):  # kill the driver (sweep.py and its Hydra multirun) once the first job has finished
        if driver.poll() is not None or time.monotonic() > deadline:
            pytest.fail(f"the Ray sweep ended before any job finished:\n{log.read_text()[-3000:]}")
        time.sleep(0.2)
    os.killpg(driver.pid, signal.SIGKILL)
    driver.wait()
    before = metrics(out)
    stamps = {j: (sweep.result_dir(out, *j) / "metrics.json").stat().st_mtime_ns for j in before}
    assert 0 < len(before) < len(JOBS)

    assert sweep.main(argv) == 0
    summary = json.loads((out / "sweep.json").read_text())
    assert sorted(map(tuple, summary["skipped_finished"])) == sorted(before)
    assert summary["finished"] == [list(j) for j in JOBS]
    for m in METHODS:  # the re-run swept exactly the jobs that had not finished
        assert _seqs_of(summary["commands"], m) == {s for s in SEQUENCES if (m, s) not in before}
    assert {j: (sweep.result_dir(out, *j) / "metrics.json").stat().st_mtime_ns for j in before} == stamps
    assert metrics(out) == joblib_metrics


def _seqs_of(commands: list[str], method: str) -> set[str]:
    """The sequences the multirun of ``method`` swept (its ``+seq=a,b``), empty when it did not run."""
    for c in commands:
        if f" estimator={method} " in f" {c} ":
            return set(next(a for a in c.split() if a.startswith("+seq=")).removeprefix("+seq=").split(","))
    return set()


def test_submitit_local_sweep_equals_joblib(data, joblib_metrics, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    out = tmp_path / "sweep"
    assert sweep.main(sweep_argv(data, out, "submitit_local")) == 0
    assert metrics(out) == joblib_metrics
    assert all((sweep.job_dir(out, m, s) / ".hydra" / "overrides.yaml").is_file() for m, s in JOBS)
