"""``torchtrack-train``: record the training set (once), train a learned weighting, keep the best checkpoint.

Hydra app on conf/learn.yaml: the pipeline of conf/config.yaml records the observations of ``dataset`` (the
synthetic set by default: no real sequence is needed), plus any recorded caches in ``extra_observations``; the
sequences in ``leave_out`` are dropped (leave-one-sequence-out), ``val_fraction`` of the rest is held out for
validation, and :func:`torchtrack.learn.train.fit` trains ``train.model`` (the shipped LearnedWeighting, or any
weighting module its ``_target_`` names, built with the other keys as its arguments) through the filter of
``filter``.
Writes into the run folder: metrics.csv, loss.png, last.pt, best.pt (with the resolved config and the sequence
lists), and copies best.pt to ``export`` when set.
"""

from __future__ import annotations

import logging
import shutil
import sys
from fnmatch import fnmatch
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from torchtrack.cli import console_main
from torchtrack.config import CONF_DIR, load_option
from torchtrack.data.errors import DataError
from torchtrack.io import write_atomic
from torchtrack.learn.cache import SequenceObservations, load_observations
from torchtrack.learn.checkpoint import build_weighting, load_checkpoint
from torchtrack.learn.train import TrainConfig, evaluate, fit, windows_of, worse_than
from torchtrack.runtime import configure

log = logging.getLogger("torchtrack.train")


def observation_files(cfg: DictConfig) -> list[Path]:
    """The dataset's recorded files (recording what is missing) and every .pt of the extra caches."""
    files: list[Path] = []
    if cfg.get("dataset") is not None:
        from torchtrack.learn.dataset import build_synthetic_set

        files += build_synthetic_set(cfg, Path(cfg.observations).expanduser())
    for folder in cfg.extra_observations:
        found = sorted(Path(folder).expanduser().glob("*.pt"))
        if not found:
            raise DataError(f"extra_observations: no .pt files in {folder}")
        files += found
    return files


def held_out(sequences: list[SequenceObservations], patterns) -> list[SequenceObservations]:
    """The sequences whose name matches one of ``patterns`` (fnmatch: a name, or a family such as
    ``*-depthnoise_high-*``); DataError for a pattern that matches none."""
    if missing := [p for p in patterns if not any(fnmatch(s.sequence, p) for s in sequences)]:
        raise DataError(f"leave_out: no recorded sequence matches {missing}")
    return [s for s in sequences if any(fnmatch(s.sequence, p) for p in patterns)]


def split(sequences: list[SequenceObservations], cfg: DictConfig) -> tuple[list, list]:
    """(train, validation) after dropping ``leave_out``; validation: ``val_fraction`` of them, drawn with the seed."""
    out = {id(s) for s in held_out(sequences, cfg.leave_out)}
    left = [s for s in sequences if id(s) not in out]
    g = torch.Generator().manual_seed(int(cfg.train.seed))
    order = torch.randperm(len(left), generator=g).tolist()
    n_val = int(round(cfg.val_fraction * len(left))) if len(left) > 1 else 0
    val = [left[i] for i in sorted(order[:n_val])]
    return [left[i] for i in sorted(order[n_val:])], val


def train_from_config(cfg: DictConfig, out: Path, progress: bool = True) -> list[dict]:
    tc = TrainConfig(**OmegaConf.to_container(cfg.train, resolve=True))
    torch.manual_seed(tc.seed)
    model = build_weighting(tc.model)  # first: a train.model that does not build fails before any recording
    sequences = [load_observations(f) for f in observation_files(cfg)]
    train_seqs, val_seqs = split(sequences, cfg)
    need_gt = tc.loss == "supervised"  # the NLL needs no ground truth: unlabelled windows start at the estimate
    train_w = windows_of(train_seqs, tc.window, tc.stride, need_ground_truth=need_gt)
    if train_w is None:
        raise DataError(_no_window(train_seqs, tc, "training"))
    val_w = windows_of(val_seqs, tc.window, tc.stride, need_ground_truth=need_gt)
    if val_w is None and cfg.val_fraction > 0:  # best.pt would be chosen on the training loss without saying so
        raise DataError(_no_window(val_seqs, tc, "validation") if val_seqs else
                        f"no validation sequence: val_fraction={cfg.val_fraction} of {len(train_seqs)} sequence(s) "
                        "rounds to none; give more sequences, or val_fraction=0 to choose best.pt on the training loss")  # fmt: skip
    log.info("training on %d windows of %d sequences, validating on %d windows of %d sequences",
             train_w.dt.shape[1], len(train_seqs), 0 if val_w is None else val_w.dt.shape[1], len(val_seqs))  # fmt: skip
    for name, w in (("training", train_w), ("validation", val_w)):
        if w is not None and (n := int((~w.gt_valid.any(0)).sum())):
            log.info("%d of the %d %s windows have no ground truth: they start from the tracker's recorded estimate "
                     "and report the NLL only", n, w.dt.shape[1], name)  # fmt: skip
    ekf = instantiate(cfg.filter)
    extra = {
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "train_sequences": [s.sequence for s in train_seqs],
        "val_sequences": [s.sequence for s in val_seqs],
    }
    baselines = {}
    if val_w is not None:  # what the learned model has to beat, on the same validation windows
        for name in ("paper", "fixed"):
            baselines[name] = evaluate(ekf, instantiate(load_option("weighting", name)), val_w, tc)
            extra[f"val_{name}"] = baselines[name]
            log.info("validation, weighting=%s: %s", name, _fmt(baselines[name]))
    history = fit(model, ekf, train_w, tc, val=val_w, out_dir=out, extra=extra, progress=progress, spec=tc.model,
                  baselines=baselines)  # fmt: skip
    if history and baselines:
        best = min(history, key=lambda h: h["select"])
        if worse := worse_than(best, baselines):
            log.warning("the best epoch (%d) is not better than the baselines on the validation windows: %s",
                        best["epoch"], "; ".join(worse))  # fmt: skip
    if history and (left := held_out(sequences, cfg.leave_out)):
        report_held_out(ekf, out / "best.pt", left, tc, need_gt)
    if cfg.get("export"):
        export(out / "best.pt", Path(cfg.export))
    return history


