"""The one keyframe store of the tracker, batched over B: per sequence the last ``size`` model frames (a ring) and
the latest tracked frame that became a keyframe.

A keyframe is a frame with a trusted pose (not found lost) that is a model frame, or a tracked frame ``every`` frames
after the previous keyframe (a model can last long: the store must stay recent for relocalisation). The store holds
what every user of a keyframe needs, the depth camera's pose in the tracker's world, the time stamp and the insertion
order; the stages that use keyframes attach their own content to the store's slots: the landmarks
(:class:`~torchtrack.pipeline.landmarks.LandmarkMap`) the LK images and the model's features to model keyframes, the
relocaliser (:class:`~torchtrack.pipeline.relocalise.Relocaliser`) ORB descriptors and their 3D points to every
keyframe. The tracker alone decides when a keyframe is taken (:meth:`KeyframeStore.due`, :meth:`KeyframeStore.add`).
"""

from __future__ import annotations

import torch
from torch import Tensor


class KeyframeStore:
    """Per sequence the last ``size`` model keyframes (slots 0 .. size - 1, a ring: the oldest is replaced) and the
    latest tracked keyframe (slot ``size``): S = size + 1 slots.

    Args:
        size: model keyframes kept per sequence.
        every: a tracked (not model) frame becomes a keyframe when this many frames passed since the sequence's last
            keyframe; 0: model frames only.

    Attributes: ``T_world_kf`` (B, S, 4, 4) float64 the keyframes' depth cameras in the tracker's world; ``time``
    (B, S) float64 their time stamps; ``stamp`` (B, S) long insertion order (-1: empty); ``live`` (B, S) bool: the
    slot holds a keyframe.
    """

    def __init__(self, *, size: int = 8, every: int = 10) -> None:
        if size < 1 or every < 0:
            raise ValueError(f"keyframes.size must be >= 1 and keyframes.every >= 0, got {size}, {every}")
        self.size, self.every = size, every
        self.reset(0)

    @property
    def slots(self) -> int:
        """S: the model keyframes' ring and the tracked keyframe's slot."""
        return self.size + 1

    def reset(self, B: int, device: torch.device | str = "cpu") -> None:
        """An empty store for B sequences."""
        S = self.slots
        self.T_world_kf = torch.eye(4, dtype=torch.float64, device=device).repeat(B, S, 1, 1)
        self.time = torch.full((B, S), -float("inf"), dtype=torch.float64, device=device)
        self.stamp = torch.full((B, S), -1, dtype=torch.long, device=device)
        self.live = torch.zeros(B, S, dtype=torch.bool, device=device)
        self.count = torch.zeros(B, dtype=torch.long, device=device)  # keyframes taken
        self.models = torch.zeros(B, dtype=torch.long, device=device)  # model keyframes taken
        self.since = torch.full((B,), self.every, dtype=torch.long, device=device)  # frames since the last keyframe

    @property
    def batch(self) -> int:
        return self.count.shape[0]

    def due(self, reselected: Tensor, active: Tensor) -> Tensor:
        """(B,) bool: this frame is a keyframe if trusted: a new model was taken (``reselected`` (B,)), or ``every``
        frames passed since the last keyframe; counts the ``active`` (B,) frames."""
        self.since = self.since + active.long()
        tracked = (self.since >= self.every) if self.every > 0 else torch.zeros_like(active)
        return active & (reselected | tracked)

    def add(self, timestamp: Tensor, T_world_depth: Tensor, mask: Tensor, model: Tensor) -> Tensor:
        """Take the current frame (time stamps (B,), camera ``T_world_depth`` (B, 4, 4)) as a keyframe of the sequences
        in ``mask`` (B,): a model keyframe where ``model`` (B,), else the tracked one. Returns (B,) long the slot each
        got (-1 where not in ``mask``), for the stages to fill."""
        slot = torch.where(mask, torch.where(model, self._model_slot(T_world_depth), self.size), -1)
        rows = mask.nonzero().squeeze(1)
        s = slot[rows]
        self.T_world_kf[rows, s] = T_world_depth.double()[rows]
        self.time[rows, s] = timestamp.double()[rows]
        self.stamp[rows, s] = self.count[rows]
        self.live[rows, s] = True
        self.count = self.count + mask.long()
        self.models = self.models + (mask & model).long()
        self.since = torch.where(mask, 0, self.since)
        return slot

    def _model_slot(self, T_world_depth: Tensor) -> Tensor:
        """(B,) the slot a new model keyframe at ``T_world_depth`` (B, 4, 4) takes: a free one while there is one; else
        the most redundant stored keyframe, the one nearest in pose to another (stored or the new one; distance
        ``|d t| + 0.3 m/rad |d angle|``; ties: the older), never the newest: the store covers the places the camera
        has been, not only the last ``size`` of them."""
        S, B = self.size, self.count.shape[0]
        T = torch.cat([self.T_world_kf[:, :S], T_world_depth.double()[:, None]], 1)  # B,S+1,4,4
        R = T[..., :3, :3]
        cos = ((torch.einsum("bsij,btij->bst", R, R) - 1) / 2).clamp(-1, 1)
        d = torch.cdist(T[..., :3, 3], T[..., :3, 3]) + 0.3 * torch.arccos(cos)  # B,S+1,S+1
        d = d + torch.eye(S + 1, dtype=d.dtype, device=d.device) * 1e9
        nearest = d[:, :S].amin(-1)  # B,S: each stored keyframe's nearest other
        newest = self.stamp[:, :S].argmax(1)
        nearest[torch.arange(B, device=d.device), newest] = float("inf")
        key = nearest + 1e-9 * self.stamp[:, :S].double()  # ties: the older
        return torch.where(self.models < S, self.models % S, key.argmin(1))

    def newest_first(self, b: int) -> list[int]:
        """Sequence b's live slots, newest keyframe first."""
        order = torch.argsort(self.stamp[b], descending=True).tolist()
        return [s for s in order if bool(self.live[b, s])]
