"""The re-selection stage (paper §III, "model re-selection"): when the tracker takes a new model, where its features
may lie, and how a new model joins the features it keeps (survivors, re-acquired landmarks) with new ones."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.frontend import smooth_depth_mask
from torchtrack.geometry import T_inv, transform_points
from torchtrack.pipeline.state import valid_first

# px: a new feature (or a re-acquired landmark) closer than this to a tracked one shares most of its 21 px LK window,
# so it measures nearly the same texture again; one value for the re-selection and the landmarks.
MIN_SEPARATION_PX = 8.0


class Kept(NamedTuple):
    """Features a re-selection keeps, (B, K, ...): colour pixels, points in the current depth camera, valid, age,
    cornerness (B, K, 2); info (B, K, 3, 3) float64 the information of each point's estimate in the camera
    (:func:`fuse_points`; None: the points are not estimates, zeros: not yet weighed)."""

    pixels: Tensor
    points: Tensor
    valid: Tensor
    age: Tensor
    cornerness: Tensor
    info: Tensor | None = None

    def cat(self, other: Kept) -> Kept:
        """These first, then ``other`` (B, K', ...), in this one's dtypes (an info on one side only: zeros on the
        other)."""
        a, b = _with_info(self, other), _with_info(other, self)
        return Kept(*(x if x is None else torch.cat([x, y.to(x.dtype)], 1) for x, y in zip(a, b, strict=True)))


def _with_info(k: Kept, other: Kept) -> Kept:
    """``k`` with zero information where it has none and ``other`` has some."""
    if k.info is not None or other.info is None:
        return k
    return k._replace(info=other.info.new_zeros(*k.valid.shape, 3, 3))


class NewModel(NamedTuple):
    """A new model's features in the current camera, (B, W, ...): colour pixels, points (depth camera), valid, age,
    cornerness (B, W, 2); info (B, W, 3, 3) the kept points' information (zeros for new ones), None as ``Kept``'s."""

    pixels: Tensor
    points: Tensor
    valid: Tensor
    age: Tensor
    cornerness: Tensor
    info: Tensor | None = None


class PointEstimate(NamedTuple):
    """Model points as estimates (B, N, ...): mean (B, N, 3) float64 in the model frame, info (B, N, 3, 3) float64
    its information (the sum of its samples'; zeros: only the birth sample, not yet weighed)."""

    mean: Tensor
    info: Tensor


def fuse_points(est: PointEstimate, samples: Tensor, var_xyz: Tensor, valid: Tensor) -> PointEstimate:
    """The information-weighted mean of each model point's samples, one more sample per feature in ``valid`` (B, N):
    ``Lambda' = Lambda + S``, ``X' = X + Lambda'^-1 S (x - X)`` with samples ``x`` (B, N, 3) in the model frame and
    their information ``S = I / var_xyz`` (``var_xyz`` (B, N) m^2, the weighting's eq. 14, per coordinate as the filter
    takes it). A point still at its birth sample (zero information) first gives that sample this sample's information
    (as if seen from this viewpoint: consecutive frames). Features not in ``valid`` keep their estimate."""
    B, N = valid.shape
    if est.mean.shape != (B, N, 3) or est.info.shape != (B, N, 3, 3) or samples.shape != (B, N, 3):
        raise ValueError("fuse_points: mean (B, N, 3), info (B, N, 3, 3), samples (B, N, 3), valid (B, N)")
    eye = torch.eye(3, dtype=torch.float64, device=samples.device)
    info = eye / var_xyz.double().clamp_min(1e-18)[..., None, None]
    born = (est.info == 0).flatten(2).all(-1)[..., None, None]
    prior = torch.where(born, info, est.info)
    total = prior + info
    e = (samples.double() - est.mean)[..., None]
    step = torch.linalg.solve(torch.where(valid[..., None, None], total, eye), info @ e)[..., 0]
    v = valid[..., None]
    return PointEstimate(torch.where(v, est.mean + step, est.mean), torch.where(v[..., None], total, est.info))


def far_from(points: Tensor, others: Tensor, others_valid: Tensor, gap: float) -> Tensor:
    """(B, C) bool: each of points (B, C, 2) is at least ``gap`` px from every valid one of others (B, N, 2)."""
    if others.shape[1] == 0:
        return torch.ones(points.shape[:2], dtype=torch.bool, device=points.device)
    d = torch.cdist(points, others).masked_fill(~others_valid[:, None, :], float("inf"))
    return d.amin(2) >= gap


class Reselection:
    """The model stage: where a model's features may lie (``region``, off depth edges), how they are selected
    (``select``, eq. 9), when a new model is taken and what it keeps.

    Args:
        region: ``region(depth (B,1,H,W)) -> (B,1,H,W) bool`` region of interest of the model (object by depth
            thresholding, or the whole frame): the ``region`` config group.
        select: ``select(gray, depth, K, roi=, sim=) -> Features``, spatio-textural selection (eq. 9): ``select``.
        fraction: take a new model when fewer than this fraction of the model's features survive.
        min_features: ... or fewer than this many.
        edge_step: improvement (None = paper): select only where the depth in a 5x5 window varies by less than this
            fraction of the depth (no features on occlusion boundaries).
        keep_survivors: improvement (False = paper): a re-selection keeps the features that still track, with their
            model points (re-expressed in the new model frame through the current pose, so their world positions do
            not change), and adds new ones only where no kept feature is within ``min_separation_px``, up to the
            selector's count. The surviving points keep anchoring the pose, so a re-selection no longer resets the
            model to one frame's estimate (less drift).
        min_separation_px: new features closer than this to a kept one are not added (:data:`MIN_SEPARATION_PX`).
        point_mean: improvement (False = paper: a model point is the one depth sample of its selection);
            True: each model point is estimated, the information-weighted mean (:func:`fuse_points`) of its
            feature's depth samples of every frame moved into the model frame by the filter's posterior pose, and
            survivors carry the mean into the new model (the filter's model stays fixed between re-selections).
    """

    def __init__(
        self,
        *,
        region: Callable,
        select: Callable,
        fraction: float = 0.5,
        min_features: int = 12,
        edge_step: float | None = 0.03,
        keep_survivors: bool = True,
        min_separation_px: float = MIN_SEPARATION_PX,
        point_mean: bool = True,
    ) -> None:
        if not 0.0 <= fraction < 1.0:
            raise ValueError(f"reselect.fraction must be in [0, 1), got {fraction}")
        self.region, self.select = region, select
        self.fraction, self.min_features, self.edge_step = fraction, min_features, edge_step
        self.keep_survivors, self.min_separation_px = keep_survivors, min_separation_px
        if not isinstance(point_mean, bool):
            raise ValueError(f"reselect.point_mean must be true or false, got {point_mean!r}")
        self.point_mean = point_mean

    @property
    def estimates_points(self) -> bool:
        """Whether the model points are estimates (``point_mean``)."""
        return self.point_mean

    def fused(self, est: PointEstimate, T_cam_obj: Tensor, points_d: Tensor, var_xyz: Tensor,
              valid: Tensor) -> PointEstimate:  # fmt: skip
        """``est`` with this frame's samples ``inv(T_cam_obj) X_d`` of the features in ``valid`` (B, N): T_cam_obj
        (B, 4, 4) the filter's posterior pose, points_d (B, N, 3) X_d (eq. 6), var_xyz (B, N) the weighting's 3D
        variances (eq. 14)."""
        samples = transform_points(T_inv(T_cam_obj.double()), points_d.double())
        return fuse_points(est, samples, var_xyz, valid)

    def needed(self, valid: Tensor, n_model: Tensor, active: Tensor) -> Tensor:
        """(B,) bool: too few of the model's ``n_model`` (B,) features survive in ``valid`` (B, N) (a fraction of the
        model's, or an absolute count), in the ``active`` (B,) sequences."""
        n = valid.sum(1)
        return active & ((n < self.fraction * n_model) | (n < self.min_features))

    def roi(self, depth: Tensor) -> Tensor:
        """(B, 1, H, W) bool where new features may be selected in a frame of ``depth`` (B, 1, H, W): the region of
        interest, off depth edges (``edge_step``)."""
        roi = self.region(depth)
        return roi if self.edge_step is None else roi & smooth_depth_mask(depth, self.edge_step)

    def survivors(self, valid: Tensor, mask: Tensor) -> Tensor:
        """(B, N) the features of ``valid`` (B, N) a re-selection of the sequences in ``mask`` (B,) keeps."""
        return valid & mask[:, None] if self.keep_survivors else torch.zeros_like(valid)

    def merge(self, kept: Kept, pixels: Tensor, points: Tensor, valid: Tensor, cornerness: Tensor,
              n_found: Tensor | None, old_width: int) -> NewModel:  # fmt: skip
        """The kept features (B, K) first, then the new ones (B, M) that are at least ``min_separation_px`` from all of
        them, up to the larger of M and ``old_width`` (the current model's width: a poor selection never cuts the
        kept ones); with ``n_found`` (B,) re-acquired landmarks among the kept, per sequence up to the larger of the
        survivors' and the new selection's count, plus those (batched equals looped). Kept features keep their age
        and cornerness; new ones (pixels (B, M, 2), points (B, M, 3) in the camera, cornerness (B, M, 2)) start at 0."""
        apart = far_from(pixels, kept.pixels.to(pixels.dtype), kept.valid, self.min_separation_px)
        ok = torch.cat([kept.valid, valid & apart], 1)
        if n_found is None:
            width = max(valid.shape[1], old_width)
        else:
            n_surv = kept.valid.sum(1) - n_found
            cap = torch.maximum(n_surv, valid.sum(1)) + n_found
            ok = ok & (ok.long().cumsum(1) <= cap[:, None])
            width = int(ok.sum(1).max())
        order = valid_first(ok, width)
        rows = torch.arange(ok.shape[0], device=ok.device)[:, None]
        ok = ok[rows, order]
        pixels = torch.cat([kept.pixels.to(pixels.dtype), pixels], 1)[rows, order]
        points = torch.cat([kept.points.to(points.dtype), points], 1)[rows, order]
        age = torch.cat([kept.age, torch.zeros_like(valid, dtype=torch.long)], 1)[rows, order]
        cornerness = torch.cat([kept.cornerness.to(cornerness.dtype), cornerness], 1)[rows, order]
        info = None if kept.info is None else torch.where(ok[..., None, None], torch.cat(
            [kept.info, kept.info.new_zeros(*valid.shape, 3, 3)], 1)[rows, order], 0.0)  # fmt: skip
        ok3 = ok[..., None]
        return NewModel(
            torch.where(ok3, pixels, 0.0), torch.where(ok3, points, 0.0), ok, torch.where(ok, age, 0),
            torch.where(ok3, cornerness, 0.0), info,
        )  # fmt: skip
