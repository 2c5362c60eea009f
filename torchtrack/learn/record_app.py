"""Console script ``torchtrack-record`` (Hydra app on conf/record.yaml): record sequences' front end
(:func:`torchtrack.learn.record.record_sequences`) or a synthetic training set
(:func:`torchtrack.learn.dataset.build_synthetic_set`) into a cache folder. Separate from :mod:`torchtrack.learn.record`
so that the recording library and the synthetic set do not import each other."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from torchtrack.cli import console_main
from torchtrack.config import CONF_DIR
from torchtrack.data.errors import DataError
from torchtrack.factory import build_sequences
from torchtrack.learn.dataset import build_synthetic_set
from torchtrack.learn.record import RECORDED_GROUPS, record_sequences
from torchtrack.runtime import configure

log = logging.getLogger("torchtrack.record")


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="record")
def app(cfg: DictConfig) -> None:
    configure(cfg.threads)
    out = Path(cfg.out).expanduser()
    try:
        if cfg.get("dataset") is not None:
            paths = build_synthetic_set(cfg, out)
        else:
            paths = record_sequences(cfg, build_sequences(cfg.data), out)
    except (DataError, FileNotFoundError) as e:
        log.error("%s", e)
        sys.exit(2)
    log.info("%d sequence(s) in %s", len(paths), out)


HELP = """\
torchtrack-record: record torchtrack's front end once per sequence, for training a learned weighting.
Tracks each sequence with the pipeline torchtrack would run (selection, LK + TIM, depth, re-selection) and stores
what the filter saw at every frame (features, their cues and variances, ground truth): one file OUT/<sequence>.pt
per sequence. torchtrack-train adds such folders to its training set with extra_observations=[OUT]. Resumable: a
file recorded from the same folder with the same config is kept; one recorded otherwise is recorded again.

Usage: torchtrack-record out=DIR [data=tum data.root=...] [key=value ...]   (or: python -m torchtrack.learn.record_app ...)

== Examples ==
  torchtrack-record data=tum data.root=../shared/data/sun3d_fragment1 out=runs/obs
      one TUM-layout folder: runs/obs/sun3d_fragment1.pt
  torchtrack-record data=tum 'data.root=[../shared/data/sun3d_fragment1,../shared/data/sun3d_fragment2]' out=runs/obs
      two folders, tracked in lockstep
  torchtrack-record +dataset=synthetic out=runs/obs_synthetic
      torchtrack-train's default synthetic set (128 sequences, rendered once into the cache) instead of data

== Keys ==
  out=DIR            (required) the cache folder: one <sequence>.pt per sequence
  batch=4            sequences tracked in lockstep (they must share the image size)
  +dataset=NAME      record a synthetic set instead of data: synthetic (128 sequences of 60 frames at 640x480) |
                     synthetic_tiny (2 sequences of 6 frames at 160x120); its keys: dataset.seeds, dataset.modes,
                     dataset.speeds, dataset.noises, dataset.base.width|height|frames, dataset.batch,
                     dataset.render_workers, dataset.cache_dir (where the renders go)
  threads=1          torch intra-op threads
  hydra.run.dir=DIR  this command's log and resolved config (default OUT/.record/<date>_<time>)

Every torchtrack config group and key applies and sets the pipeline that records: data=tum and data.* (the folders,
intrinsics, depth scale, ...), region=, select=, flow=, frontend=, filter=, weighting=, estimator=, and their keys
(torchtrack --help lists them). A file recorded with other values of the groups it depends on is recorded again:
{groups}.
Print the composed configuration: torchtrack-record --cfg job [overrides]. Hydra's own options: --hydra-help.
""".format(groups=", ".join(RECORDED_GROUPS))


def main() -> None:
    console_main("torchtrack-record", "record", HELP, app)


if __name__ == "__main__":
    main()
