"""The schemas of the ``data`` config group (``data=tum``, ``data=synthetic``), with their range checks.

Registered with the other schemas by :mod:`torchtrack.config`; plain dataclasses, so the data layer needs no Hydra.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from torchtrack.data.errors import DataError


@dataclass
class TumDataConfig:
    """A TUM-layout folder, or a list of them tracked together (:class:`torchtrack.data.tum.TumSequence`)."""

    kind: str = "tum"
    root: Any = None  # a folder or a list of folders
    camera: str | None = None  # fr1 | fr2 | fr3 | kinect_default when there is no intrinsics.txt
    intrinsics: list[float] | None = None  # colour [fx, fy, cx, cy] when neither intrinsics.txt nor camera
    depth_intrinsics: list[float] | None = None  # the depth camera's [fx, fy, cx, cy]; null = the colour ones
    depth_scale: float | None = None  # depth units per metre (TUM: 5000); overrides intrinsics.txt (logged)
    max_dt: float = 0.02  # seconds, maximum timestamp difference when associating rgb/depth/groundtruth
    T_color_depth: list[Any] | None = None  # 4x4 depth-to-colour extrinsic; null = registered
    depth_alignment: Any = "none"  # none | auto | [dx, dy] | [dx, dy, s] (see conf/data/tum.yaml)
    intrinsics_camera: str = "colour"  # whose intrinsics the given ones are when a map applies: colour | depth
    max_frames: int | None = None
    stride: int = 1
    on_bad_frame: str = "drop"  # drop (a warning, the filter predicts through the gap) | error (stop the sequence)
    min_depth_fraction: float = 0.01  # a frame with fewer pixels with depth than this fraction is bad
    max_bad_fraction: float = 0.25  # a sequence with more bad frames than this fraction of its frames fails

    def __post_init__(self) -> None:
        _check_common(self)
        if self.root is not None and (not isinstance(self.root, (str, list)) or self.root in ("", [])):
            raise DataError(f"data.root must be a folder or a non-empty list of folders, got {self.root!r}")
        if isinstance(self.root, list) and not all(isinstance(r, str) and r for r in self.root):
            raise DataError(f"data.root: every entry must be a folder, got {self.root!r}")
        for key in ("intrinsics", "depth_intrinsics"):
            k = getattr(self, key)
            if k is not None and (len(k) != 4 or min(k[0], k[1]) <= 0):
                raise DataError(f"data.{key} must be [fx, fy, cx, cy] with fx, fy > 0, got {k}")
        if self.depth_scale is not None and self.depth_scale <= 0:
            raise DataError(f"data.depth_scale must be > 0, got {self.depth_scale}")
        if self.max_dt <= 0:
            raise DataError(f"data.max_dt must be > 0, got {self.max_dt}")
        T = self.T_color_depth
        if T is not None and (len(T) != 4 or any(not isinstance(r, list) or len(r) != 4 for r in T) or not _numbers(T)):
            raise DataError(f"data.T_color_depth must be a 4x4 matrix, got {T}")
        if self.intrinsics_camera not in ("colour", "depth"):
            raise DataError(f"data.intrinsics_camera must be colour or depth, got {self.intrinsics_camera!r}")


@dataclass
class SyntheticDataConfig:
    """The embedded synthetic sequence: ``scene`` is a :class:`torchtrack.data.synthetic.SyntheticConfig`."""

    kind: str = "synthetic"
    cache_dir: str = "${oc.env:TORCHTRACK_CACHE,${oc.env:HOME}/.cache/torchtrack}/synthetic"
    max_frames: int | None = None
    stride: int = 1
    on_bad_frame: str = "drop"  # as TumDataConfig
    min_depth_fraction: float = 0.01
    max_bad_fraction: float = 0.25
    scene: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _check_common(self)


def _numbers(rows: list) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for row in rows for v in row)


def _check_common(data: TumDataConfig | SyntheticDataConfig) -> None:
    if data.max_frames is not None and data.max_frames < 1:
        raise DataError(f"data.max_frames must be >= 1 (or null for all), got {data.max_frames}")
    if data.stride < 1:
        raise DataError(f"data.stride must be >= 1, got {data.stride}")
    if data.on_bad_frame not in ("drop", "error"):
        raise DataError(f"data.on_bad_frame must be drop or error, got {data.on_bad_frame!r}")
    for key in ("min_depth_fraction", "max_bad_fraction"):
        if not 0.0 <= getattr(data, key) <= 1.0:
            raise DataError(f"data.{key} must be in [0, 1], got {getattr(data, key)}")
