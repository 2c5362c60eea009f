"""Scene description for the ray-caster: textured primitives in rigid groups, plus the default layouts.

World frame of the default scenes: z up, floor at z = 0, metres. Each primitive lives in its own
local frame (``T_group_prim``, float64) inside a rigid group: group 0 is the static world, group 1
the moving object (posed per frame by ``T_world_obj``). Local shapes:

- ``plane``: rectangle z = 0, |x| <= size[0], |y| <= size[1]; its normal is local +z (one-sided shading).
- ``box``: |x| <= size[0], |y| <= size[1], |z| <= size[2].
- ``sphere``: radius size[0] about the origin.
- ``cylinder``: axis z, radius size[0], |z| <= size[1], capped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from torchtrack.data.synthetic.config import SyntheticConfig
from torchtrack.geometry import euler_to_matrix, intrinsics_matrix, make_T

KINDS = ("plane", "box", "sphere", "cylinder")
TABLE_SIZE = 64  # lattice of the procedural textures (periodic, TABLE_SIZE cells)


@dataclass
class TextureParams:
    """Procedural texture of one primitive, in surface coordinates (metres).

    base colours c0 -> c1 modulated by value noise of scale ``noise_m``; a soft checker of square
    ``checker_m`` in colour ``c2`` with weight ``checker_weight``; per cell of size ``cell_m`` either a
    random rectangle, a blob or nothing, in a random colour. ``cell_offset`` picks this primitive's
    part of the shared random lattice so that no two primitives look alike.
    """

    c0: tuple[float, float, float]
    c1: tuple[float, float, float]
    c2: tuple[float, float, float]
    noise_m: float
    checker_m: float
    checker_weight: float
    cell_m: float
    cell_offset: tuple[int, int]
    uv_offset: tuple[float, float]


@dataclass
class Primitive:
    kind: str
    size: tuple[float, ...]
    T_group_prim: Tensor  # (4, 4) float64
    texture: TextureParams
    group: int = 0

    def __post_init__(self) -> None:
        need = {"plane": 2, "box": 3, "sphere": 1, "cylinder": 2}
        if self.kind not in need:
            raise ValueError(f"Primitive.kind must be one of {KINDS}, got {self.kind!r}")
        if len(self.size) != need[self.kind] or min(self.size) <= 0:
            raise ValueError(f"Primitive {self.kind} needs {need[self.kind]} positive sizes, got {self.size}")

    @property
    def bounding_radius(self) -> float:
        """Radius of a sphere about the local origin that contains the primitive."""
        return self.size[0] if self.kind == "sphere" else math.sqrt(sum(v * v for v in self.size))


@dataclass
class Scene:
    """Primitives, camera intrinsics and the random tables the textures read.

    Attributes:
        K: (3, 3) float32 pinhole intrinsics. width, height: image size.
        light_dir: unit (3,) direction towards the light, in each primitive's group frame, so shading
            moves rigidly with the object (brightness constancy holds exactly).
        lattice: (T, T, 8) uniform [0, 1) random values per texture cell. noise: (T, T) value-noise lattice.
    """

    primitives: list[Primitive]
    K: Tensor
    width: int
    height: int
    lattice: Tensor
    noise: Tensor
    light_dir: tuple[float, float, float] = (0.35, -0.55, 0.76)
    ambient: float = 0.45
    background_rgb: tuple[float, float, float] = (0.1, 0.1, 0.1)
    _dirs: Tensor | None = field(default=None, repr=False)
    _xy_flat: tuple[Tensor, Tensor] | None = field(default=None, repr=False)
    _atlas: dict[int, Tensor] = field(default_factory=dict, repr=False)  # baked plane textures, see texture.py

    def ray_dirs(self) -> Tensor:
        """(H, W, 3) float32 camera rays ((u - cx)/fx, (v - cy)/fy, 1): ray parameter == z-depth."""
        if self._dirs is None:
            self._dirs = pixel_rays(self.K, pixel_grid_xy(self.height, self.width))
        return self._dirs

    def ray_xy(self) -> tuple[Tensor, Tensor]:
        """(W,) and (H,) float32 ray slopes (u - cx)/fx and (v - cy)/fy of the pixel columns and rows."""
        d = self.ray_dirs()
        return d[0, :, 0], d[:, 0, 1]

    def ray_xy_flat(self) -> tuple[Tensor, Tensor]:
        """(H * W,) and (H * W,) float32 contiguous ray slopes x/z and y/z of all pixels, row-major."""
        if self._xy_flat is None:
            d = self.ray_dirs()
            self._xy_flat = (d[..., 0].reshape(-1).contiguous(), d[..., 1].reshape(-1).contiguous())
        return self._xy_flat


def pixel_grid_xy(H: int, W: int) -> Tensor:
    """(H, W, 2) float32 pixel centres (x, y)."""
    y, x = (torch.arange(n, dtype=torch.float32, device="cpu") for n in (H, W))
    ys, xs = torch.meshgrid(y, x, indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def pixel_rays(K: Tensor, pixels: Tensor) -> Tensor:
    """Pixels (..., 2) -> rays (..., 3) with z = 1 through K (3, 3)."""
    x = (pixels[..., 0] - K[0, 2]) / K[0, 0]
    y = (pixels[..., 1] - K[1, 2]) / K[1, 1]
    return torch.stack([x, y, torch.ones_like(x)], dim=-1).float()


def pose(xyz: tuple[float, float, float], rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Tensor:
    """(4, 4) float64 from a translation and Euler angles in degrees (R = Rz @ Ry @ Rx)."""
    R = euler_to_matrix(torch.tensor([math.radians(a) for a in rpy_deg], dtype=torch.float64, device="cpu"))
    return make_T(R, torch.tensor(xyz, dtype=torch.float64, device="cpu"))


def frame_pose(origin, x_axis, y_axis) -> Tensor:
    """(4, 4) float64 whose local x, y axes are the given world directions (z = x cross y)."""
    x, y = (torch.tensor(v, dtype=torch.float64, device="cpu") for v in (x_axis, y_axis))
    R = torch.stack([x, y, torch.linalg.cross(x, y)], dim=-1)
    return make_T(R, torch.tensor(origin, dtype=torch.float64, device="cpu"))


class _Textures:
    """Draws per-primitive texture parameters from one generator (deterministic from the seed)."""

    def __init__(self, gen: torch.Generator):
        self.gen = gen

    def _u(self, lo: float = 0.0, hi: float = 1.0, n: int = 1) -> list[float]:
        return (lo + (hi - lo) * torch.rand(n, generator=self.gen, dtype=torch.float64)).tolist()

    def __call__(self, cell_m: float, checker_m: float, checker_weight: float, dark: bool = False) -> TextureParams:
        jitter = self._u(0.8, 1.25)[0]
        c0 = tuple(self._u(0.05, 0.35, 3) if dark else self._u(0.25, 0.6, 3))
        c1 = tuple(min(1.0, c + 0.2) for c in c0)
        c2 = tuple(self._u(0.7, 0.95, 3))
        ij = torch.randint(0, TABLE_SIZE, (2,), generator=self.gen).tolist()
        return TextureParams(
            c0=c0,
            c1=c1,
            c2=c2,
            noise_m=0.6 * cell_m,
            checker_m=checker_m * jitter,
            checker_weight=checker_weight,
            cell_m=cell_m * jitter,
            cell_offset=(ij[0], ij[1]),
            uv_offset=tuple(self._u(0.0, 10.0, 2)),
        )


def _room(tex: _Textures) -> list[Primitive]:
    """Floor and three walls of a 3.3 m x 4.7 m room, normals facing inside."""
    return [
        Primitive("plane", (1.65, 2.35), frame_pose((0.15, -1.15, 0.0), (1, 0, 0), (0, 1, 0)), tex(0.35, 0.3, 0.8)),
        Primitive("plane", (1.65, 1.5), frame_pose((0.15, 1.2, 1.5), (1, 0, 0), (0, 0, 1)), tex(0.2, 0.0, 0.0)),
        Primitive("plane", (2.35, 1.5), frame_pose((-1.5, -1.15, 1.5), (0, 1, 0), (0, 0, 1)), tex(0.3, 0.2, 0.5)),
        Primitive("plane", (2.35, 1.5), frame_pose((1.8, -1.15, 1.5), (0, -1, 0), (0, 0, 1)), tex(0.2, 0.0, 0.0)),
    ]


def _props(tex: _Textures, gen: torch.Generator) -> list[Primitive]:
    """Static shapes on the floor: spheres, boxes, standing and lying cylinders (curvature for the SIM)."""
    d = (0.08 * (torch.rand(6, 2, generator=gen, dtype=torch.float64) - 0.5)).tolist()  # position jitter
    yaw = (60 * torch.rand(6, generator=gen, dtype=torch.float64) - 30).tolist()
    return [
        Primitive("sphere", (0.22,), pose((-0.55 + d[0][0], 0.25 + d[0][1], 0.22), (0, 0, yaw[0])), tex(0.1, 0.07, 0.7)),
        Primitive("box", (0.22, 0.16, 0.2), pose((0.4 + d[1][0], 0.45 + d[1][1], 0.2), (0, 0, 25 + yaw[1])), tex(0.1, 0.08, 0.5)),
        Primitive("sphere", (0.11,), pose((0.4 + d[1][0], 0.45 + d[1][1], 0.51), (0, 0, yaw[2])), tex(0.06, 0.04, 0.8)),
        Primitive("cylinder", (0.12, 0.3), pose((-0.05 + d[3][0], -0.15 + d[3][1], 0.3), (0, 0, yaw[3])), tex(0.08, 0.06, 0.6)),
        Primitive("cylinder", (0.09, 0.28), pose((0.55 + d[4][0], -0.45 + d[4][1], 0.09), (0, 90, yaw[4])), tex(0.07, 0.05, 0.7)),
        Primitive("box", (0.1, 0.1, 0.1), pose((-0.45 + d[5][0], -0.55 + d[5][1], 0.1), (0, 0, yaw[5])), tex(0.06, 0.05, 0.6)),
    ]  # fmt: skip


def _compound_object(tex: _Textures) -> list[Primitive]:
    """One rigid object (group 1) about its own origin: a box body, a sphere, two cylinders (~30 cm)."""
    return [
        Primitive("box", (0.14, 0.1, 0.09), pose((0.0, 0.0, 0.0)), tex(0.05, 0.035, 0.6), group=1),
        Primitive("sphere", (0.075,), pose((0.04, 0.01, 0.11), (0, 0, 40)), tex(0.04, 0.03, 0.7), group=1),
        Primitive("cylinder", (0.045, 0.12), pose((0.0, -0.1, -0.035), (0, 90, 0)), tex(0.04, 0.03, 0.7), group=1),
        Primitive("cylinder", (0.03, 0.06), pose((-0.08, 0.04, 0.15)), tex(0.03, 0.025, 0.6), group=1),
    ]


def _small_object(tex: _Textures) -> list[Primitive]:
    """A small rigid object (group 1, ~18 cm across): a 16 x 10 x 8 cm box, a 4 cm sphere on it and a lying
    cylinder, finely textured (2-2.5 cm cells) so that a few dozen corners stay visible at 0.55 m."""
    return [
        Primitive("box", (0.08, 0.05, 0.04), pose((0.0, 0.0, 0.0)), tex(0.025, 0.02, 0.6), group=1),
        Primitive("sphere", (0.04,), pose((0.025, 0.005, 0.072), (0, 0, 40)), tex(0.02, 0.015, 0.7), group=1),
        Primitive("cylinder", (0.023, 0.058), pose((0.0, -0.072, -0.016), (0, 90, 0)), tex(0.02, 0.015, 0.7), group=1),
    ]  # fmt: skip


def make_scene(primitives: list[Primitive], cfg: SyntheticConfig) -> Scene:
    """A scene of the given primitives seen through cfg's camera, texture tables drawn from cfg.seed."""
    gen = torch.Generator().manual_seed(int(cfg.seed) + 1)
    return Scene(
        primitives=list(primitives),
        K=intrinsics_matrix(cfg.fx, cfg.fy, cfg.cx, cfg.cy),
        width=cfg.width,
        height=cfg.height,
        lattice=torch.rand(TABLE_SIZE, TABLE_SIZE, 8, generator=gen),
        noise=torch.rand(TABLE_SIZE, TABLE_SIZE, generator=gen),
    )


def random_texture(
    seed: int, cell_m: float = 0.1, checker_m: float = 0.06, checker_weight: float = 0.7
) -> TextureParams:
    """A texture drawn like the default scene's, for hand-made scenes."""
    return _Textures(torch.Generator().manual_seed(seed))(cell_m, checker_m, checker_weight)


def default_scene(cfg: SyntheticConfig) -> Scene:
    """The scene of ``cfg``: room corner with props (scene mode) or ``cfg.object`` (object mode)."""
    gen = torch.Generator().manual_seed(int(cfg.seed))
    tex = _Textures(gen)
    prims: list[Primitive] = []
    if cfg.mode == "scene" or cfg.background:
        prims += _room(tex)
    if cfg.mode == "scene":
        prims += _props(tex, gen)
    else:
        prims += _small_object(tex) if cfg.object == "small" else _compound_object(tex)
    return make_scene(prims, cfg)
