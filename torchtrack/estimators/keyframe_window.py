"""The keyframe window of the landmark map as a :func:`~torchtrack.estimators.window.refine_window` problem.

The map keeps, per sequence, S keyframe slots (camera pose ``T_world_kf``, insertion stamp) with up to P features each:
its landmark identity (the same number in every keyframe that saw it: a landmark re-acquired into a new model keeps
its identity), pixel, 3D point measured from depth in that keyframe's depth camera, and the keyframe's measurement
variances (the filter's, eqs. 11-14, that frame's means). The current frame adds the landmarks re-acquired now.
The window's poses are the valid slots, oldest first (the gauge: fixed), then the current camera; its landmarks the
identities seen at least twice (a landmark seen once constrains no pose). The refined landmark positions are returned
per slot feature and per re-acquired landmark, so that every copy of an identity moves together.

Frames: ``world`` is the tracker's world; cameras are depth cameras; pixels colour pixels.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.estimators.window import WindowResult, refine_window
from torchtrack.geometry import T_inv


class KeyframeWindow(NamedTuple):
    """The refined keyframe window, batched over B.

    T_world_kf: (B, S, 4, 4) refined keyframe camera poses (slots as given; the oldest and the unused unchanged).
    T_world_depth: (B, 4, 4) the refined current camera pose.
    world_kf: (B, S, P, 3) the landmark positions of the slots' features (unchanged where not in the window).
    world_now: (B, C, 3) the positions of the re-acquired landmarks (unchanged where not in the window).
    inlier_now: (B, C) bool, the re-acquired landmarks whose 3D and pixel measurements passed the inlier test (True
        where not in the window).
    used: (B,) bool, a window with at least one landmark seen twice; result: the raw :class:`WindowResult`.
    """

    T_world_kf: Tensor
    T_world_depth: Tensor
    world_kf: Tensor
    world_now: Tensor
    inlier_now: Tensor
    used: Tensor
    result: WindowResult


def refine_keyframes(
    T_world_kf: Tensor, stamp: Tensor, ident: Tensor, pixels: Tensor, points: Tensor, valid: Tensor, world: Tensor,
    var_pix: Tensor, var_xyz: Tensor, T_world_depth: Tensor, ident_now: Tensor, pixels_now: Tensor,
    points_now: Tensor, valid_now: Tensor, world_now: Tensor, var_pix_now: Tensor, var_xyz_now: Tensor, K: Tensor,
    T_color_depth: Tensor, refine=refine_window, has_xyz: Tensor | None = None, camera_info: Tensor | None = None,
) -> KeyframeWindow:  # fmt: skip
    """Refine the keyframes, the current camera and the landmarks seen at least twice (module docstring).

    Args:
        T_world_kf: (B, S, 4, 4) keyframe camera poses; stamp: (B, S) insertion order (-1: empty slot).
        ident: (B, S, P) long landmark identities (-1: none); pixels: (B, S, P, 2); points: (B, S, P, 3) measured in
            the keyframe's depth camera; valid: (B, S, P); world: (B, S, P, 3) the landmarks' current positions.
        var_pix, var_xyz: (B, S) the keyframes' measurement variances (px^2, m^2 per coordinate).
        T_world_depth: (B, 4, 4) the current camera; ident_now (B, C), pixels_now (B, C, 2), points_now (B, C, 3),
            valid_now (B, C), world_now (B, C, 3): the re-acquired landmarks; var_pix_now, var_xyz_now: (B,).
        K: (B, 3, 3) colour intrinsics; T_color_depth: (B, 4, 4). refine: the solver (a configured
            :class:`~torchtrack.estimators.window.WindowRefiner` or :func:`refine_window`).
        has_xyz: (B, S, P) bool, the slots' features whose 3D point was measured there (default: all valid); the
            others give their pixel only (a landmark re-acquired into a keyframe keeps its original position).
        camera_info: (B, 6, 6) information of a prior on the left twist ``xi`` of the current camera's
            ``exp(xi) T_cam_world``, ``T_cam_world = T_world_depth^-1`` (the filter's posterior: the same twist as its
            ``T_cam_obj``'s), or None: the current camera is free (the keyframes are never given priors).
    """
    B, S, P = ident.shape
    C = ident_now.shape[1]
    f64 = dict(dtype=torch.float64, device=T_world_kf.device)
    order = torch.sort(torch.where(stamp >= 0, stamp, torch.iinfo(torch.long).max), dim=1).indices  # oldest first
    slot_ok = (stamp >= 0).gather(1, order)  # B,S
    take = lambda x: x.gather(1, order.view(B, S, *[1] * (x.dim() - 2)).expand_as(x))  # noqa: E731
    ids_all = torch.cat([torch.where(valid, ident, -1).gather(1, order[..., None].expand(B, S, P)).reshape(B, S * P),
                         torch.where(valid_now, ident_now, -1)], 1)  # fmt: skip  # B, S*P + C
    cols, n_cols = [], 0
    for b in range(B):  # identities seen twice -> window columns (B is small; P * S + C ~ 1e3)
        ids = ids_all[b]
        u, inv, counts = torch.unique(ids, return_inverse=True, return_counts=True)
        keep = (u >= 0) & (counts >= 2)
        col = torch.cumsum(keep.long(), 0) - 1
        cols.append(torch.where(keep[inv], col[inv], -1))
        n_cols = max(n_cols, int(keep.sum()))
    col = torch.stack(cols)  # B, S*P + C: window column of each observation, -1 outside
    Kn, U = S + 1, max(n_cols, 1)
    obs_col = col.clamp_min(0)
    in_win = col >= 0
    # observations (B, K, U, ...): slots' features then the current frame's
    pix_all = torch.cat([take(pixels.to(**f64)).reshape(B, S * P, 2), pixels_now.to(**f64)], 1)
    pts_all = torch.cat([take(points.to(**f64)).reshape(B, S * P, 3), points_now.to(**f64)], 1)
    wld_all = torch.cat([take(world.to(**f64)).reshape(B, S * P, 3), world_now.to(**f64)], 1)
    pose_of = torch.cat([torch.arange(S, device=ident.device).repeat_interleave(P), torch.full((C,), S, device=ident.device)])
    pose_of = pose_of.expand(B, -1)
    flat = torch.where(in_win, pose_of * U + obs_col, Kn * U)  # B, S*P + C index into K*U (+1: the unused)
    zeros = lambda *s: torch.zeros(B, Kn * U + 1, *s, **f64)  # noqa: E731
    z_pix = zeros(2).scatter(1, flat[..., None].expand(-1, -1, 2), pix_all)[:, :-1]
    z_pts = zeros(3).scatter(1, flat[..., None].expand(-1, -1, 3), pts_all)[:, :-1]
    ok = torch.zeros(B, Kn * U + 1, dtype=torch.bool, device=ident.device).scatter(1, flat, in_win)[:, :-1]
    xyz_all = torch.ones_like(in_win) if has_xyz is None else torch.cat(
        [take(has_xyz).reshape(B, S * P), torch.ones_like(valid_now)], 1)  # fmt: skip
    ok_xyz = torch.zeros(B, Kn * U + 1, dtype=torch.bool, device=ident.device).scatter(1, flat, in_win & xyz_all)[
        :, :-1
    ]
    to_col = torch.where(in_win, obs_col, U)[..., None].expand(-1, -1, 3)
    X0 = torch.zeros(B, U + 1, 3, **f64).scatter(1, to_col, wld_all)[:, :-1]
    vp = torch.cat([take(var_pix.to(**f64)), var_pix_now.to(**f64)[:, None]], 1)  # B,K
    vx = torch.cat([take(var_xyz.to(**f64)), var_xyz_now.to(**f64)[:, None]], 1)
    T_world_cam = torch.cat([take(T_world_kf.to(**f64)), T_world_depth.to(**f64)[:, None]], 1)
    pose_valid = torch.cat([slot_ok, torch.ones(B, 1, dtype=torch.bool, device=ident.device)], 1)
    ok = ok.reshape(B, Kn, U) & pose_valid[..., None]
    ok_xyz = ok_xyz.reshape(B, Kn, U) & ok
    prior = {}
    if camera_info is not None:  # on the current camera only (the last pose)
        info = torch.zeros(B, Kn, 6, 6, **f64)
        info[:, S] = camera_info.to(**f64)
        prior = dict(pose_prior_info=info)
    res = refine(T_inv(T_world_cam), X0, z_pts.reshape(B, Kn, U, 3), z_pix.reshape(B, Kn, U, 2),
                 vx[..., None].expand(B, Kn, U), vp[..., None].expand(B, Kn, U), ok_xyz, ok, K, T_color_depth,
                 pose_valid=pose_valid, **prior)  # fmt: skip
    used = in_win.any(1)
    T_new = T_inv(res.T_cam_world)  # B,K,4,4 in the window's order
    T_slots = torch.empty_like(T_new[:, :S]).scatter(1, order.view(B, S, 1, 1).expand(B, S, 4, 4), T_new[:, :S])
    u4 = used[:, None, None]
    moved = slot_ok.clone()
    moved[:, 0] = False  # the oldest is the gauge: its pose is given back as it came (not through two inverses)
    moved = torch.zeros_like(moved).scatter(1, order, moved) & used[:, None]
    T_slots = torch.where(moved[..., None, None], T_slots, T_world_kf.to(**f64))
    X_new = res.points_world.gather(1, obs_col[..., None].expand(-1, -1, 3))  # B, S*P + C
    X_new = torch.where((in_win & used[:, None])[..., None], X_new, wld_all)
    world_kf = torch.empty_like(X_new[:, : S * P]).view(B, S, P, 3).scatter(
        1, order.view(B, S, 1, 1).expand(B, S, P, 3), X_new[:, : S * P].view(B, S, P, 3))  # fmt: skip
    inl = (res.inlier_xyz & res.inlier_pix)[:, S].gather(1, obs_col[:, S * P :])
    inlier_now = torch.where(in_win[:, S * P :] & used[:, None], inl, True)
    return KeyframeWindow(T_slots, torch.where(u4, T_new[:, S], T_world_depth.to(**f64)), world_kf, X_new[:, S * P :],
                          inlier_now, used, res)  # fmt: skip
