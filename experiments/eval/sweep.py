"""The paper's sweep: sequences x methods (trackers, ablations, a peer), one folder per job, finished jobs skipped.

    python experiments/eval/sweep.py --data ../shared/data --out runs/paper                      # all, joblib x2
    python experiments/eval/sweep.py --data ../shared/data --out runs/smoke -- data.max_frames=5 plots=false
    python experiments/eval/sweep.py --out runs/paper --methods fusion_ekf,horn --sequences sun3d_fragment1
    python experiments/eval/sweep.py --out runs/paper --launcher submitit_slurm -- hydra.launcher.partition=cpu
    python experiments/eval/sweep.py --out runs/paper --launcher ray -- hydra.launcher.ray.init.address=HEAD:6379
    python experiments/eval/sweep.py --out runs/paper --dry-run                                   # print the plan

Layout of ``OUT``::

    OUT/<method>/<seq>/.hydra/            one Hydra job: resolved config, overrides
    OUT/<method>/<seq>/<seq>/metrics.json the tracker's outputs (trajectory.txt, frames.csv, plots)
    OUT/sweep.json                        what was asked, the commands, what is finished

A job is finished when its ``metrics.json`` exists (the runner writes it last, atomically), so a killed
sweep run again skips what is done and redoes only the rest. A finished job whose recorded overrides
differ from the ones asked now is an error (use another ``--out`` or ``--rerun-changed``): numbers
made with different settings never mix silently.

For every method one Hydra multirun (``torchtrack -m``) covers its unfinished sequences: ``+seq`` is
swept, ``data.root=DATA/${seq}`` and ``hydra.sweep.subdir=${seq}`` follow it, and the launcher
(``--launcher joblib|basic|submitit_local|submitit_slurm|paper_slurm|ray``; Hydra's plugins, see
experiments/README.md for installing them) runs the jobs. The peer method
(Open3D RGB-D odometry) runs in this process through :func:`peers.open3d_rgbd_odometry`
and writes the same layout.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from torchtrack.io import write_json

log = logging.getLogger("sweep")

DEFAULT_DATA = Path(__file__).resolve().parents[3] / "shared" / "data"


@dataclass(frozen=True)
class Method:
    """A column of the paper's tables: Hydra overrides of ``torchtrack`` (or a peer run in this process)."""

    name: str  # folder name under OUT
    label: str  # column title in the report
    overrides: tuple[str, ...] = ()
    peer: bool = False


# Table IV's ablations are cumulative (EKF-1: no spatio-textural selection; EKF-2: also no SIM-assisted
# tracking; EKF-3: also no weighting), composed from conf/experiment/ekf{1,2,3}.yaml, each setting one switch.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("fusion_ekf", "Proposed", ("estimator=fusion_ekf",)),
        Method("paper", "Proposed, paper as written", ("estimator=fusion_ekf", "+experiment=paper")),
        Method("icp", "ICP", ("estimator=icp",)),
        Method("cpd", "CPD", ("estimator=cpd",)),
        Method("horn", "Quaternion", ("estimator=horn",)),
        Method("ekf1", "EKF-1", ("estimator=fusion_ekf", "+experiment=ekf1")),
        Method("ekf2", "EKF-2", ("estimator=fusion_ekf", "+experiment=[ekf1,ekf2]")),
        Method("ekf3", "EKF-3", ("estimator=fusion_ekf", "+experiment=[ekf1,ekf2,ekf3]")),
        Method("open3d_odometry", "Open3D odometry", peer=True),
    )
}


# ----------------------------------------------------------------------------------------------- layout


def job_dir(out: Path, method: str, seq: str) -> Path:
    """The Hydra job folder of (method, seq): ``OUT/<method>/<seq>``."""
    return Path(out) / method / seq


def result_dir(out: Path, method: str, seq: str) -> Path:
    """Where the tracker writes the sequence's files: ``OUT/<method>/<seq>/<seq>``."""
    return job_dir(out, method, seq) / seq


def is_finished(out: Path, method: str, seq: str) -> bool:
    return (result_dir(out, method, seq) / "metrics.json").is_file()


def discover_sequences(data: Path) -> list[str]:
    """Names of the TUM-layout folders (holding rgb.txt and depth.txt) directly under ``data``, sorted."""
    data = Path(data)
    if not data.is_dir():
        raise FileNotFoundError(f"data folder {data} not found")
    return sorted(p.name for p in data.iterdir() if (p / "rgb.txt").is_file() and (p / "depth.txt").is_file())