def report_held_out(ekf, best: Path, sequences: list[SequenceObservations], tc: TrainConfig, need_gt: bool) -> None:
    """Log the best model and the baselines on the windows of the left-out sequences (a held-out family)."""
    win = windows_of(sequences, tc.window, tc.stride, need_ground_truth=need_gt)
    if win is None:
        log.warning("%s", _no_window(sequences, tc, "held-out"))
        return
    model = load_checkpoint(best)[0].eval()
    rows = {"learned": evaluate(ekf, model, win, tc)}
    rows |= {name: evaluate(ekf, instantiate(load_option("weighting", name)), win, tc) for name in ("paper", "fixed")}
    log.info("held out (%d windows of %d sequences): %s", win.dt.shape[1], len(sequences),
             "; ".join(f"{name} {_fmt(r)}" for name, r in rows.items()))  # fmt: skip


def _no_window(sequences: list[SequenceObservations], tc: TrainConfig, split: str) -> str:
    """One line: why ``sequences`` give no window (too short, or no ground truth for the supervised loss)."""
    names = ", ".join(s.sequence for s in sequences) or "none"
    if tc.loss == "supervised" and all(s.frames > tc.window for s in sequences):
        return (f"no {split} window: train.loss=supervised needs ground truth and the {split} sequences ({names}) have "
                "none; train.loss=nll needs none (calibration on unlabelled sequences)")  # fmt: skip
    return f"no {split} window: the {split} sequences ({names}) have at most train.window={tc.window} frames"


def export(src: Path, dst: Path) -> None:
    write_atomic(dst, lambda tmp: shutil.copyfile(src, tmp))
    log.info("best checkpoint copied to %s", dst)


def _fmt(stats: dict) -> str:
    return "  ".join(f"{k}={v:.4g}" for k, v in stats.items())


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="learn")
def app(cfg: DictConfig) -> None:
    configure(cfg.threads)
    out = Path(HydraConfig.get().runtime.output_dir)
    try:
        history = train_from_config(cfg, out)
    except (DataError, FileNotFoundError, ImportError) as e:  # ImportError: train.model._target_ (one line)
        log.error("%s", e)
        sys.exit(2)
    if history:
        best = min(history, key=lambda h: h["select"])
        mine = {k: v for k, v in best.items() if k.startswith(("train_", "val_"))}
        log.info("best epoch %d: %s", best["epoch"], _fmt(mine))
    log.info("run folder: %s", out)


