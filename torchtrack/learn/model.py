"""Learned measurement weighting: per-feature cues in, per-feature noise variances out (replaces eqs. (11)-(14)).

``LearnedWeighting(inputs) -> Variances(var_pix, var_xyz)``, the interface of
:class:`~torchtrack.filter.weighting.PaperWeighting`, so it drops into the tracker unchanged. It reads
``inputs.cues`` (B, N, C) in :data:`~torchtrack.filter.cues.CUE_NAMES` order (``needs_cues = True`` asks the
tracker to fill them) and ``inputs.valid``; ``inputs.depth`` only for the optional depth prior.

Architecture (DeepSets, permutation-equivariant over the features of a frame)::

    x_i = normalise(cues_i)                       fixed per-cue transforms, :data:`CUE_TRANSFORMS`
    h_i = phi(x_i)                                per-feature MLP, C -> H -> H
    c   = rho([mean_valid h, max_valid h])        frame context, 2H -> H
    s_i = head([h_i, c])                          2H -> H -> 2: log-variance scores (pixel, 3D)
    s_i = soft_clamp(s_i, log_ratio_min, log_ratio_max)

Invalid features are zeroed before the MLP and left out of the pools, so garbage (even NaN) in their slots
changes nothing, and get the nominal variances. Output modes:

* ``"normalised"`` keeps the paper's normalisation (eqs. (11), (14)): ``var_i = sigma2 N exp(s_i) / sum_j
  exp(s_j)`` over the valid features, so their mean is ``sigma2``; the network only redistributes weight.
* ``"absolute"``: ``var_i = sigma2 exp(s_i)``, i.e. the log-variance is the score plus ``log(sigma2)``.

In both modes ``log(var / sigma2)`` of one feature stays in ``[log_ratio_min, log_ratio_max]`` (the soft clamp,
smooth and with nonzero gradient everywhere); ratios are relative because the pixel (px^2) and 3D (m^2) variances
live on different scales. ``depth_var_exponent = e != 0`` then multiplies var_xyz by ``(z / depth_ref)^e`` — after
the normalisation, as PaperWeighting does — a fixed Kinect-style prior the network corrects.

The last layer is zero-initialised: an untrained model outputs ``sigma2_pix``, ``sigma2_xyz`` (times the depth
prior) for every feature, i.e. FixedWeighting.

References: Zaheer et al., "Deep Sets" (NeurIPS 2017); Haarnoja et al., "Backprop KF" (NeurIPS 2016).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn

from torchtrack.filter.cues import CUE_NAMES
from torchtrack.filter.weighting import Variances, WeightingInputs

# Fixed input normalisation, one entry per cue: (kind, scale). Part of the model's definition: changing it
# changes what a checkpoint means (bump checkpoint.VERSION). Kinds:
#   "log1p": log1p(max(x, 0) / scale)  non-negative, heavy-tailed cues; scale = a typical small value
#   "log":   log(max(x, scale))        positive scale-like cues; scale = the floor
#   "id":    x                         cues already in [0, 1]
CUE_TRANSFORMS: dict[str, tuple[str, float]] = {
    "d_tim_int": ("log1p", 0.1),  # px; 0.1 px -> 0.69, D_TIM_CAP = 100 px -> 6.9
    "d_tim_sim": ("log1p", 0.1),  # px
    "sim_won": ("id", 1.0),  # {0, 1}
    "lk_residual": ("log1p", 0.01),  # intensity in [0, 1]: 0.01 ~ 2.5 grey levels
    "depth": ("log", 0.1),  # m, floored at 10 cm: log z, 0 at 1 m
    "centroid_dist": ("log", 0.01),  # m, floored at 1 cm (eq. 13's 1/dist is unbounded at the centroid)
    "cornerness_int": ("id", 1.0),  # [0, 1)
    "cornerness_sim": ("id", 1.0),  # [0, 1)
    "sim_value": ("id", 1.0),  # [0, 1]
    "track_age": ("log1p", 1.0),  # frames
    "prev_reproj": ("log1p", 0.1),  # px
    "u_norm": ("id", 1.0),  # [0, 1]
    "v_norm": ("id", 1.0),  # [0, 1]
    "depth_step": ("log1p", 0.005),  # m; 5 mm (noise at ~1.5 m) -> 0.69, a 1 m edge -> 5.3
    "depth_holes": ("id", 1.0),  # [0, 1]
    "lk_min_eig": ("log1p", 1e-4),  # (1/px)^2 on [0, 1] intensities; 1e-4 ~ the LK tracker's min_eig
    "fb_error": ("log1p", 0.1),  # px, as d_tim_*
}
if tuple(CUE_TRANSFORMS) != CUE_NAMES:  # a new or reordered cue needs a decision here, not a silent default
    raise ImportError(f"torchtrack.learn.model: CUE_TRANSFORMS {list(CUE_TRANSFORMS)} != CUE_NAMES {list(CUE_NAMES)}")

Mode = Literal["normalised", "absolute"]
_CONFIG_KEYS = (
    "mode",
    "sigma2_pix",
    "sigma2_xyz",
    "hidden",
    "depth_var_exponent",
    "depth_ref",
    "log_ratio_min",
    "log_ratio_max",
)


def normalise_cues(cues: Tensor, kinds: Tensor, scales: Tensor) -> Tensor:
    """(..., C) raw cues -> (..., C) network inputs by :data:`CUE_TRANSFORMS`; kinds (C,) 0 id, 1 log1p, 2 log."""
    log1p = torch.log1p(cues.clamp_min(0) / scales)
    log = torch.log(torch.maximum(cues, scales))
    return torch.where(kinds == 1, log1p, torch.where(kinds == 2, log, cues))


def soft_clamp(s: Tensor, lo: float, hi: float) -> Tensor:
    """Smooth clamp into (lo, hi) with lo < 0 < hi: identity to first order at 0 (and exactly 0 at 0), a tanh
    saturation on each side. The gradient is finite everywhere, and positive until tanh rounds to 1 (|s| beyond
    ~9 |bound| in float32, ~19 |bound| in float64), where it is 0, never NaN."""
    return torch.where(s >= 0, hi * torch.tanh(s / hi), lo * torch.tanh(s / lo))


def _mlp(*sizes: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:], strict=True):
        layers += [nn.Linear(a, b), nn.SiLU()]
    return nn.Sequential(*layers)


class LearnedWeighting(nn.Module):
    """Permutation-equivariant learned weighting (module docstring): ``forward(inputs) -> Variances``.

    Args:
        mode: ``"normalised"`` (mean variance over the valid features kept, as eqs. (11)/(14)) or ``"absolute"``.
        sigma2_pix: nominal pixel variance (px^2); sigma2_xyz: nominal 3D variance (m^2) at depth_ref.
        hidden: width H of every hidden layer (H = 32: 5858 parameters with the 17 cues of cue version 2).
        depth_var_exponent: var_xyz x (z / depth_ref)^e after the network (0: none); as PaperWeighting.
        depth_ref: reference depth (m) of that prior.
        log_ratio_min, log_ratio_max: soft bounds of ``log(var / sigma2)`` per feature (before the depth prior);
            the defaults +-7 allow a factor ~1100 either way (~33 in standard deviation).
    """

    needs_cues = True

    def __init__(
        self,
        *,
        mode: Mode = "normalised",
        sigma2_pix: float = 1.0,
        sigma2_xyz: float = 4e-6,
        hidden: int = 32,
        depth_var_exponent: float = 4.0,
        depth_ref: float = 1.0,
        log_ratio_min: float = -7.0,
        log_ratio_max: float = 7.0,
    ) -> None:
        super().__init__()
        if mode not in ("normalised", "absolute"):
            raise ValueError(f"LearnedWeighting: mode must be 'normalised' or 'absolute', got {mode!r}")
        if sigma2_pix <= 0 or sigma2_xyz <= 0 or depth_ref <= 0 or hidden < 1:
            raise ValueError("LearnedWeighting: sigma2_pix, sigma2_xyz, depth_ref and hidden must be > 0")
        if not log_ratio_min < 0 < log_ratio_max:
            raise ValueError(
                f"LearnedWeighting: need log_ratio_min < 0 < log_ratio_max, got {log_ratio_min}, {log_ratio_max}"
            )
        self.mode, self.hidden = mode, int(hidden)
        self.sigma2_pix, self.sigma2_xyz = float(sigma2_pix), float(sigma2_xyz)
        self.depth_var_exponent, self.depth_ref = float(depth_var_exponent), float(depth_ref)
        self.log_ratio_min, self.log_ratio_max = float(log_ratio_min), float(log_ratio_max)
        kind_code = {"id": 0, "log1p": 1, "log": 2}
        kinds = torch.tensor([kind_code[k] for k, _ in CUE_TRANSFORMS.values()], device="cpu")
        scales = torch.tensor([s for _, s in CUE_TRANSFORMS.values()], device="cpu")
        # Fixed by the code, not data: kept out of the state dict (see CUE_TRANSFORMS).
        self.register_buffer("cue_kinds", kinds, persistent=False)
        self.register_buffer("cue_scales", scales, persistent=False)
        C, H = len(CUE_NAMES), self.hidden
        self.phi = _mlp(C, H, H)  # per feature
        self.rho = _mlp(2 * H, H)  # frame context from the pooled features
        self.head = nn.Sequential(*_mlp(2 * H, H), nn.Linear(H, 2))  # -> (s_pix, s_xyz)
        nn.init.zeros_(self.head[-1].weight)  # untrained = constant nominal variances
        nn.init.zeros_(self.head[-1].bias)

    @property
    def config(self) -> dict:
        """The constructor's keyword arguments: ``LearnedWeighting(**m.config)`` rebuilds m's architecture."""
        return {k: getattr(self, k) for k in _CONFIG_KEYS}

    def scores(self, cues: Tensor, valid: Tensor) -> Tensor:
        """cues (B, N, C), valid (B, N) -> (B, N, 2) clamped log-variance scores (pixel, 3D); 0 where invalid."""
        w = self.head[-1].weight
        valid3 = valid[..., None]
        x = torch.where(valid3, cues.to(w.dtype), w.new_zeros(()))  # garbage never enters
        h = self.phi(normalise_cues(x, self.cue_kinds, self.cue_scales))  # B,N,H
        n = valid.sum(-1, keepdim=True)  # B,1
        mean = (h * valid3).sum(-2) / n.clamp_min(1)
        peak = h.masked_fill(~valid3, torch.finfo(h.dtype).min).amax(-2)
        peak = torch.where(n > 0, peak, h.new_zeros(()))  # no valid feature: empty pool = 0
        c = self.rho(torch.cat([mean, peak], -1))  # B,H
        s = self.head(torch.cat([h, c[:, None].expand_as(h)], -1))  # B,N,2
        s = soft_clamp(s, self.log_ratio_min, self.log_ratio_max)
        return torch.where(valid3, s, s.new_zeros(()))

    def forward(self, inputs: WeightingInputs) -> Variances:
        """inputs.cues (B, N, C), valid (B, N), depth (B, N) -> Variances (B, N) in the dtype of inputs.d_tim."""
        valid, cues = inputs.valid, inputs.cues
        if cues is None or cues.ndim != 3 or cues.shape[:2] != valid.shape or cues.shape[2] != len(CUE_NAMES):
            got = None if cues is None else tuple(cues.shape)
            raise ValueError(
                f"LearnedWeighting: expected cues (B, N, {len(CUE_NAMES)}) with valid (B, N) = {tuple(valid.shape)}; got {got}"
            )
        s = self.scores(cues, valid).to(inputs.d_tim.dtype)
        var_pix = self._variances(s[..., 0], valid, self.sigma2_pix)
        var_xyz = self._variances(s[..., 1], valid, self.sigma2_xyz)
        if self.depth_var_exponent != 0.0:  # after the normalisation, as PaperWeighting
            z = torch.where(valid, inputs.depth, torch.full_like(inputs.depth, self.depth_ref)).clamp_min(1e-3)
            var_xyz = var_xyz * (z / self.depth_ref) ** self.depth_var_exponent
        return Variances(var_pix, var_xyz)

    def _variances(self, s: Tensor, valid: Tensor, sigma2: float) -> Tensor:
        """(B, N) scores -> variances; sigma2 where invalid (and, normalised, in a frame without valid feature)."""
        e = torch.where(valid, torch.exp(s), torch.zeros_like(s))  # s is bounded: no overflow
        if self.mode == "absolute":
            return torch.where(valid, sigma2 * e, torch.full_like(s, sigma2))
        n = valid.sum(-1, keepdim=True).to(s.dtype)
        total = e.sum(-1, keepdim=True)
        total = torch.where(n > 0, total, torch.ones_like(total))  # no valid feature: every slot is nominal
        return torch.where(valid, sigma2 * (n * e / total), torch.full_like(s, sigma2))  # eqs. (11)/(14)
