"""Landmark re-acquisition: model points that outlive their model, re-tracked from the keyframe that saw them.

Every model keyframe of the tracker's one store (:class:`~torchtrack.pipeline.keyframes.KeyframeStore`, the last
``keyframes.size`` per sequence) carries its LK images (intensity and SIM) and its model's features, each with its
pixel there and its position in the tracker's world (``per_keyframe`` features each). At a re-selection the landmarks are projected with the current camera pose; those inside the image,
in front of the camera, not occluded (the depth there is not nearer than the predicted one) and seen by their keyframe
from about the current viewpoint are tracked from their keyframe into the current frame by the same combined LK + TIM
tracker (eq. 10), starting at the projection, and kept only when the forward-backward check passes, a second start
converges to the same pixel, the LK photometric residual is small and the depth at the tracked pixel puts the point
within ``max_offset_m`` of the prediction. With ``correct`` the camera pose is then re-fitted (:func:`refine_pose`)
to them together with the current model's features (the prior), and the verified ones enter the new model with their
ORIGINAL world positions: old anchors pull the pose back instead of chaining the drift.

The depth measurement of a pixel belongs to the tracker's frame (:class:`~torchtrack.pipeline.state.Measure`): the
map gets it as an argument.

Frames: ``world`` is the tracker's world (its first camera); ``cam`` the depth camera; pixels are colour pixels.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from torchtrack.frontend import PreparedFrame
from torchtrack.geometry import (
    T_inv,
    project,
    rotation_angle,
    sample_depth,
    se3_log,
    transform_points,
)
from torchtrack.image.flow import FlowFrame, TrackResult, prepare_frame, repeat_frame, zero_frame
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.pose_fit import refine_pose
from torchtrack.pipeline.reselect import MIN_SEPARATION_PX, far_from
from torchtrack.pipeline.state import Measure


class Reacquired(NamedTuple):
    """Landmarks found again in the current frame, all (B, C, ...) with ``valid`` (B, C).

    pixels: (B, C, 2) tracked colour pixels; points_world: (B, C, 3) float64 their stored world positions;
    points_cam: (B, C, 3) the points measured from depth at ``pixels`` (depth camera); cornerness: (B, C, 2);
    T_world_depth: (B, 4, 4) float64 the camera pose the landmarks were verified against (re-fitted with ``correct``).
    """

    pixels: Tensor
    points_world: Tensor
    points_cam: Tensor
    cornerness: Tensor
    valid: Tensor
    T_world_depth: Tensor


class LandmarkMap:
    """The features of the model keyframes of the tracker's :class:`KeyframeStore` (its slots 0 .. size - 1) as world
    landmarks, batched over B.

    Args:
        per_keyframe: landmarks kept per keyframe (the model's first valid features: survivors and re-acquired first).
        max_candidates: at most this many landmarks per sequence are re-tracked at one re-selection (oldest keyframe
            first: the oldest anchors remove the most drift).
        min_separation_px: a landmark closer than this to a tracked feature or to an older landmark is not re-tracked.
        max_residual: largest LK photometric residual (mean absolute grey difference over the window, [0, 1]).
        max_shift_px: largest distance between the tracked pixel and the projection (the drift it may correct).
        max_offset_m: largest distance between the measured and the predicted 3D point, times max(1, z^2).
        occlusion: a projection is occluded where the depth there is nearer than the predicted by this fraction.
        correct: re-fit the camera pose to the re-acquired landmarks and the current model's features
            (:func:`refine_pose`) when ``min_inliers`` landmarks agree.
        inlier_m: the 3D residual's standard deviation in that fit, times max(1, z^2) (pixels: 1 px).
        min_inliers: landmarks needed for a correction (fewer: no correction, the inliers still join the model).
        max_correction_m, max_correction_deg: a larger correction is not applied (a wrong fit, not drift).
        max_angle_deg: re-track only landmarks whose keyframe's rotation and ray to the point are within this angle.
        max_scale: ... and whose depth changed by at most this ratio (LK tracks a translation of the window).
        converge_px, probe_px: a second LK started ``probe_px`` away must end within ``converge_px`` of the first.

    The map is the tracker's ``landmarks`` stage: at a re-selection :meth:`reacquire` gives the landmarks found again
    in the current frame (:class:`Reacquired`), the anchors of the new model, and the camera pose they agree with.
    """

    def __init__(
        self,
        *,
        per_keyframe: int = 128,
        max_candidates: int = 256,
        min_separation_px: float = MIN_SEPARATION_PX,
        max_residual: float = 0.1,
        max_shift_px: float = 30.0,
        max_offset_m: float = 0.1,
        occlusion: float = 0.05,
        correct: bool = True,
        inlier_m: float = 0.02,
        min_inliers: int = 8,
        max_correction_m: float = 0.1,
        max_correction_deg: float = 5.0,
        max_angle_deg: float = 15.0,
        max_scale: float = 1.25,
        converge_px: float = 0.5,
        probe_px: float = 3.0,
    ) -> None:
        if per_keyframe < 1 or max_candidates < 1:
            raise ValueError(f"LandmarkMap: per_keyframe and max_candidates must be >= 1, got "
                             f"{per_keyframe}, {max_candidates}")  # fmt: skip
        self.P, self.C = per_keyframe, max_candidates
        self.min_separation_px, self.max_residual, self.max_shift_px = min_separation_px, max_residual, max_shift_px
        self.max_offset_m, self.occlusion = max_offset_m, occlusion
        self.correct, self.inlier_m, self.min_inliers = correct, inlier_m, min_inliers
        self.max_correction_m, self.max_correction_rad = max_correction_m, math.radians(max_correction_deg)
        self.max_angle_deg, self.max_scale = max_angle_deg, max_scale
        self.converge_px, self.probe_px = converge_px, probe_px
        self.per_slot = False  # True: one LK call per keyframe slot (the reference of the batched call; tests, benches)
        self.reset()

    def reset(self) -> None:
        """No landmarks (the tracker's first frame)."""
        self.gray = self.sim = None  # (S, B, 1, H, W) the keyframes' LK images, per slot of the keyframe store
        self.pyramids: dict[int, FlowFrame] = {}  # LK pyramids of the slots, built on first use (per-slot tracking)
        self.stack: FlowFrame | None = None  # all slots' LK images as one frame of S * B sequences (s * B + b)
        self.pixels = self.world = self.cornerness = self.valid = None  # (B, S, P, ...) the keyframes' features

    def _allocate(self, S: int, gray: Tensor, sim: Tensor | None) -> None:
        P, B, dev = self.P, gray.shape[0], gray.device
        self.gray = torch.zeros(S, *gray.shape, dtype=gray.dtype, device=dev)
        self.sim = None if sim is None else torch.zeros(S, *sim.shape, dtype=sim.dtype, device=dev)
        self.pixels = torch.zeros(B, S, P, 2, device=dev)
        self.world = torch.zeros(B, S, P, 3, dtype=torch.float64, device=dev)
        self.cornerness = torch.zeros(B, S, P, 2, device=dev)
        self.valid = torch.zeros(B, S, P, dtype=torch.bool, device=dev)

    def add(self, store: KeyframeStore, slot: Tensor, cur: PreparedFrame, pixels: Tensor, points_world: Tensor,
            cornerness: Tensor, valid: Tensor) -> None:  # fmt: skip
        """Attach the current frame's LK images and features to the model keyframes ``slot`` (B,) of ``store`` just
        took (-1: none; a tracked keyframe's slot is not one): pixels (B, N, 2), points_world (B, N, 3) in the
        tracker's world, cornerness (B, N, 2), valid (B, N) (the first ``per_keyframe`` valid ones are kept)."""
        if pixels.shape[:2] != valid.shape or points_world.shape[:2] != valid.shape or slot.shape != valid.shape[:1]:
            raise ValueError(f"LandmarkMap.add: pixels, points_world (B, N, .), valid (B, N), slot (B,); got "
                             f"{tuple(pixels.shape)}, {tuple(points_world.shape)}, {tuple(valid.shape)}, {tuple(slot.shape)}")  # fmt: skip
        gray, sim = cur.flow.images[0], (cur.flow.images[1] if cur.flow.has_sim else None)  # what LK tracks
        if self.gray is None:
            self._allocate(store.size, gray, sim)
            images = (self.gray.flatten(0, 1),) + (() if sim is None else (self.sim.flatten(0, 1),))
            self.stack = zero_frame(images, cur.flow.pyramid.levels, max_window=cur.flow.pyramid.max_window)
        rows = (slot >= 0).nonzero().squeeze(1)
        if len(rows) == 0:
            return
        slot = slot[rows]
        for k in slot.unique().tolist():
            self.pyramids.pop(k, None)
        self.gray[slot, rows] = gray[rows]
        if self.sim is not None:
            self.sim[slot, rows] = sim[rows]
        self._store_pyramid(slot, rows, cur.flow)
        order = torch.sort((~valid).to(torch.uint8), dim=1, stable=True).indices[:, : self.P]  # valid first
        self.pixels[rows, slot] = _take(pixels.float(), order, self.P)[rows]
        self.world[rows, slot] = _take(points_world.double(), order, self.P)[rows]
        self.cornerness[rows, slot] = _take(cornerness.float(), order, self.P)[rows]
        self.valid[rows, slot] = _take(valid, order, self.P)[rows]

    def candidates(self, store: KeyframeStore, cur: PreparedFrame, K: Tensor, T_color_depth: Tensor,
                   T_world_depth: Tensor, tracked: Tensor, tracked_valid: Tensor, mask: Tensor):  # fmt: skip
        """The landmarks worth re-tracking, at most ``max_candidates`` per sequence, oldest keyframe first:
        in front of the camera, inside the image (LK's border), not occluded, not near a tracked feature (B, N, 2)
        or an older landmark. Returns (index (B, C) into the flattened (S * P) landmarks, valid (B, C),
        projection (B, C, 2), predicted point in the depth camera (B, C, 3) float64)."""
        B, S, P = self.valid.shape
        H, W = cur.gray.shape[-2:]
        world = self.world.reshape(B, S * P, 3)
        X_cam = transform_points(T_inv(T_world_depth.double()), world)
        X_col = transform_points(T_color_depth.double(), X_cam)
        proj = project(K.double(), X_col).float()
        z = X_col[..., 2]
        border = 12.0
        inside = (proj[..., 0] >= border) & (proj[..., 0] <= W - 1 - border)
        inside &= (proj[..., 1] >= border) & (proj[..., 1] <= H - 1 - border)
        d = sample_depth(cur.depth, proj).double()
        visible = (z > 0.1) & inside & (d > 0) & (d >= z * (1 - self.occlusion))  # nothing nearer in front of it
        live = (self.valid & store.live[:, :S, None]).reshape(B, S * P)  # the model keyframes' slots: 0 .. S-1
        ok = live & visible & mask[:, None] & self._similar_view(store, T_world_depth, world, X_cam)
        ok &= far_from(proj, tracked.float(), tracked_valid, self.min_separation_px)
        age = store.stamp[:, :S, None].expand(B, S, P).reshape(B, S * P)  # smaller = older keyframe
        key = torch.where(ok, age, torch.iinfo(torch.long).max)
        C = min(self.C, S * P)
        index = torch.sort(key, dim=1, stable=True).indices[:, :C]
        ok, proj = ok.gather(1, index), proj.gather(1, index[..., None].expand(-1, -1, 2))
        X_cam = X_cam.gather(1, index[..., None].expand(-1, -1, 3))
        # among themselves: keep a landmark only when no older (earlier in the order) one projects within the gap
        gap = torch.cdist(proj, proj)
        earlier = torch.ones(C, C, dtype=torch.bool, device=ok.device).tril(-1)
        clash = (gap < self.min_separation_px) & earlier & ok[:, None, :]
        return index, ok & ~clash.any(-1), proj, X_cam

    def _similar_view(self, store: KeyframeStore, T_world_depth: Tensor, world: Tensor, X_cam: Tensor) -> Tensor:
        """(B, S * P) bool: the landmark's keyframe saw it from about the current viewpoint (LK tracks translations of
        a window): the cameras' rotation and the two rays to the point differ by at most ``max_angle_deg`` and its
        depth by at most the ``max_scale`` ratio, so its window looks about the same."""
        B, S, P = self.valid.shape
        T_world_kf = store.T_world_kf[:, :S]  # the model keyframes'
        R_rel = T_world_depth[:, None, :3, :3].double().transpose(-1, -2) @ T_world_kf[..., :3, :3]  # B,S,3,3
        near = torch.rad2deg(rotation_angle(R_rel)) <= self.max_angle_deg  # B,S
        X_kf = transform_points(T_inv(T_world_kf).reshape(B * S, 4, 4), world.reshape(B * S, P, 3))
        ratio = X_cam[..., 2] / X_kf.reshape(B, S * P, 3)[..., 2].clamp_min(1e-6)
        scale_ok = (ratio <= self.max_scale) & (ratio >= 1 / self.max_scale)
        ray_kf = world.reshape(B, S, P, 3) - T_world_kf[:, :, None, :3, 3]  # from each camera to the point
        ray_cur = world - T_world_depth[:, None, :3, 3].double()
        cos_ray = torch.nn.functional.cosine_similarity(ray_kf.reshape(B, S * P, 3), ray_cur, dim=-1)
        parallax_ok = cos_ray >= math.cos(math.radians(self.max_angle_deg))
        return near[:, :, None].expand(B, S, P).reshape(B, S * P) & scale_ok & parallax_ok

    def reacquire(self, store: KeyframeStore, flow: Callable, cur: PreparedFrame, measure: Measure,
                  T_world_depth: Tensor, tracked: Tensor, tracked_valid: Tensor, mask: Tensor,
                  tracked_world: Tensor | None = None) -> Reacquired:  # fmt: skip
        """Re-track the visible landmarks of the sequences in ``mask`` (B,) from their keyframes into ``cur`` with
        ``flow`` (the combined LK + TIM tracker, started at the projection under ``T_world_depth`` (B, 4, 4) float64)
        and verify them against the frame's depth (``measure``); ``tracked`` (B, N, 2) / ``tracked_valid`` (B, N): the
        features the model keeps, at ``tracked_world`` (B, N, 3) under the current pose: with ``correct`` they take
        part in the pose fit, so that the landmarks move the pose only as far as they outweigh the current model."""
        B, K, T_color_depth = T_world_depth.shape[0], measure.K, measure.T_color_depth
        if self.gray is None:
            self._allocate(store.size, cur.flow.images[0], cur.flow.images[1] if cur.flow.has_sim else None)
        index, ok, proj, X_pred = self.candidates(store, cur, K, T_color_depth, T_world_depth, tracked, tracked_valid,
                                                  mask)  # fmt: skip
        S, P = store.size, self.P
        slot = index // P
        kf_pix = self.pixels.reshape(B, S * P, 2).gather(1, index[..., None].expand(-1, -1, 2))
        if self.per_slot or not getattr(flow, "pyramids_only", False):  # a flow of its own may read the images
            pixels, good, residual = self._track_per_slot(flow, cur, slot, ok, kf_pix, proj)
        else:
            pixels, good, residual = self._track_batched(flow, cur, slot, ok, kf_pix, proj)
        X_meas, has_depth = measure(pixels)
        z = X_pred[..., 2]
        offset = torch.linalg.vector_norm(X_meas.double() - X_pred, dim=-1)
        shift = torch.linalg.vector_norm(pixels - proj, dim=-1)
        good &= has_depth & (residual <= self.max_residual) & (shift <= self.max_shift_px)
        good &= offset <= self.max_offset_m * z.square().clamp_min(1.0)
        good &= far_from(pixels, tracked.float(), tracked_valid, self.min_separation_px)
        world = self.world.reshape(B, S * P, 3).gather(1, index[..., None].expand(-1, -1, 3))
        corner = self.cornerness.reshape(B, S * P, 2).gather(1, index[..., None].expand(-1, -1, 2))
        T_world_depth = T_world_depth.double()
        if self.correct:
            n = good.shape[1]
            if tracked_world is not None:  # the current model's features: the prior of the fit
                X_tr, has = measure(tracked)
                world = torch.cat([world, tracked_world.double()], 1)
                pixels_fit, X_fit = torch.cat([pixels, tracked.float()], 1), torch.cat([X_meas, X_tr], 1)
                good_fit = torch.cat([good, tracked_valid & has], 1)
            else:
                pixels_fit, X_fit, good_fit = pixels, X_meas, good
            T_world_depth, inl = self._corrected(K, T_color_depth, T_world_depth, world, pixels_fit, X_fit, good_fit, n)
            world, good = world[:, :n], inl[:, :n]
        return Reacquired(pixels, world, X_meas, corner, good, T_world_depth)

    def _verified(self, both: TrackResult, sel: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The tracks of a (B, 2C) call of both starts (below): pixels (B, C, 2), good (B, C) (both tracked, the two
        ends within ``converge_px``) and the LK residual (B, C), of the landmarks ``sel`` (B, C)."""
        n = sel.shape[1]
        tr_points, probe_points = both.points.float().split(n, 1)
        tr_valid, probe_valid = both.valid.split(n, 1)
        same = torch.linalg.vector_norm(tr_points - probe_points, dim=-1) <= self.converge_px
        return tr_points, tr_valid & probe_valid & same, both.residual[:, :n]

    def _track_per_slot(self, flow: Callable, cur: PreparedFrame, slot: Tensor, ok: Tensor, kf_pix: Tensor,
                        proj: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        """The candidates ``ok`` (B, C) re-tracked from their keyframe slots ``slot`` (B, C) with one ``flow`` call per
        slot (batched over B): pixels (B, C, 2) (the projection ``proj`` where not tracked), good (B, C), residual
        (B, C) (inf where not tracked). The reference of :meth:`_track_batched`; the path of a flow other than the combined tracker."""
        pixels, good = proj.clone(), torch.zeros_like(ok)
        residual = torch.full(ok.shape, float("inf"), device=ok.device)
        for s in slot[ok].unique().tolist():  # one LK call per keyframe slot, batched over B
            sel = ok & (slot == s)
            if s not in self.pyramids:
                sim = None if self.sim is None else self.sim[s]
                self.pyramids[s] = prepare_frame(self.gray[s], sim, cur.flow.pyramid.levels)
            # eq. (10), from the keyframe, started at the projection and (second half) probe_px away from it: a second
            # start must converge there too. One call for both (every point's track is independent of the others).
            both = flow(self.pyramids[s], cur.flow, kf_pix.repeat(1, 2, 1), sel.repeat(1, 2), with_residual=True,
                        init=torch.cat([proj, proj + self.probe_px], 1))  # fmt: skip
            tr_points, tr_good, tr_residual = self._verified(both, sel)
            pixels = torch.where(sel[..., None], tr_points, pixels)
            good = torch.where(sel, tr_good, good)
            residual = torch.where(sel, tr_residual, residual)
        return pixels, good, residual

    def _track_batched(self, flow: Callable, cur: PreparedFrame, slot: Tensor, ok: Tensor, kf_pix: Tensor,
                       proj: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # fmt: skip
        """:meth:`_track_per_slot` as ONE ``flow`` call over all S keyframe slots: the slots' frames stacked as S * B
        sequences (:attr:`stack`, kept up to date by :meth:`add`), the current frame repeated S times as next
        (:func:`~torchtrack.image.flow.repeat_frame`, no copy); landmark c of sequence b is tracked in row
        slot[b, c] * B + b. Every track is independent of the others, so each equals its per-slot call's."""
        B, C = ok.shape
        S = self.gray.shape[0]
        kf = self._stacked(cur.flow.pyramid.levels)
        each = lambda x: x[None].expand(S, *x.shape).reshape(S * B, *x.shape[1:])  # noqa: E731  # row s * B + b
        sel = ok[None] & (slot[None] == torch.arange(S, device=ok.device)[:, None, None])  # S,B,C
        both = flow(kf, repeat_frame(cur.flow, S), each(kf_pix).repeat(1, 2, 1), sel.reshape(S * B, C).repeat(1, 2),
                    with_residual=True, init=each(torch.cat([proj, proj + self.probe_px], 1)))  # fmt: skip
        tr_points, tr_good, tr_residual = self._verified(both, sel.reshape(S * B, C))
        at = slot[None].clamp(0, S - 1)  # each landmark's row of its slot

        def pick(x: Tensor) -> Tensor:  # (S * B, C, ...) -> (B, C, ...)
            x = x.view(S, B, C, *x.shape[2:])
            return x.gather(0, at.view(1, B, C, *[1] * (x.dim() - 3)).expand(1, B, C, *x.shape[3:]))[0]

        pixels = torch.where(ok[..., None], pick(tr_points), proj)
        return pixels, ok & pick(tr_good), torch.where(ok, pick(tr_residual), float("inf"))

    def _stacked(self, levels: int) -> FlowFrame:
        """All slots' LK images as one prepared frame of S * B sequences (row s * B + b): zeros at the first
        :meth:`add`, which then copies each new keyframe's pyramid in (not rebuilt); built from the slots' images
        where there is none of ``levels``."""
        if self.stack is None or self.stack.pyramid.levels != levels:
            sim = None if self.sim is None else self.sim.flatten(0, 1)
            self.stack = prepare_frame(self.gray.flatten(0, 1), sim, levels)
        return self.stack

    def _store_pyramid(self, slot: Tensor, rows: Tensor, frame: FlowFrame) -> None:
        """Copy the pyramid of ``frame`` (the current frame's, B sequences) of sequences ``rows`` (R,) into the stack's
        slots ``slot`` (R,): the stack then equals the stack rebuilt from the slots' images. A pyramid of another
        geometry drops the stack (rebuilt on use)."""
        if self.stack is None:
            return
        dst, src = self.stack.pyramid, frame.pyramid
        if (dst.levels, dst.pad, dst.stride, dst.channels) != (src.levels, src.pad, src.stride, 1):
            self.stack = None
            return
        S, B, K = self.gray.shape[0], frame.batch, len(frame.images)
        with torch.inference_mode():  # the pyramids' buffers are inference tensors (build_pyramid)
            for level in range(dst.levels):
                h = dst.size(level)[0] + 2 * dst.pad  # rows of one image of this level; its images are contiguous
                to, of = (p.flat[int(p.row_start[level, 0]) * p.stride :][: p.batch * h * p.stride] for p in (dst, src))
                to, of = to.view(K, S, B, h, dst.stride), of.view(K, B, h, src.stride)
                for s, b in zip(slot.tolist(), rows.tolist(), strict=True):  # plain copies of each image
                    to[:, s, b].copy_(of[:, b])

    def _corrected(self, K: Tensor, T_color_depth: Tensor, T_world_depth: Tensor, world: Tensor, pixels: Tensor,
                   X_meas: Tensor, good: Tensor, n: int) -> tuple[Tensor, Tensor]:  # fmt: skip
        """The camera pose (B, 4, 4) re-fitted to the points (world (B, C, 3), their tracked pixels and measured
        points in the depth camera; the first ``n`` are landmarks, the rest the current model's features) by
        :func:`refine_pose`, and the inliers among ``good`` (B, C). Sequences with fewer than ``min_inliers``
        landmark inliers, or a correction above ``max_correction_m`` / ``max_correction_deg``,
        keep their pose; their landmarks are still filtered by the inlier test under that pose."""
        T_cd = T_color_depth.double()
        T_color_world = T_cd @ T_inv(T_world_depth)
        meas = transform_points(T_cd, X_meas.double())
        fit = refine_pose(K, T_color_world, world, pixels, meas, good, sigma_m=self.inlier_m)
        fit = refine_pose(K, fit.T_color_world, world, pixels, meas, fit.inliers, sigma_m=self.inlier_m)
        T_new = T_inv(fit.T_color_world) @ T_cd
        step = se3_log(T_inv(T_world_depth) @ T_new)
        small = (step[:, :3].norm(dim=-1) <= self.max_correction_m) & (
            step[:, 3:].norm(dim=-1) <= self.max_correction_rad
        )
        use = small & (fit.inliers[:, :n].sum(1) >= self.min_inliers)
        T_out = torch.where(use[:, None, None], T_new, T_world_depth)
        kept = refine_pose(K, T_cd @ T_inv(T_out), world, pixels, meas, good, sigma_m=self.inlier_m, iters=0).inliers
        return T_out, kept


def _take(x: Tensor, order: Tensor, n: int) -> Tensor:
    """x (B, N, ...) at the indices order (B, M) along dim 1, padded to n with zeros (False)."""
    x = x.gather(1, order.view(*order.shape, *[1] * (x.dim() - 2)).expand(-1, -1, *x.shape[2:]))
    if x.shape[1] >= n:
        return x
    return torch.cat([x, torch.zeros(x.shape[0], n - x.shape[1], *x.shape[2:], dtype=x.dtype, device=x.device)], 1)