HELP = """\
torchtrack-train: train a learned measurement weighting through torchtrack's differentiable fusion EKF.
Records the training set's front end once (the synthetic set by default: no real sequence is needed), then replays
windows of recorded frames through the filter and fits a small network that maps per-feature cues to pixel and 3D
variances. The run folder gets metrics.csv, loss.png, last.pt and best.pt; track with the result:
torchtrack weighting=learned weighting.checkpoint=RUN/best.pt.
The default set is 128 synthetic sequences of 60 frames at 640x480 (eight sensor models: conf/dataset/synthetic.yaml).
The first run renders and records them into the cache ($TORCHTRACK_CACHE, else ~/.cache/torchtrack) and then trains
30 epochs; a quarter of it (seed 0, medium speed: 32 sequences) took 12 min rendering, 3 min recording and 9 min
training on 2 loaded cores. Later runs reuse the cache.

Usage: torchtrack-train [key=value ...]   (or: python -m torchtrack.learn.train_app ...)

== Examples ==
  torchtrack-train
      the default: the synthetic set, 30 epochs of the innovation likelihood (train.loss=nll)
  torchtrack-train 'dataset.seeds=[0]' '~dataset.modes.object' '~dataset.modes.near' '~dataset.speeds.fast' '~dataset.noises.kinect3x_flying' '~dataset.noises.misregistered' '~dataset.noises.blur_light' '~dataset.noises.none' '~dataset.noises.depthnoise_low' '~dataset.noises.depthnoise_high' '~dataset.noises.rig' train.epochs=1 val_fraction=0.5
      a small run: 2 synthetic sequences (a scene and a bare object, medium speed, Kinect noise), one epoch (minutes)
  torchtrack-train train.loss=supervised export=runs/supervised.pt
      the pose-error loss against ground truth; best.pt also copied to runs/supervised.pt
  torchtrack-train 'extra_observations=[runs/obs]' 'leave_out=[sun3d_fragment1]'
      add the sequences torchtrack-record wrote into runs/obs; never train or validate on sun3d_fragment1
  torchtrack-train '~dataset' 'extra_observations=[runs/mine]' val_fraction=0.34
      calibrate the weighting on your sensor: train on your own sequences only, recorded first with
      torchtrack-record data=tum 'data.root=[A,B,C]' out=runs/mine; no groundtruth.txt is needed (train.loss=nll).
      Validation reports the held-out NLL; pose errors only where ground truth exists

== Keys ==
  dataset=synthetic         the synthetic set recorded and trained on: synthetic (128 sequences: 2 seeds x scene,
                            object, bare object, near small object x medium, fast x 8 sensor models) | synthetic_tiny (2
                            sequences of 6 frames at 160x120, for tests: set train.window to 3, stride to 1); keys:
                            dataset.seeds, dataset.modes, dataset.speeds, dataset.noises (~dataset.KEY.NAME drops
                            an entry), dataset.base.width|height|frames, dataset.batch, dataset.render_workers
  extra_observations=[]     more folders of .pt files from torchtrack-record (e.g. real sequences), added to the set
  leave_out=[]              sequence names or patterns (the .pt file names; a family: '*-depthnoise_high-*') never
                            trained or validated on; the best model and eqs. 11-14 are reported on them at the end
  val_fraction=0.2          of the sequences, held out for validation (drawn with train.seed); best.pt is the epoch
                            with the lowest validation loss; none left is an error (a fraction of 0: no validation,
                            best.pt by the training loss). Each epoch's line puts the model beside eqs. 11-14
                            (paper) and the fixed weighting on the same validation windows
  export=null               copy best.pt to this path at the end
  observations=DIR          where the dataset's recordings go (default $TORCHTRACK_CACHE/observations/<dataset.name>)
  threads=1                 torch intra-op threads
  hydra.run.dir=DIR         the run folder (default outputs/train/<date>/<time>)

== train.* keys (the optimisation) ==
  train.epochs=30           passes over the training windows
  train.loss=nll            nll (the innovations' negative log-likelihood: needs no ground truth) | supervised (pose
                            error against ground truth, weighted by train.w_trans=1.0 per m, train.w_rot=1.0 per rad)
  train.lr=0.001            Adam's learning rate; train.weight_decay=0.0, train.clip=1.0 (gradient-norm clip)
  train.window=8            frames per window, replayed from the ground-truth pose of its first frame (nll on
                            unlabelled sequences: from the tracker's recorded estimate)
  train.stride=4            frames between window starts
  train.batch=32            windows per optimiser step
  train.max_windows=null    a random subset of this many training windows per epoch (null: all)
  train.noise_scale=true    replay the filter's online noise scale as the tracker runs it (false: the weighting's R
                            alone; an absolute model, train.model.mode, then gives the level)
  train.gate=0.999          the filter's chi-square gate during training, as in the tracker; train.refit=0.999 likewise
  train.seed=0              initialisation, window order and the validation split
  train.model._target_=torchtrack.learn.model.LearnedWeighting  the weighting trained: any torch module
                            WeightingInputs -> Variances importable by that dotted path (docs/extending.md); the
                            other train.model keys are its constructor's arguments, null ones left to its defaults
  train.model.hidden=32     LearnedWeighting's width
  train.model.mode=null     normalised (the default: relative variances whose mean eqs. 11-14 keep) | absolute;
                            train.model.sigma2_pix, sigma2_xyz, depth_var_exponent, depth_ref: its nominal values
                            (null: its defaults, those of the paper weighting)

Every torchtrack config group and key applies and sets the pipeline that records the sequences and the filter that
training runs through: select=, flow=, frontend=, pipeline=, filter= and their keys (torchtrack --help lists them).
Print the composed configuration: torchtrack-train --cfg job [overrides]. Hydra's own options: --hydra-help.
"""


def main() -> None:
    console_main("torchtrack-train", "learn", HELP, app)


if __name__ == "__main__":
    main()