def job_overrides(method: Method, seq: str, data: Path, extra: list[str]) -> list[str]:
    """The task overrides of one job, as Hydra records them in ``.hydra/overrides.yaml`` (up to escaping).

    ``seq`` may be a comma list (a Hydra sweep). ``hydra.*`` overrides (launcher settings) are not task
    overrides: Hydra does not record them, and they do not change results. The peer keeps only the
    ``data.*`` overrides (it reads frames, it has no tracker)."""
    common = [f"+seq={seq}", "data=tum", f"data.root={Path(data).resolve()}/${{seq}}"]
    task = [o for o in extra if not _is_hydra(o)]
    if method.peer:
        return common + [o for o in task if o.lstrip("+~").startswith("data.")]
    return common + list(method.overrides) + task


def _is_hydra(override: str) -> bool:
    return override.lstrip("+~").startswith(("hydra.", "hydra/"))


def recorded_overrides(out: Path, method: str, seq: str) -> list[str] | None:
    """The overrides a finished job ran with (Hydra's ``overrides.yaml`` or the peer's ``job.json``)."""
    d = job_dir(out, method, seq)
    if (d / ".hydra" / "overrides.yaml").is_file():
        return list(yaml.safe_load((d / ".hydra" / "overrides.yaml").read_text()) or [])
    if (d / "job.json").is_file():
        return list(json.loads((d / "job.json").read_text())["overrides"])
    return None


def canonical(overrides: list[str]) -> list[str]:
    """Overrides in one spelling (Hydra's parser: ``plots=false`` == ``plots=False``, ``${x}`` == ``$\\{x\\}``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(list(overrides))
    return sorted(f"{o.type.name}:{o.key_or_group}={o.get_value_element_as_str()}" for o in parsed)


@dataclass
class Plan:
    """todo: method -> unfinished sequences; done: finished (method, seq); changed: finished with other overrides."""

    todo: dict[str, list[str]] = field(default_factory=dict)
    done: list[tuple[str, str]] = field(default_factory=list)
    changed: list[tuple[str, str]] = field(default_factory=list)


def plan_sweep(
    out: Path, methods: list[str], sequences: list[str], data: Path, extra: list[str], rerun_changed: bool = False
) -> Plan:
    """Split the (method, seq) jobs into finished and to-do; a finished job run with other overrides is
    ``changed`` (and to-do again when ``rerun_changed``)."""
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ValueError(f"unknown method(s) {unknown}; choose from {list(METHODS)}")
    plan = Plan()
    for name in methods:
        for seq in sequences:
            if not is_finished(out, name, seq):
                plan.todo.setdefault(name, []).append(seq)
                continue
            had = recorded_overrides(out, name, seq)
            if had is not None and canonical(had) != canonical(job_overrides(METHODS[name], seq, data, extra)):
                plan.changed.append((name, seq))
                if rerun_changed:
                    plan.todo.setdefault(name, []).append(seq)
                    continue
            plan.done.append((name, seq))
    return plan


# ----------------------------------------------------------------------------------------------- launching


# The plugin (an importable module under hydra_plugins) each launcher config comes from, and how to install it.
PLUGINS = {
    "joblib": ("hydra_joblib_launcher", 'pip install -e ".[dev]"'),
    "submitit_local": ("hydra_submitit_launcher", 'pip install -e ".[submitit]"'),
    "submitit_slurm": ("hydra_submitit_launcher", 'pip install -e ".[submitit]"'),
    "paper_slurm": ("hydra_submitit_launcher", 'pip install -e ".[submitit]"'),
    "ray": ("hydra_ray_launcher", 'pip install -e ".[ray]" && pip install --no-deps hydra-ray-launcher==1.2.2'),
}
RAY_OBJECT_STORE = "hydra.launcher.ray.init.object_store_memory"


def missing_plugin(launcher: str) -> str | None:
    """The install command of ``launcher``'s plugin when it is not importable here, else None."""
    import importlib.util

    module, install = PLUGINS.get(launcher, (None, None))
    if module is None or importlib.util.find_spec(f"hydra_plugins.{module}") is not None:
        return None
    return install


