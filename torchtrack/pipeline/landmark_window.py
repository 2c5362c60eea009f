"""The landmark map's windowed refinement (issue 24): landmark identities across keyframes and the refinement at a
re-selection (``landmarks.refine``).

Identities. A model keyframe's features are landmarks; a feature that survives into the next model (a survivor) or a
landmark re-acquired into it is the SAME landmark seen again, so it keeps its identity: at a re-acquisition the map
notes the survivors' identities (their world positions are those of the newest model keyframe's features) and the
re-acquired ones' (``pending``, by pixel), and the next keyframe's features take them where their pixels match; the
others are new landmarks. Each keyframe keeps the 3D point its new landmarks were measured at (in its depth camera;
``has_xyz``): a landmark that joined a model at its stored position has only its pixel measured there.

Refinement. At a re-selection, after the landmarks' update: the keyframes with landmarks (oldest fixed), the current
camera and the landmarks seen at least twice (its survivors and the re-acquired ones included) are refined jointly by
:func:`~torchtrack.estimators.keyframe_window.refine_keyframes` (robust LM, the filter's variances: each keyframe's
mean ones, the current frame's for now). The refined keyframe poses and landmark positions replace the stored ones,
the current camera becomes the back end's pose (``set_pose``) before the new model is chained to it.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.keyframe_window import KeyframeWindow, refine_keyframes
from torchtrack.estimators.window import WindowRefiner
from torchtrack.geometry import T_inv, rigid, se3_log, transform_points

_SAME_M = 1e-4  # a survivor is the newest keyframe's feature at the same world position (float32 round trips: ~1e-6)
_SAME_PX = 1e-3  # a keyframe feature is a pending one at the same pixel (pixels pass through unchanged)


class Identities:
    """Landmark identities of the map's keyframe slots, batched over B: ``ident`` (B, S, P) long (-1: none), ``meas``
    (B, S, P, 3) float64 the 3D points measured in each keyframe's depth camera, ``has_xyz`` (B, S, P)."""

    def __init__(self, B: int, S: int, P: int, device) -> None:
        self.ident = torch.full((B, S, P), -1, dtype=torch.long, device=device)
        self.meas = torch.zeros(B, S, P, 3, dtype=torch.float64, device=device)
        self.has_xyz = torch.zeros(B, S, P, dtype=torch.bool, device=device)
        self.next_id = torch.zeros(B, dtype=torch.long, device=device)
        self.pending: tuple[Tensor, Tensor] | None = None  # pixels (B, M, 2), identities (B, M) of the next keyframe

    def note(self, tracked: Tensor, tracked_world: Tensor, tracked_valid: Tensor, newest_world: Tensor,
             newest_ident: Tensor, newest_valid: Tensor, found: Tensor, found_ident: Tensor, found_ok: Tensor) -> Tensor:  # fmt: skip
        """Remember the identities the next keyframe's features will carry: survivors ``tracked`` (B, N, 2) at
        ``tracked_world`` (B, N, 3) matched to the newest keyframe's features (B, P, 3) / (B, P) / (B, P), and the
        re-acquired ``found`` (B, C, 2) with ``found_ident`` (B, C) where ``found_ok``. Returns the survivors' (B, N)."""
        d = torch.cdist(tracked_world.double(), newest_world.double()).masked_fill(~newest_valid[:, None, :], torch.inf)
        dmin, j = d.min(-1) if d.shape[-1] else (torch.full(tracked.shape[:2], torch.inf), None)
        sid = torch.where(tracked_valid & (dmin < _SAME_M), newest_ident.gather(1, j), -1) if j is not None else \
            torch.full(tracked.shape[:2], -1, dtype=torch.long)  # fmt: skip
        self.pending = (torch.cat([tracked.float(), found.float()], 1),
                        torch.cat([sid, torch.where(found_ok, found_ident, -1)], 1))  # fmt: skip
        return sid

    def assign(self, rows: Tensor, slot: Tensor, pixels: Tensor, valid: Tensor, world: Tensor, T_world_kf: Tensor):
        """The identities of the features (pixels (R, P, 2), valid (R, P), world (R, P, 3)) just stored in ``slot``
        (R,) of the sequences ``rows`` (R,), the keyframe at ``T_world_kf`` (R, 4, 4): pending ones keep theirs, the
        others are new landmarks measured here."""
        ids = torch.full(valid.shape, -1, dtype=torch.long, device=valid.device)
        if self.pending is not None and self.pending[0].shape[1] > 0:
            ppx, pid = self.pending[0][rows], self.pending[1][rows]
            d = torch.cdist(pixels.double(), ppx.double()).masked_fill((pid < 0)[:, None, :], torch.inf)
            dmin, j = d.min(-1)
            ids = torch.where(valid & (dmin < _SAME_PX), pid.gather(1, j), -1)
        new = valid & (ids < 0)
        ids = torch.where(new, self.next_id[rows, None] + torch.cumsum(new.long(), 1) - 1, ids)
        self.next_id[rows] += new.sum(1)
        self.ident[rows, slot] = torch.where(valid, ids, -1)
        self.has_xyz[rows, slot] = new
        self.meas[rows, slot] = transform_points(T_inv(T_world_kf.double()), world.double())
        self.pending = None


