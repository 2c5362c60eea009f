"""Per-feature quality cues: what a learned weighting sees of each tracked feature.

A frame's cues are one (B, N, C) float32 tensor whose last axis follows :data:`CUE_NAMES`. Cues are raw,
finite physical values (pixels, metres, frames); a model normalises them itself. Values that do not exist
for a feature (the SIM tracker did not run, a track failed) are capped at :data:`D_TIM_CAP` pixels, never inf.
Bump :data:`CUE_VERSION` whenever a name, its order or its meaning changes: caches and checkpoints carry it,
and a mismatch is an error.
"""

from __future__ import annotations

import torch
from torch import Tensor

CUE_VERSION = 1
D_TIM_CAP = 100.0  # px; stands for "did not track" in the d_TIM cues

CUE_NAMES: tuple[str, ...] = (
    "d_tim_int",  # px, d_TIM (eq. 10) of the intensity tracker; D_TIM_CAP where it did not run or failed
    "d_tim_sim",  # px, d_TIM of the SIM tracker; D_TIM_CAP where it did not run or failed
    "sim_won",  # 1 where the SIM tracker won (eq. 10, step III), else 0
    "lk_residual",  # mean |I_next(x + d) - I_prev(x)| over the final LK window of the winning tracker, image units
    "depth",  # z of the measured 3D point X_d, m (depth camera)
    "centroid_dist",  # ||X_d - centroid of the frame's valid X_d||, m (eq. 13's cue)
    "cornerness_int",  # normalised intensity Harris cornerness at selection (eq. 9)
    "cornerness_sim",  # normalised SIM Harris cornerness at selection (eq. 9)
    "sim_value",  # shape index (eq. 8) at the tracked pixel, [0, 1]
    "track_age",  # frames since the feature was selected (0 in its selection frame)
    "prev_reproj",  # px, the feature's reprojection residual (eq. 16) in the previous frame; 0 when new
    "u_norm",  # pixel x / image width, [0, 1]
    "v_norm",  # pixel y / image height, [0, 1]
)
CUE_INDEX = {name: i for i, name in enumerate(CUE_NAMES)}


def stack_cues(**cues: Tensor) -> Tensor:
    """Stack named (B, N) cues into (B, N, C) float32 in :data:`CUE_NAMES` order; non-finite values -> D_TIM_CAP.

    Every name of CUE_NAMES must be given, and nothing else."""
    missing, extra = set(CUE_NAMES) - set(cues), set(cues) - set(CUE_NAMES)
    if missing or extra:
        raise ValueError(f"stack_cues: missing {sorted(missing)}, unknown {sorted(extra)}")
    out = torch.stack([cues[n].float() for n in CUE_NAMES], -1)
    return torch.nan_to_num(out, nan=D_TIM_CAP, posinf=D_TIM_CAP, neginf=-D_TIM_CAP)


def check_cue_names(names, version: int, where: str) -> None:
    """Raise a clear error when ``names``/``version`` (from a cache or a checkpoint) differ from this code's."""
    if tuple(names) != CUE_NAMES or int(version) != CUE_VERSION:
        raise ValueError(
            f"{where}: expects cues {list(names)} (cue version {version}); this torchtrack has {list(CUE_NAMES)} "
            f"(cue version {CUE_VERSION}). Re-record the cache or retrain the model."
        )
