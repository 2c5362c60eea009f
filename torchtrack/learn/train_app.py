"""``torchtrack-train``: record the training set (once), train a learned weighting, keep the best checkpoint.

Hydra app on conf/learn.yaml: the pipeline of conf/config.yaml records the observations of ``dataset`` (the
synthetic set by default: no real sequence is needed), plus any recorded caches in ``extra_observations``; the
sequences in ``leave_out`` are dropped (leave-one-sequence-out), ``val_fraction`` of the rest is held out for
validation, and :func:`torchtrack.learn.train.fit` trains ``train.model`` through the filter of ``filter``.
Writes into the run folder: metrics.csv, loss.png, last.pt, best.pt (with the resolved config and the sequence
lists), and copies best.pt to ``export`` when set.
"""

from __future__ import annotations

import logging
import shutil
import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from torchtrack.config import CONF_DIR, exit_on_bad_overrides, load_option
from torchtrack.data.errors import DataError
from torchtrack.io import write_atomic
from torchtrack.learn.cache import SequenceObservations, load_observations
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.train import TrainConfig, evaluate, fit, windows_of
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


def split(sequences: list[SequenceObservations], cfg: DictConfig) -> tuple[list, list]:
    """(train, validation) after dropping ``leave_out``; validation: ``val_fraction`` of them, drawn with the seed."""
    left = [s for s in sequences if s.sequence not in set(cfg.leave_out)]
    if missing := set(cfg.leave_out) - {s.sequence for s in sequences}:
        raise DataError(f"leave_out: no recorded sequence named {sorted(missing)}")
    g = torch.Generator().manual_seed(int(cfg.train.seed))
    order = torch.randperm(len(left), generator=g).tolist()
    n_val = int(round(cfg.val_fraction * len(left))) if len(left) > 1 else 0
    val = [left[i] for i in sorted(order[:n_val])]
    return [left[i] for i in sorted(order[n_val:])], val


def train_from_config(cfg: DictConfig, out: Path, progress: bool = True) -> list[dict]:
    sequences = [load_observations(f) for f in observation_files(cfg)]
    train_seqs, val_seqs = split(sequences, cfg)
    tc = TrainConfig(**OmegaConf.to_container(cfg.train, resolve=True))
    train_w = windows_of(train_seqs, tc.window, tc.stride)
    if train_w is None:
        raise DataError("no training window: the sequences are shorter than train.window or have no ground truth")
    val_w = windows_of(val_seqs, tc.window, tc.stride)
    log.info("training on %d windows of %d sequences, validating on %d windows of %d sequences",
             train_w.dt.shape[1], len(train_seqs), 0 if val_w is None else val_w.dt.shape[1], len(val_seqs))  # fmt: skip
    ekf = instantiate(cfg.filter, jacobian=tc.jacobian)
    torch.manual_seed(tc.seed)
    model = LearnedWeighting(**tc.model)
    extra = {
        "config": OmegaConf.to_yaml(cfg, resolve=True),
        "train_sequences": [s.sequence for s in train_seqs],
        "val_sequences": [s.sequence for s in val_seqs],
    }
    if val_w is not None:  # what the learned model has to beat, on the same validation windows
        for name in ("paper", "fixed"):
            base = instantiate(load_option("weighting", name))
            extra[f"val_{name}"] = evaluate(ekf, base, val_w, tc)
            log.info("validation, weighting=%s: %s", name, _fmt(extra[f"val_{name}"]))
    history = fit(model, ekf, train_w, tc, val=val_w, out_dir=out, extra=extra, progress=progress)
    if cfg.get("export"):
        export(out / "best.pt", Path(cfg.export))
    return history


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
    except (DataError, FileNotFoundError) as e:
        log.error("%s", e)
        sys.exit(2)
    if history:
        best = min(history, key=lambda h: h["select"])
        log.info("best epoch %d: %s", best["epoch"], _fmt({k: v for k, v in best.items() if k != "epoch"}))
    log.info("run folder: %s", out)


def main() -> None:
    logging.getLogger("PIL").setLevel(logging.WARNING)
    exit_on_bad_overrides("torchtrack-train", "learn")  # a bad value: one line, exit code 2
    app()


if __name__ == "__main__":
    main()
