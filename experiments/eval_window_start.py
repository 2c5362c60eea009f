"""How a training window starts (issue 22, deliverable 6): validation NLL and drift of learned models under three
starts, on the same scored frames.

The scored frames are frames s+5..s+12 for every window start s = 0, 4, ... of each validation sequence (the split
torchtrack-train draws: ``val_fraction`` and ``train.seed`` over the sorted recordings of OBS). The starts: zero
velocity at frame s+4 (training's default), the ground-truth velocity at s+4 (``train.start_velocity=ground_truth``),
or a 4-frame burn-in from s at rest (``train.burn_in=4``). Every model is evaluated under all three, and eqs. 11-14
(``paper``) with them.

    python experiments/eval_window_start.py OBS zero=RUN0/best.pt gtvel=RUN1/best.pt ...

OBS: a folder of recordings (``torchtrack-record +dataset=synthetic out=OBS``); the models: ``NAME=CHECKPOINT``,
e.g. from ``torchtrack-train '~dataset' 'extra_observations=[OBS]' train.start_velocity=ground_truth``.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from torchtrack.config import CONF_DIR, load_option
from torchtrack.learn.cache import load_observations
from torchtrack.learn.checkpoint import load_checkpoint
from torchtrack.learn.rollout import concat_windows
from torchtrack.learn.train import TrainConfig, evaluate, select_windows, sequence_windows
from torchtrack.learn.train_app import split

WINDOW, BURN_IN, STRIDE = 8, 4, 4


def main(argv: list[str]) -> int:
    torch.set_num_threads(1)
    obs, models = Path(argv[0]), dict(a.split("=", 1) for a in argv[1:])
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="learn", overrides=["~dataset"])
    _, val = split([load_observations(f) for f in sorted(obs.glob("*.pt"))], cfg)
    print("validation:", [s.sequence for s in val])
    base = {**OmegaConf.to_container(cfg.train, resolve=True), "loss": "nll", "window": WINDOW, "stride": STRIDE}
    ekf = instantiate(cfg.filter, jacobian=base["jacobian"])
    # the windows of WINDOW frames starting at s + BURN_IN (each sequence's first, at 0, dropped) score the same
    # frames as the windows of BURN_IN + WINDOW frames starting at s
    late = [sequence_windows(s, WINDOW, STRIDE) for s in val]
    late = concat_windows([select_windows(w, torch.arange(1, w.dt.shape[1])) for w in late])
    early = concat_windows([sequence_windows(s, BURN_IN + WINDOW, STRIDE) for s in val])
    assert torch.equal(late.dt, early.dt[BURN_IN:]) and torch.equal(late.pixels, early.pixels[BURN_IN:])
    starts = {
        "zero": (late, TrainConfig(**base)),
        "gt_velocity": (late, TrainConfig(**{**base, "start_velocity": "ground_truth"})),
        f"burn_in{BURN_IN}": (early, TrainConfig(**{**base, "burn_in": BURN_IN})),
    }
    weightings = {"paper": instantiate(load_option("weighting", "paper"))}
    weightings.update({k: load_checkpoint(v)[0] for k, v in models.items()})
    print("| model | start | windows | NLL per measurement | drift mm | rotation deg |\n|---|---|---|---|---|---|")
    for name, w in weightings.items():
        for start, (win, tc) in starts.items():
            r = evaluate(ekf, w, win, tc)
            print(
                f"| {name} | {start} | {win.dt.shape[1]} | {r['nll']:.4f} | {r['trans_mm']:.4f} | {r['rot_deg']:.4f} |"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
