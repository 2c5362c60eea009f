"""The observation cache: one sequence's front end recorded once, to replay the back end on it many times.

The front end (selection, LK + TIM, depth lookup, re-selection) does not depend on the measurement variances, so
a learned weighting is trained by replaying only the back end on what the tracker's back end saw. One file per
sequence, ``<sequence name>.pt``: ``torch.save`` of a dict (read with ``torch.load(weights_only=True)``, no images
needed), written atomically (:func:`torchtrack.io.write_atomic`).

Metadata: ``format`` = ``"torchtrack-observations"``, ``version`` (:data:`VERSION`), ``cue_names`` and
``cue_version`` (:mod:`torchtrack.filter.cues`), ``sequence`` (name), ``source`` (the sequence's folder),
``config`` (the recording's resolved front-end and back-end config, YAML text), ``weighting`` (the weighting's
class path, whose variances are stored).

Tensors, for T frames and N the widest frame's feature count (narrower frames padded with zeros / False). Frames:
``cam`` is the depth camera; ``obj`` the model's object frame (tracker.py: the model frame's depth camera moved to
the centroid of its features); column vectors, ``T_a_b`` maps b coordinates into a.

=====================  ============  ========  =========================================================================
key                    shape         dtype     meaning
=====================  ============  ========  =========================================================================
timestamp              (T,)          float64   s
dt                     (T,)          float64   s since the previous frame, clamped >= 1e-3 as the tracker does; dt[0] = 0
K, K_depth             (3, 3)        float64   colour / depth intrinsics, px (the tracker used them in float32)
T_color_depth          (4, 4)        float64   depth-to-colour extrinsic, m
points_obj             (T, N, 3)     float32   model points X_o in ``obj``, m (the model in use during frame t)
points_d               (T, N, 3)     float32   measured points X_d in ``cam``, m, eq. (6)
pixels                 (T, N, 2)     float32   tracked pixels in the colour image, px, eq. (7)
valid                  (T, N)        bool      the feature is measured (row 0, the first selection: all False)
has_depth              (T, N)        bool      ... with its 3D point (eq. 6); valid and not has_depth: its pixel only
cues                   (T, N, C)     float32   :data:`~torchtrack.filter.cues.CUE_NAMES`; zeros where not valid
var_pix, var_xyz       (T, N)        float32   the recording weighting's variances, px^2 and m^2 (0 in row 0)
reselected             (T,)          bool      a new model was taken at the END of frame t (row 0: the first model)
model_T_cam_obj        (T, 4, 4)     float64   the pose the back end was reset to then (identity where not reselected)
model_frame            (T,)          int64     the frame whose model is in use during frame t (row 0: 0)
T_world_color_gt       (T, 4, 4)     float64   ground-truth colour-camera-to-world (TUM; identity where absent)
gt_valid               (T,)          bool      ground truth present
T_cam_obj_gt           (T, 4, 4)     float64   inv(G[t]) @ G[m] @ model_T_cam_obj[m], G the DEPTH camera's
                                               ground truth T_world_color_gt @ T_color_depth (geometry.rig),
                                               m = model_frame[t]: the current model's true pose (identity where
                                               not valid)
T_cam_obj_gt_valid     (T,)          bool      gt_valid[t] & gt_valid[m]
T_cam_obj_est          (T, 4, 4)     float64   the tracker's estimate (the back end's output; row 0: the model pose)
noise_scale            (T, 2)        float64   the online noise scale k [pix, xyz] after frame t (1 when off; row 0: 1)
noise_dof              (T, 2)        float64   ... and the redundancy behind it (0 when off; row 0: 0)
=====================  ============  ========  =========================================================================

Rows t >= 1 are the back end's input exactly as the tracker passed it (``points_obj``, ``points_d``, ``pixels``,
``valid``, ``has_depth``, ``dt``, ``K``, ``T_color_depth``: :meth:`SequenceObservations.observation`), with its
variances (:meth:`SequenceObservations.variances`) and the noise scale the tracker had before it (row t - 1's). A frame t with ``reselected[t]`` is an update of the OLD model (its row
belongs to model ``model_frame[t]``); the back end is reset to ``model_T_cam_obj[t]`` after it. Replaying the back
end thus reproduces ``T_cam_obj_est``.

The one approximation of replaying with other variances: the front end's decisions that depend on the pose are
those of the recording run — features dropped for their reprojection residual (``outliers.max_residual_px``), the
survivors of a re-selection re-expressed in the new model frame through the then-current estimate, and the frames
at which re-selections happen (the number of surviving features).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import torch
from torch import Tensor

from torchtrack.filter.cues import CUE_NAMES, CUE_VERSION, check_cue_names
from torchtrack.filter.frame import Observation
from torchtrack.filter.weighting import Variances
from torchtrack.geometry import T_inv
from torchtrack.geometry.rig import T_world_depth_from_color
from torchtrack.io import write_atomic

FORMAT = "torchtrack-observations"
VERSION = 4  # 4: noise_scale, noise_dof; 3: has_depth (pixel-only features); 2: T_world_color_gt, T_cam_obj_gt from the depth camera's
_META = ("sequence", "source", "config", "weighting")


@dataclass
class SequenceObservations:
    """One sequence's recorded observations; fields as in the module docstring (metadata strings first)."""

    sequence: str
    source: str
    config: str
    weighting: str
    timestamp: Tensor
    dt: Tensor
    K: Tensor
    K_depth: Tensor
    T_color_depth: Tensor
    points_obj: Tensor
    points_d: Tensor
    pixels: Tensor
    valid: Tensor
    has_depth: Tensor
    cues: Tensor
    var_pix: Tensor
    var_xyz: Tensor
    reselected: Tensor
    model_T_cam_obj: Tensor
    model_frame: Tensor
    T_world_color_gt: Tensor
    gt_valid: Tensor
    T_cam_obj_gt: Tensor
    T_cam_obj_gt_valid: Tensor
    T_cam_obj_est: Tensor
    noise_scale: Tensor
    noise_dof: Tensor

    @property
    def frames(self) -> int:
        """T."""
        return self.valid.shape[0]

    @property
    def width(self) -> int:
        """N, the padded number of features per frame."""
        return self.valid.shape[1]

    def tensors(self) -> dict[str, Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name not in _META}

    def to(self, dtype: torch.dtype) -> SequenceObservations:
        """A copy with every floating tensor in ``dtype`` (masks and indices unchanged)."""
        moved = {k: v.to(dtype) if v.is_floating_point() else v for k, v in self.tensors().items()}
        return SequenceObservations(**{k: getattr(self, k) for k in _META}, **moved)

    def observation(self, t: int) -> Observation:
        """The back end's input of frame t >= 1 with B = 1, as the tracker built it: dt, K and T_color_depth in the
        points' dtype (the tracker's float32, or the dtype of :meth:`to`)."""
        if not 1 <= t < self.frames:
            raise IndexError(f"observation: frame {t} is not in 1..{self.frames - 1}")
        dtype, s = self.points_obj.dtype, slice(t, t + 1)
        return Observation(
            self.dt[s].to(dtype), self.points_obj[s], self.points_d[s], self.pixels[s], self.valid[s],
            self.K[None].to(dtype), self.T_color_depth[None].to(dtype), has_depth=self.has_depth[s],
        )  # fmt: skip

    def variances(self, t: int) -> Variances:
        """The recording weighting's variances of frame t, B = 1."""
        return Variances(self.var_pix[t : t + 1], self.var_xyz[t : t + 1])

    def to_dict(self) -> dict:
        """The cache file's dict (module docstring)."""
        meta = {"format": FORMAT, "version": VERSION, "cue_names": list(CUE_NAMES), "cue_version": CUE_VERSION}
        return {**meta, **{k: getattr(self, k) for k in _META}, **self.tensors()}