def launcher_overrides(launcher: str, jobs: int, extra: list[str] = ()) -> list[str]:
    """Hydra overrides selecting the launcher plugin (``basic`` is Hydra's sequential one).

    Ray: hydra-ray-launcher 1.2.2 passes ``object_store_memory`` (75 MB) to ``ray.init`` unless it is set, and
    Ray >= 2 refuses that when attaching to a running cluster (``hydra.launcher.ray.init.address=...``): then it
    is set to null (the cluster's own store). Without an address the plugin starts a local Ray with its 75 MB."""
    if launcher == "basic":
        return []
    ov = [f"hydra/launcher={launcher}"]
    if launcher == "joblib":
        ov.append(f"hydra.launcher.n_jobs={jobs}")
    attach = _extra_value(list(extra), "hydra.launcher.ray.init.address") is not None
    if launcher == "ray" and attach and _extra_value(list(extra), RAY_OBJECT_STORE) is None:
        ov.append(f"++{RAY_OBJECT_STORE}=null")
    return ov


def hydra_command(
    method: Method,
    seqs: list[str],
    out: Path,
    data: Path,
    extra: list[str],
    launcher: str,
    jobs: int,
    program: list[str],
) -> list[str]:
    """One multirun of ``program`` (``python -m torchtrack.cli``) over ``seqs`` for ``method``."""
    if method.peer:
        raise ValueError(f"{method.name} is a peer: it runs in-process, not through Hydra")
    task = job_overrides(method, ",".join(seqs), data, extra) + [o for o in extra if _is_hydra(o)]
    hydra = [f"hydra.sweep.dir={Path(out).resolve() / method.name}", "hydra.sweep.subdir=${seq}"]
    return [*program, "-m", *task, *hydra, *launcher_overrides(launcher, jobs, extra)]


def _extra_value(extra: list[str], key: str):
    for o in extra:
        k, _, v = o.lstrip("+").partition("=")
        if k == key:
            return None if v in ("null", "None") else yaml.safe_load(v)
    return None


def run_peer(out: Path, seq: str, data: Path, extra: list[str]) -> dict:
    """Open3D RGB-D odometry on one sequence, written like a tracker run (trajectory.txt, metrics.json)."""
    import numpy as np
    from peers import open3d_rgbd_odometry

    from torchtrack.data.tum import TumSequence
    from torchtrack.data.tum_io import write_tum_trajectory
    from torchtrack.metrics import trajectory_metrics

    method = METHODS["open3d_odometry"]
    jd, rd = job_dir(out, method.name, seq), result_dir(out, method.name, seq)
    rd.mkdir(parents=True, exist_ok=True)
    opts = {k: _extra_value(extra, f"data.{k}") for k in ("max_frames", "stride", "max_dt")}
    opts = {k: v for k, v in opts.items() if v is not None}
    job = {"method": method.name, "sequence": seq, "data_root": str(Path(data).resolve() / seq), "options": opts}
    job["overrides"] = job_overrides(method, seq, data, extra)
    write_json(jd / "job.json", job)
    sequence = TumSequence(Path(data) / seq, **opts)
    T_world_cam, fps = open3d_rgbd_odometry(sequence, progress=False)
    write_tum_trajectory(rd / "trajectory.txt", sequence.timestamps, T_world_cam)
    metrics = {"sequence": sequence.name, "method": method.name, "frames": len(sequence), "fps": fps}
    if int(np.sum(sequence.gt_valid)) >= 2:
        metrics.update(trajectory_metrics(sequence.timestamps, T_world_cam, sequence.groundtruth, sequence.gt_valid))
    write_json(rd / "metrics.json", metrics)
    return metrics


def machine_description() -> str:
    """CPU model and count, OS and Python: the line RESULTS.md quotes."""
    cpu = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.is_file():
        names = [ln.split(":", 1)[1].strip() for ln in cpuinfo.read_text().splitlines() if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    return f"{cpu}, {os.cpu_count()} logical CPUs, {platform.system()} {platform.release()}, Python {platform.python_version()}"


def write_summary(out: Path, args: argparse.Namespace, extra: list[str], commands: list[list[str]], plan: Plan) -> None:
    """OUT/sweep.json: what was asked and run, and which jobs are finished now (atomic write)."""
    finished = [[m, s] for m in args.methods for s in args.sequences if is_finished(out, m, s)]
    summary = {
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
        "machine": machine_description(),
        "data": str(Path(args.data).resolve()),
        "methods": {m: {"label": METHODS[m].label, "overrides": list(METHODS[m].overrides)} for m in args.methods},
        "sequences": args.sequences,
        "extra_overrides": extra,
        "launcher": args.launcher,
        "commands": [" ".join(c) for c in commands],
        "skipped_finished": [list(j) for j in plan.done],
        "finished": finished,
        "unfinished": [[m, s] for m in args.methods for s in args.sequences if [m, s] not in finished],
    }
    write_json(out / "sweep.json", summary)


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawTextHelpFormatter):
    """--help: help texts as written, and every option's default."""


