"""Tracking loss: a per-frame health signal, and relocalisation against recent keyframes.

After each frame the tracker's result is checked (:func:`frame_health`): the fraction of the previous frame's
features that LK still tracked with depth, the fraction of those the filter rejected (gate, refit), and the
posterior position standard deviation. A frame failing a threshold is ``lost``. A lost sequence is relocalised:
ORB features of the current frame are matched (Hamming, ratio test) against those of its keyframes (the tracker's one
:class:`~torchtrack.pipeline.keyframes.KeyframeStore`: model frames, and a tracked frame every ``keyframes.every``
frames), whose 3D points in the tracker's world were attached when they were taken, and the camera pose follows from
PnP with RANSAC (OpenCV), refined on the inliers and verified by the inlier count. Where it agrees with the tracked
pose nothing changes; where it differs, the decision (:class:`Relocalisation`) tells the tracker to take a new model
at the relocalised pose. Where it fails, the frame's pose is not trusted (``interrupted``) and every following frame
tries again until one relocalises; frames whose pose is not trusted never become keyframes.

References:
    E. Rublee et al., "ORB: an efficient alternative to SIFT or SURF", ICCV 2011.
    V. Lepetit, F. Moreno-Noguer, P. Fua, "EPnP: an accurate O(n) solution to the PnP problem", IJCV 2009.
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from torchtrack.frontend import PreparedFrame
from torchtrack.geometry import T_inv, rotation_angle
from torchtrack.pipeline.keyframes import KeyframeStore
from torchtrack.pipeline.state import Measure


class Health(NamedTuple):
    """Per-frame health of B sequences, each (B,).

    Attributes:
        survival: features LK tracked with depth / the previous frame's features (0 when it had none).
        rejected: fraction of the tracked features the back end did not use (chi-square gate and refit).
        pos_std: m, posterior position standard deviation (sqrt of the covariance's translation trace).
    """

    survival: Tensor
    rejected: Tensor
    pos_std: Tensor


class LossCheck(NamedTuple):
    """What the loss check did this frame, each (B,): ``lost`` (the health check failed), ``relocalised`` (the
    pose was replaced by a relocalisation), ``interrupted`` (the pose is not trusted: lost and not relocalised, now
    or since an earlier frame), ``inliers`` (PnP inliers of the relocalisation tried, 0 if none); ``health``."""

    lost: Tensor
    relocalised: Tensor
    interrupted: Tensor
    inliers: Tensor
    health: Health


class Relocalisation(NamedTuple):
    """The loss check's decision for one frame, for the tracker to apply: ``T_world_depth`` (B, 4, 4) the camera poses
    found where ``relocalised`` (B,) (a new model is to be taken there; other rows: the tracked pose) and the
    frame's :class:`LossCheck` ``loss``."""

    T_world_depth: Tensor
    relocalised: Tensor
    loss: LossCheck


class Keyframe(NamedTuple):
    """A model frame's ORB descriptors (M, 32) uint8 and their 3D points (M, 3) float64 in the tracker's world."""

    descriptors: np.ndarray
    points_world: np.ndarray


def frame_health(n_prev: Tensor, result) -> Health:
    """Health of a tracked frame from ``n_prev`` (B,) the previous frame's feature count and its
    :class:`~torchtrack.pipeline.state.StepResult` (with ``observation`` and ``estimate``)."""
    tracked = result.observation.valid.sum(1)
    survival = torch.where(n_prev > 0, tracked / n_prev.clamp_min(1), torch.zeros_like(tracked, dtype=torch.float32))
    used = getattr(result.estimate, "used_xyz", None)
    used_n = used.sum(1) if used is not None else tracked
    rejected = torch.where(tracked > 0, 1.0 - used_n / tracked.clamp_min(1), torch.ones_like(survival))
    cov = getattr(result.estimate, "cov", None)
    pos_std = (
        cov[:, 3:6, 3:6].diagonal(dim1=-2, dim2=-1).sum(-1).sqrt() if cov is not None else torch.zeros_like(survival)
    )
    return Health(survival.float(), rejected.float(), pos_std.float())


def orb_features(gray: Tensor, n: int) -> tuple[np.ndarray, np.ndarray | None]:
    """ORB keypoints of ``gray`` (H, W) in [0, 1]: (pixels (M, 2) float32, descriptors (M, 32) uint8 or None)."""
    img = (gray.detach().cpu().numpy() * 255.0).round().clip(0, 255).astype(np.uint8)
    kps, desc = cv2.ORB_create(nfeatures=n).detectAndCompute(img, None)
    return np.array([k.pt for k in kps], dtype=np.float32).reshape(-1, 2), desc


def pnp_pose(
    points_world: np.ndarray, pixels: np.ndarray, K: np.ndarray, reprojection_px: float
) -> tuple[np.ndarray | None, int]:
    """Camera pose from 2D-3D matches by EPnP in RANSAC, refined (Levenberg-Marquardt) on the inliers.

    Args: points_world (M, 3), pixels (M, 2), K (3, 3). Returns (T_cam_world (4, 4) or None, inlier count)."""
    if len(pixels) < 6:
        return None, 0
    obj, img = points_world.astype(np.float64), pixels.astype(np.float64)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        obj, img, K, None, iterationsCount=300, reprojectionError=reprojection_px, confidence=0.999,
        flags=cv2.SOLVEPNP_EPNP,
    )  # fmt: skip
    if not ok or inl is None or len(inl) < 6:
        return None, 0
    inl = inl[:, 0]
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    n = int((np.linalg.norm(proj[:, 0] - img, axis=1) < reprojection_px).sum())
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cv2.Rodrigues(rvec)[0], tvec[:, 0]
    return T, n