def object_poses_gt(
    T_world_color_gt: Tensor, gt_valid: Tensor, reselected: Tensor, model_T_cam_obj: Tensor, T_color_depth: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Ground-truth pose of the model in use in each frame's DEPTH camera (the tracker's ``cam``).

    Args:
        T_world_color_gt: (T, 4, 4) the colour camera's ground truth, camera-to-world; gt_valid (T,) bool.
        reselected: (T,) bool, a model taken at the end of frame t (reselected[0] must be True).
        model_T_cam_obj: (T, 4, 4) the model's pose in its own frame's depth camera (where reselected).
        T_color_depth: (4, 4) the depth-to-colour extrinsic.

    Returns:
        model_frame (T,) int64 (the last s < t with reselected[s]; 0 for t = 0), T_cam_obj_gt (T, 4, 4) float64 =
        inv(G[t]) @ G[m] @ model_T_cam_obj[m] with G the depth camera's ground truth (identity where not valid), and
        its valid mask (T,) = gt_valid[t] & gt_valid[m].
    """
    T = reselected.shape[0]
    if T == 0 or not bool(reselected[0]):
        raise ValueError("object_poses_gt: frame 0 must take the first model (reselected[0] True)")
    idx = torch.arange(T, device="cpu")
    taken = torch.where(reselected, idx, torch.zeros_like(idx))
    model_frame = torch.cat([idx[:1] * 0, taken[:-1]]).cummax(0).values
    G = T_world_depth_from_color(T_world_color_gt, T_color_depth)
    pose = T_inv(G) @ G[model_frame] @ model_T_cam_obj.double()[model_frame]
    valid = gt_valid & gt_valid[model_frame]
    eye = torch.eye(4, dtype=torch.float64, device="cpu").expand(T, 4, 4)
    return model_frame, torch.where(valid[:, None, None], pose, eye), valid


def _shapes(T: int, N: int) -> dict[str, tuple[tuple[int, ...], str]]:
    """Expected shape and kind (f: floating, b: bool, i: int64) of every tensor."""
    C = len(CUE_NAMES)
    per_frame = {k: ((T,), "f") for k in ("timestamp", "dt")}
    per_frame |= {k: ((T,), "b") for k in ("reselected", "gt_valid", "T_cam_obj_gt_valid")}
    per_frame |= {k: ((T, 4, 4), "f") for k in ("model_T_cam_obj", "T_world_color_gt", "T_cam_obj_gt", "T_cam_obj_est")}
    per_frame |= {k: ((T, 2), "f") for k in ("noise_scale", "noise_dof")}
    features = {"points_obj": ((T, N, 3), "f"), "points_d": ((T, N, 3), "f"), "pixels": ((T, N, 2), "f")}
    features |= {"valid": ((T, N), "b"), "has_depth": ((T, N), "b"), "cues": ((T, N, C), "f")}
    features |= {"var_pix": ((T, N), "f"), "var_xyz": ((T, N), "f")}
    const = {"K": ((3, 3), "f"), "K_depth": ((3, 3), "f"), "T_color_depth": ((4, 4), "f")}
    return {**per_frame, **features, **const, "model_frame": ((T,), "i")}


def _kind(t: Tensor) -> str:
    return "f" if t.is_floating_point() else "b" if t.dtype == torch.bool else "i" if t.dtype == torch.int64 else "?"


def validate(obs: SequenceObservations, where: str) -> None:
    """Raise ValueError (naming ``where``) unless every tensor has its documented shape and kind."""
    if obs.valid.ndim != 2:
        raise ValueError(f"{where}: valid must be (T, N), got {tuple(obs.valid.shape)}")
    for name, (shape, kind) in _shapes(*obs.valid.shape).items():
        t = getattr(obs, name)
        if not isinstance(t, Tensor) or tuple(t.shape) != shape or _kind(t) != kind:
            got = f"{tuple(t.shape)} {t.dtype}" if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{where}: field {name!r} must be {shape} ({kind}), got {got}")


def save_observations(obs: SequenceObservations, path: str | Path) -> Path:
    """Write ``obs`` to ``path`` atomically (:func:`torchtrack.io.write_atomic`): a failed write leaves no partial
    file and any previous file intact."""
    path = Path(path)
    validate(obs, str(path))
    return write_atomic(path, lambda tmp: torch.save(obs.to_dict(), tmp))


def load_observations(path: str | Path) -> SequenceObservations:
    """Read a cache file; ValueError naming the file when it is not readable, of another format or version, has
    other cues than this torchtrack, or lacks a field or has a field of the wrong shape."""
    path = Path(path)
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise
    except Exception as e:  # a truncated zip, a pickle error, ...: all mean "corrupt"
        raise ValueError(f"{path}: not a readable observation cache ({type(e).__name__}: {e})") from e
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a torchtrack observation cache (format {FORMAT!r} expected)")
    if data.get("version") != VERSION:
        raise ValueError(
            f"{path}: observation cache version {data.get('version')}, this torchtrack reads version {VERSION}; "
            "re-record it (torchtrack-record)"
        )
    check_cue_names(data.get("cue_names", ()), data.get("cue_version", -1), str(path))
    names = [f.name for f in fields(SequenceObservations)]
    missing = [k for k in names if k not in data]
    if missing:
        raise ValueError(f"{path}: observation cache lacks {missing}")
    obs = SequenceObservations(**{k: data[k] for k in names})
    validate(obs, str(path))
    return obs