def _parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1 :]
    else:
        extra = []
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=HelpFormatter)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="folder of TUM-layout sequences")
    p.add_argument("--out", type=Path, required=True, help="sweep folder (re-run it to resume)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma list from {','.join(METHODS)}")
    p.add_argument("--sequences", default=None, help="comma list of folder names under --data (None: all)")
    p.add_argument(
        "--launcher",
        default="joblib",
        help="Hydra launcher: joblib, basic, submitit_local, submitit_slurm, paper_slurm, ray\n"
        "(a Ray cluster: -- hydra.launcher.ray.init.address=HOST:PORT)",
    )
    p.add_argument("--jobs", type=int, default=2, help="parallel jobs of the joblib launcher and of the peer")
    p.add_argument("--program", default=f"{sys.executable} -m torchtrack.cli", help="the Hydra app to launch")
    p.add_argument("--rerun-changed", action="store_true", help="redo finished jobs whose overrides differ")
    p.add_argument("--dry-run", action="store_true", help="print the plan and the commands, run nothing")
    args = p.parse_args(argv)
    install = missing_plugin(args.launcher) if args.program == p.get_default("program") else None
    if install and not args.dry_run:
        p.error(f"--launcher {args.launcher} needs its Hydra plugin, not installed here: {install}")
    args.methods = [m for m in args.methods.split(",") if m]
    seqs = args.sequences.split(",") if args.sequences else discover_sequences(args.data)
    missing = [s for s in seqs if not (args.data / s).is_dir()]
    if missing:
        p.error(f"sequence folder(s) {missing} not found under {args.data}")
    args.sequences = seqs
    return args, extra


def main(argv: list[str] | None = None) -> int:
    """Run the sweep; returns 0 when every job is finished, 1 when some failed, 2 on a changed job."""
    logging.basicConfig(level=logging.INFO, format="[%(asctime)s][sweep] %(message)s")
    args, extra = _parse(sys.argv[1:] if argv is None else argv)
    out = args.out
    plan = plan_sweep(out, args.methods, args.sequences, args.data, extra, args.rerun_changed)
    if plan.changed and not args.rerun_changed:
        jobs = ", ".join(f"{m}/{s}" for m, s in plan.changed)
        log.error("finished job(s) %s ran with other overrides; use another --out or --rerun-changed", jobs)
        return 2
    log.info("%d job(s) finished already (skipped), %d to run", len(plan.done), sum(map(len, plan.todo.values())))
    commands = []
    for name, seqs in plan.todo.items():
        method = METHODS[name]
        if method.peer:
            commands.append(["<in-process>", "open3d_rgbd_odometry", *seqs])
            log.info("%s: %s", name, ", ".join(seqs))
            if not args.dry_run:
                _run_peers(out, seqs, args, extra)
            continue
        cmd = hydra_command(method, seqs, out, args.data, extra, args.launcher, args.jobs, args.program.split())
        commands.append(cmd)
        log.info("%s: %s", name, " ".join(cmd))
        if not args.dry_run:
            rc = subprocess.call(cmd)
            if rc != 0:
                log.error("%s: multirun exited with %d; its unfinished jobs stay to-do (see its logs)", name, rc)
    if not args.dry_run:
        write_summary(out, args, extra, commands, plan)
    left = [f"{m}/{s}" for m in args.methods for s in args.sequences if not is_finished(out, m, s)]
    if left and not args.dry_run:
        log.error("unfinished: %s (run the same command again to retry only these)", ", ".join(left))
        return 1
    return 0


def _run_peers(out: Path, seqs: list[str], args: argparse.Namespace, extra: list[str]) -> None:
    from joblib import Parallel, delayed

    def one(seq: str) -> None:
        try:
            run_peer(out, seq, args.data, extra)
        except Exception as e:  # noqa: BLE001 - a failed sequence stays to-do; the others go on
            logging.getLogger("sweep").error("open3d_odometry/%s failed: %s", seq, e)

    Parallel(n_jobs=min(args.jobs, len(seqs)))(delayed(one)(s) for s in seqs)


if __name__ == "__main__":
    sys.exit(main())