class Relocaliser:
    """The loss check and relocalisation of :mod:`torchtrack.pipeline.relocalise`, the tracker's ``relocaliser`` stage:
    after each frame :meth:`check` returns a :class:`Relocalisation` that the tracker applies; where the tracker then
    takes a keyframe, :meth:`add` attaches its ORB descriptors to it.

    Args:
        recover: False (the paper): the loss check only marks lost frames (and warns); no relocalisation, the
            pose goes on as tracked.
        min_survival: lost when fewer than this fraction of the previous frame's features were tracked with depth.
        max_rejected: ... or when the filter rejected more than this fraction of them.
        max_pos_std: m, ... or when the posterior position standard deviation exceeds this.
        orb_features: ORB keypoints per image.
        ratio: Lowe's ratio test on the two nearest descriptors.
        reprojection_px: RANSAC inlier threshold.
        min_inliers: a relocalisation is accepted with at least this many inliers.
        agree_m, agree_deg: a relocalised pose this close to the tracked one confirms it (nothing changes).
    """

    def __init__(
        self,
        *,
        recover: bool = True,
        min_survival: float = 0.25,
        max_rejected: float = 0.95,
        max_pos_std: float = 0.01,
        orb_features: int = 1000,
        ratio: float = 0.8,
        reprojection_px: float = 3.0,
        min_inliers: int = 30,
        agree_m: float = 0.02,
        agree_deg: float = 2.0,
    ) -> None:
        self.recover = recover
        self.min_survival, self.max_rejected, self.max_pos_std = min_survival, max_rejected, max_pos_std
        self.n_orb, self.ratio = orb_features, ratio
        self.reprojection_px, self.min_inliers = reprojection_px, min_inliers
        self.agree_m, self.agree_rad = agree_m, float(np.deg2rad(agree_deg))
        self.reset(0, 0)

    def reset(self, B: int, slots: int, device: torch.device | str | None = None) -> None:
        """Nothing stored for B sequences of a keyframe store with ``slots`` slots each (the tracker's first frame)."""
        self.orb: list[list[Keyframe | None]] = [[None] * slots for _ in range(B)]  # per keyframe slot
        self.interrupted = torch.zeros(B, dtype=torch.bool, device=device)

    def check(self, store: KeyframeStore, frame, cur: PreparedFrame, result, n_prev: Tensor | None) -> Relocalisation:
        """The loss check of the frame ``result`` (a :class:`~torchtrack.pipeline.state.StepResult`) that the tracker
        made of ``frame`` (prepared as ``cur``; ``n_prev`` (B,) the previous frame's feature count, None on the first
        frame), and the relocalisation of the lost sequences against the keyframes of ``store``: the decision, for
        the tracker to apply."""
        B, dev = frame.rgb.shape[0], frame.rgb.device
        zeros = torch.zeros(B, device=dev)
        health = frame_health(n_prev, result) if result.observation is not None else Health(zeros + 1, zeros, zeros)
        lost = frame.active & (
            (health.survival < self.min_survival)
            | (health.rejected > self.max_rejected)
            | (health.pos_std > self.max_pos_std)
        )
        retry = (lost | (self.interrupted & frame.active)) & self.recover
        relocalised = torch.zeros(B, dtype=torch.bool, device=dev)
        inliers = torch.zeros(B, dtype=torch.long, device=dev)
        T_new = result.T_world_depth.clone()
        for b in retry.nonzero()[:, 0].tolist():
            T, inliers[b] = self._relocalise(store, frame, cur, b)
            if T is None:
                continue
            self.interrupted[b] = False
            if not self._agrees(T, result.T_world_depth[b]):
                T_new[b], relocalised[b] = T, True
        self.interrupted |= retry & (inliers < self.min_inliers)
        check = LossCheck(lost, relocalised, self.interrupted & frame.active, inliers, health)
        return Relocalisation(T_new, relocalised, check)

    @staticmethod
    def trusted(decision: Relocalisation) -> Tensor:
        """(B,) bool: the frame's pose is trusted after the decision (not lost, or relocalised, and not interrupted):
        only such a frame may become a keyframe."""
        loss = decision.loss
        return ~loss.interrupted & (~loss.lost | loss.relocalised)

    def add(self, slot: Tensor, cur: PreparedFrame, measure: Measure, T_world_depth: Tensor) -> None:
        """Attach the ORB descriptors of the current frame (prepared as ``cur``, camera ``T_world_depth`` (B, 4, 4)) and
        their 3D points (the frame's ``measure``, eq. 6) in the tracker's world to the keyframes ``slot`` (B,) the store
        just took (-1: none); only when relocalisation is on (``recover``)."""
        for b in (slot >= 0).nonzero()[:, 0].tolist():
            kf = self._describe(cur, measure.row(b), b, T_world_depth[b]) if self.recover else None
            self.orb[b][int(slot[b])] = kf

    # ---------------------------------------------------------------------------------------------- internals
    def _agrees(self, T_a: Tensor, T_b: Tensor) -> bool:
        E = T_inv(T_a.double()) @ T_b.double()
        return bool(E[:3, 3].norm() <= self.agree_m) and bool(rotation_angle(E[:3, :3]) <= self.agree_rad)

    def _describe(self, cur: PreparedFrame, measure: Measure, b: int, T_world_depth: Tensor) -> Keyframe | None:
        """Sequence b's current frame (a keyframe; ``measure``: its measurement, B = 1) as ORB descriptors and world
        points; None with too few."""
        pixels, desc = orb_features(cur.gray[b, 0], self.n_orb)
        if desc is None:
            return None
        points, ok = measure(torch.from_numpy(pixels)[None].to(cur.depth.device))
        points, ok = points[0].double(), ok[0]
        world = (points @ T_world_depth[:3, :3].T.double() + T_world_depth[:3, 3].double())[ok].cpu().numpy()
        return Keyframe(desc[ok.cpu().numpy()], world) if len(world) >= self.min_inliers else None

    def _relocalise(self, store: KeyframeStore, frame, cur: PreparedFrame, b: int) -> tuple[Tensor | None, int]:
        """Sequence b's camera pose T_world_depth (4, 4) from its current frame against its keyframes, newest first;
        (None, best inlier count) when none verifies."""
        keyframes = [self.orb[b][s] for s in store.newest_first(b) if self.orb[b][s] is not None]
        if not keyframes:
            return None, 0
        pixels, desc = orb_features(cur.gray[b, 0], self.n_orb)
        if desc is None:
            return None, 0
        K = frame.K[b].double().cpu().numpy()
        T_depth_color = T_inv(frame.T_color_depth[b].double().cpu())
        best = 0
        matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        for kf in keyframes:
            pairs = [m for m in matcher.knnMatch(desc, kf.descriptors, k=2) if len(m) == 2]
            good = [m[0] for m in pairs if m[0].distance < self.ratio * m[1].distance]
            if len(good) < self.min_inliers:
                continue
            cur, ref = np.array([m.queryIdx for m in good]), np.array([m.trainIdx for m in good])
            T_color_world, n = pnp_pose(kf.points_world[ref], pixels[cur], K, self.reprojection_px)
            best = max(best, n)
            if T_color_world is not None and n >= self.min_inliers:
                T_cam_world = T_depth_color @ torch.from_numpy(T_color_world)
                return T_inv(T_cam_world).to(dtype=torch.float64, device=frame.rgb.device), n  # the frame's device
        return None, best
