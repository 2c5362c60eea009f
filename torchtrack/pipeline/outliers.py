"""The outlier stage: the reprojection residual of each tracked feature after the update (eq. 16) and which features
leave the model for it (slipped tracks, non-rigid points, wrong depth)."""

from __future__ import annotations

import torch
from torch import Tensor

from torchtrack.metrics import reprojection_errors


def feature_residuals(
    K: Tensor, T_color_depth: Tensor, T_cam_obj: Tensor, points_obj: Tensor, pixels: Tensor, valid: Tensor
) -> Tensor:
    """(B, N) reprojection error (eq. 16, px) of each feature: model points (B, N, 3) under ``T_cam_obj`` (B, 4, 4)
    against their tracked colour pixels (B, N, 2); inf where undefined (not valid, behind the camera)."""
    T_color_obj = T_color_depth.double() @ T_cam_obj
    err = reprojection_errors(K, T_color_obj, points_obj, pixels, valid).float()
    return torch.nan_to_num(err, nan=float("inf"))


class ResidualDrop:
    """Drops the features whose pixel is farther than ``max_residual_px`` from their model point reprojected with the
    updated pose (None = the paper: every tracked feature stays)."""

    def __init__(self, *, max_residual_px: float | None = 3.0) -> None:
        if max_residual_px is not None and max_residual_px <= 0:
            raise ValueError(f"outliers.max_residual_px must be > 0 (or null), got {max_residual_px}")
        self.max_residual_px = max_residual_px

    def __call__(self, residuals: Tensor, valid: Tensor) -> Tensor:
        """(B, N) the features of ``valid`` (B, N) that stay, given their ``residuals`` (B, N) px."""
        return valid if self.max_residual_px is None else valid & (residuals <= self.max_residual_px)
