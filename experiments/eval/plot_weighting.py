"""What a learned weighting learned: its variances against its main cues, beside eqs. 11-14's, on recorded frames.

    python experiments/eval/plot_weighting.py --observations OBS [--checkpoint CKPT] [--out PNG]

OBS: a folder of observation caches (torchtrack-record, e.g. the synthetic set's); CKPT: a torchtrack-train
checkpoint (default: the shipped torchtrack/learn/weights/default.pt). For every valid feature with depth of every
recorded frame, the model's and eqs. 11-14's (``weighting=paper``) pixel and 3D variances are computed from the
recorded cues; the figure shows their medians (and the model's 25-75 % band) in quantile bins of depth, d_TIM, the
depth step in the 5x5 window and the track age. Both are relative weights (each frame's mean is the nominal, eqs.
11/14), so the curves compare shapes; the online noise scale sets the level at run time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402
from hydra.utils import instantiate  # noqa: E402

from torchtrack.config import load_option  # noqa: E402
from torchtrack.filter.cues import CUE_INDEX  # noqa: E402
from torchtrack.learn.cache import load_observations  # noqa: E402
from torchtrack.learn.checkpoint import load_checkpoint  # noqa: E402
from torchtrack.learn.train import sequence_windows  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[2] / "torchtrack" / "learn" / "weights" / "default.pt"
CUES = (("depth", "depth (m)", 1.0), ("d_tim", "d_TIM (px)", 1.0), ("depth_step", "depth step (mm)", 1e3),
        ("track_age", "track age (frames)", 1.0))  # fmt: skip


def variances(files: list[Path], weightings: dict) -> tuple[dict[str, torch.Tensor], dict[str, tuple]]:
    """Cues (name -> (M,)) and each weighting's (var_pix, var_xyz) (M,) over every valid feature with depth."""
    cues, out = [], {n: ([], []) for n in weightings}
    with torch.no_grad():
        for f in files:
            seq = load_observations(f).to(torch.float64)
            win = sequence_windows(seq, seq.frames - 1, seq.frames, need_ground_truth=False)
            if win is None:
                continue
            for t in range(win.frames):
                inputs = win.weighting_inputs(t)
                v = inputs.valid[0]
                c = inputs.cues[0][v]
                cues.append(torch.stack([c[:, CUE_INDEX["depth"]], inputs.d_tim[0][v], c[:, CUE_INDEX["depth_step"]],
                                         c[:, CUE_INDEX["track_age"]]], -1))  # fmt: skip
                for name, w in weightings.items():
                    var = w(inputs)
                    out[name][0].append(var.var_pix[0][v])
                    out[name][1].append(var.var_xyz[0][v])
    c = torch.cat(cues)
    return {n: c[:, i] for i, (n, _, _) in enumerate(CUES)}, {
        n: (torch.cat(p), torch.cat(x)) for n, (p, x) in out.items()
    }


def binned(x: torch.Tensor, y: torch.Tensor, bins: int = 12) -> tuple[list, list, list, list]:
    """Quantile bins of x: centre (median x), and y's median, 25 % and 75 % per bin."""
    edges = torch.quantile(x, torch.linspace(0, 1, bins + 1, dtype=x.dtype))
    cx, med, lo, hi = [], [], [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        m = (x >= a) & (x <= b)
        if int(m.sum()) < 5:
            continue
        q = torch.quantile(y[m], torch.tensor([0.5, 0.25, 0.75], dtype=y.dtype))
        cx.append(float(x[m].median()))
        med.append(float(q[0]))
        lo.append(float(q[1]))
        hi.append(float(q[2]))
    return cx, med, lo, hi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)  # fmt: skip
    ap.add_argument("--observations", type=Path, required=True, help="a folder of observation caches (*.pt)")
    ap.add_argument("--checkpoint", type=Path, default=SHIPPED, help="a torchtrack-train checkpoint")
    ap.add_argument("--out", type=Path, default=Path("learned-weighting-cues.png"), help="the figure")
    args = ap.parse_args()
    files = sorted(args.observations.glob("*.pt"))
    if not files:
        raise SystemExit(f"{args.observations}: no observation caches (*.pt)")
    model = load_checkpoint(args.checkpoint)[0].double().eval()
    paper = instantiate(load_option("weighting", "paper"))
    cues, var = variances(files, {"learned": model, "eqs. 11-14": paper})
    fig, axes = plt.subplots(2, len(CUES), figsize=(4 * len(CUES), 6.5), sharey="row")
    for j, (name, label, unit) in enumerate(CUES):
        x = cues[name].clamp_min(1e-3) if name == "d_tim" else cues[name]  # log axis: d_TIM of 0 shown at 1e-3 px
        for i, (ylabel, scale) in enumerate((("pixel sd (px)", 1.0), ("3D sd (mm)", 1e3))):
            ax = axes[i, j]
            for wname, style in (("learned", "C0"), ("eqs. 11-14", "C1")):
                y = var[wname][i].sqrt() * scale
                cx, med, lo, hi = binned(x, y)
                cx = [unit * v for v in cx]
                ax.plot(cx, med, marker="o", ms=3, color=style, label=wname)
                if wname == "learned":
                    ax.fill_between(cx, lo, hi, color=style, alpha=0.2)
            ax.set_yscale("log")
            if name == "d_tim":
                ax.set_xscale("log")
            elif name in ("depth_step", "track_age"):
                ax.set_xscale("symlog", linthresh=1.0)
            ax.grid(alpha=0.3)
            ax.set_xlabel(label)
            if j == 0:
                ax.set_ylabel(ylabel)
    axes[0, 0].legend()
    fig.suptitle(f"{args.checkpoint.name} on {len(files)} recorded sequences ({len(cues['depth'])} feature-frames): "
                 "median and 25-75 % of the learned sd per cue bin, eqs. 11-14's median")  # fmt: skip
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
