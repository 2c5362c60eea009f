"""Configuration of a synthetic RGB-D sequence: camera, motion, noise, seed. Validated at construction."""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field

# Bump when the renderer's output for a given config changes, so that cached sequences are re-rendered.
RENDERER_VERSION = "1"

MODES = ("scene", "object")
NOISES = ("kinect", "none")
OBJECTS = ("compound", "small")  # object mode: the ~30 cm compound object, or a ~15 cm one (the object case)


@dataclass
class KinectNoise:
    """Kinect v1-like sensor model, applied per frame when ``SyntheticConfig.noise == "kinect"``.

    Axial depth noise: ``sigma(z) = a + b * (z - z0)^2`` metres, the fit of Nguyen, Izadi & Lovell,
    "Modeling Kinect Sensor Noise for Improved 3D Reconstruction and Tracking" (3DIMPVT 2012):
    a = 1.2 mm, b = 1.9e-3 1/m, z0 = 0.4 m (surfaces facing the sensor). Khoshelham & Elberink,
    "Accuracy and Resolution of Kinect Depth Data for Indoor Mapping Applications" (Sensors 12(2), 2012)
    give ``sigma = 1.425e-3 * z^2`` (a = 0, z0 = 0): a few mm at 1 m, about 4 cm at 5 m.

    Quantisation: Kinect measures disparity in 1/8 pixel steps with a ~580 px IR focal length and a
    7.5 cm projector baseline (Khoshelham & Elberink 2012), so depth steps are ``z^2 / (f b) / 8``
    (2.9 mm at 1 m, 7 cm at 5 m). ``disparity_subpixel = 0`` switches quantisation off.

    Holes: pixels whose 4-neighbourhood depth jump exceeds ``edge_jump_m`` lose their depth (dilated
    by ``edge_dilate_px``), plus i.i.d. dropouts with probability ``dropout_prob`` and the sensor's
    working range ``[min_depth_m, max_depth_m]``. Colour gets i.i.d. Gaussian noise ``rgb_sigma``.
    """

    sigma_a_m: float = 0.0012
    sigma_b_per_m: float = 0.0019
    sigma_z0_m: float = 0.4
    disparity_focal_px: float = 580.0
    disparity_baseline_m: float = 0.075
    disparity_subpixel: float = 0.125
    edge_jump_m: float = 0.05
    edge_dilate_px: int = 1
    dropout_prob: float = 0.005
    min_depth_m: float = 0.4
    max_depth_m: float = 6.0
    rgb_sigma: float = 0.01
    sigma_scale: float = 1.0  # the axial noise is sigma_scale * sigma(z): a sensor noisier or cleaner than the fit


@dataclass
class SensorEffects:
    """Effects of real RGB-D sensors beyond :class:`KinectNoise` (:mod:`torchtrack.data.synthetic.effects`), each
    off at its default. Frame i's time is ``t_i = i / fps``; ground truth stays the colour camera's pose at t_i.

    * ``depth_shift_px = (dx, dy)``: depth misregistered against colour by whole pixels,
      ``depth_out[v, u] = depth[v - dy, u - dx]`` (0 where that falls outside), as a miscalibrated extrinsic.
    * ``depth_time_offset_s``: the depth image is taken at ``t_i + offset`` (unsynchronised streams, e.g. 7-Scenes).
    * ``flying_pixel_prob``: each pixel at a depth edge (the clean depth of its 3 x 3 neighbourhood spans more than
      ``KinectNoise.edge_jump_m``) reads, with this probability, ``lo + a (hi - lo)``, a ~ U(0, 1), lo/hi the
      neighbourhood's smallest/largest clean depth: a mixed return between the two surfaces (after the noise, so
      it also fills the edge holes the Kinect model cuts).
    * ``blur_exposure_s``: colour averaged over ``blur_samples`` poses evenly spaced over
      ``[t_i - e / 2, t_i + e / 2]`` (motion blur; depth is not blurred).
    * ``light_gain_amplitude = A``: colour (before its noise) times ``1 + A sin(2 pi t_i / light_period_s)``,
      clamped to [0, 1]: a global lighting change over time (brightness constancy broken).
    """

    depth_shift_px: tuple[int, int] = (0, 0)
    depth_time_offset_s: float = 0.0
    flying_pixel_prob: float = 0.0
    blur_exposure_s: float = 0.0
    blur_samples: int = 5
    light_gain_amplitude: float = 0.0
    light_period_s: float = 4.0

    def __post_init__(self) -> None:
        self.depth_shift_px = tuple(int(v) for v in self.depth_shift_px)
        if len(self.depth_shift_px) != 2:
            raise ValueError(f"SensorEffects.depth_shift_px must be (dx, dy), got {self.depth_shift_px}")
        if not 0 <= self.flying_pixel_prob <= 1 or self.blur_exposure_s < 0 or self.blur_samples < 1:
            raise ValueError(f"SensorEffects: need flying_pixel_prob in [0, 1], blur_exposure_s >= 0, blur_samples >= 1: "
                             f"{self}")  # fmt: skip
        if not 0 <= self.light_gain_amplitude < 1 or self.light_period_s <= 0:
            raise ValueError(f"SensorEffects: need light_gain_amplitude in [0, 1), light_period_s > 0: {self}")