class Refined(NamedTuple):
    """T_world_depth: (B, 4, 4) the refined current camera; points_world (B, C, 3) and valid (B, C): the re-acquired
    landmarks' refined positions and inliers; used: (B,) bool, a window was refined."""

    T_world_depth: Tensor
    points_world: Tensor
    valid: Tensor
    used: Tensor


def refine_at_reselection(lm, store, refiner: WindowRefiner, acq, tracked: Tensor, tracked_valid: Tensor,
                          tracked_points: Tensor, tracked_world: Tensor, survivor_ident: Tensor, T_world_depth: Tensor,
                          v_pix: Tensor, v_xyz: Tensor, K: Tensor, T_color_depth: Tensor, mask: Tensor,
                          max_m: float, max_rad: float, camera_cov: Tensor | None = None,
                          xyz_scale: Tensor | None = None) -> Refined:  # fmt: skip
    """Refine the keyframe window of the map ``lm`` (its :class:`Identities` ``lm.ids``, the keyframe store ``store``)
    with the current frame's survivors (``tracked`` (B, N, 2), ``tracked_valid`` (B, N), measured ``tracked_points``
    (B, N, 3), ``tracked_world`` (B, N, 3), ``survivor_ident`` (B, N)) and re-acquired landmarks ``acq``, for the
    sequences in ``mask`` (B,); the current camera starts at ``T_world_depth`` (B, 4, 4); ``v_pix``, ``v_xyz`` (B,)
    the frame's mean variances; a window that moves the camera more than ``max_m`` / ``max_rad`` (the landmark stage's
    ``max_correction_m`` / ``_deg``) is not applied; ``camera_cov`` (B, 6, 6): the current camera's prior covariance
    (the back end's posterior as a left twist, ``pose_covariance``), or None: no prior; ``xyz_scale`` (B,): the
    factor of the keyframes' stored 3D variances (the online noise scale's, as ``v_xyz`` already carries it).
    Updates the map's landmark positions and the store's keyframe poses in place."""
    ids = lm.ids
    var_kf = lm.var_kf if xyz_scale is None else lm.var_kf * xyz_scale.to(lm.var_kf.dtype)[:, None]
    B, S, P = ids.ident.shape
    found = acq.valid & mask[:, None]
    surv = tracked_valid & (survivor_ident >= 0) & mask[:, None]
    has_lm = lm.valid.any(-1)  # slots holding landmarks: the gauge is the oldest of them
    stamp = torch.where(has_lm, store.stamp[:, :S], -1)  # the model keyframes' slots 0 .. S-1 (slot S: the tracked one)
    var_pix = torch.full((B, S), 1.0, dtype=torch.float64, device=mask.device) * v_pix.double()[:, None]
    kw: KeyframeWindow = refine_keyframes(
        store.T_world_kf[:, :S], stamp, ids.ident, lm.pixels, ids.meas, lm.valid, lm.world, var_pix, var_kf,
        T_world_depth, torch.cat([survivor_ident, lm.last_ident], 1), torch.cat([tracked.float(), acq.pixels.float()], 1),
        torch.cat([tracked_points.double(), acq.points_cam.double()], 1), torch.cat([surv, found], 1),
        torch.cat([tracked_world.double(), acq.points_world.double()], 1), v_pix, v_xyz, K, T_color_depth,
        refine=refiner, has_xyz=ids.has_xyz, camera_info=None if camera_cov is None else torch.linalg.inv(camera_cov),
    )  # fmt: skip
    finite = torch.isfinite(kw.T_world_depth).flatten(1).all(1) & torch.isfinite(kw.T_world_kf).flatten(1).all(1)
    finite &= torch.isfinite(kw.world_kf).flatten(1).all(1) & torch.isfinite(kw.world_now).flatten(1).all(1)
    step = se3_log(T_inv(T_world_depth.double()) @ torch.where(finite[:, None, None], kw.T_world_depth, T_world_depth))
    small = (step[:, :3].norm(dim=-1) <= max_m) & (step[:, 3:].norm(dim=-1) <= max_rad)
    used = kw.used & mask & finite & small  # a window that diverged or jumps further than drift changes nothing
    u4 = used[:, None, None, None]
    kf = torch.where(u4 & has_lm[..., None, None], rigid(kw.T_world_kf), store.T_world_kf[:, :S])
    store.T_world_kf = torch.cat([kf, store.T_world_kf[:, S:]], 1)
    lm.world = torch.where(u4, kw.world_kf, lm.world)
    N = tracked.shape[1]
    T = torch.where(used[:, None, None], rigid(kw.T_world_depth), T_world_depth.double())
    points = torch.where(used[:, None, None], kw.world_now[:, N:], acq.points_world.double())
    return Refined(T, points, acq.valid & torch.where(used[:, None], kw.inlier_now[:, N:], True), used)