@dataclass
class SyntheticConfig:
    """Everything that determines a synthetic sequence (its hash names the cached folder).

    ``mode="scene"``: static textured room corner with props, moving camera; ground truth T_world_cam.
    ``mode="object"``: static camera, one compound object moving (rotating about its own centre) in
    front of an optional far background; ground truth T_obj_cam (world := object) and T_cam_obj.
    ``background`` (object mode only): the room behind the object, else empty space (depth 0).
    ``object`` (object mode only): ``"compound"`` (box, sphere, two cylinders, ~30 cm, seen from 0.9 m) or
    ``"small"`` (an ~18 cm textured box with a sphere and a cylinder, seen from ``object_distance_m``, 0.55 m by
    default: it fills about 5-10 % of the image, the object case).
    ``object_distance_m``: camera-to-object-centre distance in metres (None: the object's default).
    Intrinsics left as None are derived from the image size (525 px focal at 640 x 480, centre
    ``(W - 1) / 2, (H - 1) / 2``). Motion: smooth sums of sinusoids whose RMS step per frame is
    ``trans_step_m`` metres and ``rot_step_deg`` degrees.
    ``depth_camera`` (None: depth registered to colour): a second camera for the depth images, same image size,
    ``{"fx", "fy", "cx", "cy", "T_color_depth"}`` (its intrinsics and the 4x4 depth-to-colour extrinsic, row-major
    nested lists); ground truth stays the colour camera's, as in TUM.
    """

    width: int = 640
    height: int = 480
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    frames: int = 30
    seed: int = 0
    mode: str = "scene"
    noise: str = "kinect"
    background: bool = True
    trans_step_m: float = 0.01
    rot_step_deg: float = 1.0
    fps: float = 30.0
    depth_scale: float = 5000.0
    kinect: KinectNoise = field(default_factory=KinectNoise)
    depth_camera: dict | None = None
    object: str = "compound"
    object_distance_m: float | None = None
    effects: SensorEffects = field(default_factory=SensorEffects)

    def __post_init__(self) -> None:
        if isinstance(self.kinect, dict):  # from JSON / Hydra
            self.kinect = KinectNoise(**self.kinect)
        if isinstance(self.effects, dict):
            self.effects = SensorEffects(**self.effects)
        if self.mode not in MODES:
            raise ValueError(f"SyntheticConfig.mode must be one of {MODES}, got {self.mode!r}")
        if self.object not in OBJECTS:
            raise ValueError(f"SyntheticConfig.object must be one of {OBJECTS}, got {self.object!r}")
        if self.object_distance_m is not None and self.object_distance_m <= 0.1:
            raise ValueError(f"SyntheticConfig.object_distance_m must be > 0.1 m, got {self.object_distance_m}")
        if self.noise not in NOISES:
            raise ValueError(f"SyntheticConfig.noise must be one of {NOISES}, got {self.noise!r}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"SyntheticConfig image size must be at least 16x16, got {self.width}x{self.height}")
        if self.frames < 1:
            raise ValueError(f"SyntheticConfig.frames must be >= 1, got {self.frames}")
        if self.trans_step_m < 0 or self.rot_step_deg < 0:
            raise ValueError(f"SyntheticConfig steps must be >= 0, got {self.trans_step_m} m, {self.rot_step_deg} deg")
        if self.fps <= 0 or self.depth_scale <= 0:
            raise ValueError(f"SyntheticConfig fps and depth_scale must be > 0, got {self.fps}, {self.depth_scale}")
        scale = self.width / 640.0
        self.fx = float(525.0 * scale if self.fx is None else self.fx)
        self.fy = float(525.0 * scale if self.fy is None else self.fy)
        self.cx = float((self.width - 1) / 2 if self.cx is None else self.cx)
        self.cy = float((self.height - 1) / 2 if self.cy is None else self.cy)
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"SyntheticConfig focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        k = self.kinect
        if min(k.sigma_a_m, k.sigma_b_per_m, k.dropout_prob, k.rgb_sigma, k.disparity_subpixel, k.sigma_scale) < 0:
            raise ValueError(f"SyntheticConfig.kinect parameters must be >= 0, got {k}")
        if not 0 <= k.dropout_prob < 1 or k.min_depth_m >= k.max_depth_m:
            raise ValueError(f"SyntheticConfig.kinect has a bad dropout or depth range: {k}")
        d = self.depth_camera
        if d is not None:
            T = d.get("T_color_depth")
            if set(d) != {"fx", "fy", "cx", "cy", "T_color_depth"} or min(d["fx"], d["fy"]) <= 0:
                raise ValueError(f"SyntheticConfig.depth_camera needs fx, fy > 0, cx, cy and T_color_depth, got {d}")
            if len(T) != 4 or any(len(row) != 4 for row in T):
                raise ValueError(f"SyntheticConfig.depth_camera.T_color_depth must be 4x4, got {T}")
            self.depth_camera = {k: float(d[k]) for k in ("fx", "fy", "cx", "cy")} | {
                "T_color_depth": [[float(v) for v in row] for row in T]
            }

    def to_dict(self) -> dict:
        """Resolved, JSON-serialisable parameters (no ``depth_camera`` when depth is registered, no ``object`` /
        ``object_distance_m``, ``kinect.sigma_scale`` or ``effects`` at their defaults: same digests as before the
        options existed)."""
        out = asdict(self)
        out["effects"]["depth_shift_px"] = list(out["effects"]["depth_shift_px"])
        defaults = (("depth_camera", None), ("object", "compound"), ("object_distance_m", None),
                    ("effects", asdict(SensorEffects()) | {"depth_shift_px": [0, 0]}))  # fmt: skip
        for key, default in defaults:
            if out[key] == default:
                del out[key]
        if out["kinect"]["sigma_scale"] == 1.0:
            del out["kinect"]["sigma_scale"]
        return out

    def digest(self) -> str:
        """12 hex digits identifying the rendered output (config plus renderer version)."""
        text = json.dumps({"v": RENDERER_VERSION, **self.to_dict()}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:12]
