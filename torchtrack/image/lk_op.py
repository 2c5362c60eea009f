"""The compiled operators ``torch.ops.torchtrack.lk_track`` (csrc/lk.cpp, the LK inner loop),
``torch.ops.torchtrack.shape_index_map`` (csrc/sim.cpp, the SIM), ``torch.ops.torchtrack.dense_fit`` and
``depth_points`` (csrc/dense.cpp, the dense map's alignment and the points a keyframe adds) and
``torch.ops.torchtrack.voxel_add``, ``voxel_rehash``, ``pool_update`` (csrc/voxel.cpp,
the voxel map's fusion, its table's refill, the alignment's pool after a fusion): one library, built on first use,
cached, with fake kernels; :mod:`torchtrack.image.lk`, :mod:`torchtrack.image.shape_index`,
:mod:`torchtrack.pipeline.dense_map` and :mod:`torchtrack.mapping.voxel_grid` fall back to their pure-torch references
where it cannot be built.

Build: ``torch.utils.cpp_extension.load`` (ninja, the system C++ compiler, ``-O3``) into
``$TORCHTRACK_CACHE/ext/lk_<hash>`` (default ``~/.cache/torchtrack``), where the hash covers the source, the flags
and the torch version: a changed source builds anew, an unchanged one loads in milliseconds. Concurrent first use
(two pytest workers, CI) is safe: torch's loader holds a file baton (``lock`` in the build folder) while one process
builds; the others wait for it and then load the same library. Nothing is built at pip-install time (an isolated
build environment would fetch another torch). ``TORCHTRACK_NO_BUILD=1`` disables the build (the fallback, tested).
A first build takes tens of seconds: :func:`warm_up` runs it before a run's timed loop and says so on one line.
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
import warnings
from pathlib import Path
from typing import TextIO

import torch
from torch import Tensor

SOURCE = Path(__file__).with_name("csrc") / "lk.cpp"
SOURCES = [SOURCE, *(SOURCE.with_name(f"{name}.cpp") for name in ("sim", "dense", "voxel", "corners"))]
# -fopenmp compiles at::parallel_for's OpenMP region; it is not linked: the symbols resolve to torch's own OpenMP
# runtime (linking the system libgomp would load a second one).
CFLAGS = ["-O3", "-fopenmp", "-fno-math-errno"]
_state: dict = {}


def cache_dir() -> Path:
    """$TORCHTRACK_CACHE, else ~/.cache/torchtrack (the data cache's root, config.DataConfig.cache_dir)."""
    return Path(os.environ.get("TORCHTRACK_CACHE") or Path.home() / ".cache" / "torchtrack").expanduser()


def build_key() -> str:
    h = hashlib.sha256(b"".join(s.read_bytes() for s in SOURCES))
    h.update(" ".join(CFLAGS + [torch.__version__]).encode())
    return h.hexdigest()[:16]


def _library() -> tuple[Path, Path]:
    """(build folder, library file) of this source's build."""
    key = build_key()
    folder = cache_dir() / "ext" / f"lk_{key}"
    return folder, folder / f"torchtrack_lk_{key}.so"


def _finished(folder: Path, library: Path) -> bool:
    """A finished build: the library there and no build holding the lock."""
    return library.is_file() and not (folder / "lock").exists()


def _build() -> float:
    """Build (or load the cached build of) the operator; returns the seconds it took. A finished build loads directly:
    torch's loader would import cpp_extension and run the compiler's and ninja's checks first (~0.5-1 s of start-up)."""
    folder, library = _library()
    key = folder.name[len("lk_") :]
    t0 = time.perf_counter()
    if _finished(folder, library):
        try:
            torch.ops.load_library(str(library))
            return time.perf_counter() - t0
        except OSError:  # unreadable: build it again below
            pass
    from torch.utils.cpp_extension import load

    folder.mkdir(parents=True, exist_ok=True)
    load(name=f"torchtrack_lk_{key}", sources=[str(s) for s in SOURCES], extra_cflags=CFLAGS, build_directory=str(folder),
         is_python_module=False, verbose=False)  # fmt: skip
    return time.perf_counter() - t0


def available() -> bool:
    """Whether the operator is loaded, building it on the first call; where it cannot be built (no compiler, no
    ninja, ``TORCHTRACK_NO_BUILD=1``) one warning line, once, and False."""
    if "ok" not in _state:
        try:
            if os.environ.get("TORCHTRACK_NO_BUILD", "") not in ("", "0"):
                raise RuntimeError("TORCHTRACK_NO_BUILD is set")
            _state["build_s"] = _build()
            _register_fake()
            _state["ok"] = True
        except Exception as e:  # any build failure: the reference path still works
            _state["ok"], _state["error"] = False, f"{type(e).__name__}: {str(e).strip().splitlines()[-1:]}"
            warnings.warn(f"torchtrack: compiled LK operator unavailable ({_state['error']}); using the pure-torch "
                          "LK, SIM and alignment (slower)", RuntimeWarning, stacklevel=3)  # fmt: skip
    return _state["ok"]


def needs_build() -> bool:
    """Whether :func:`available` would compile the operators now (first use of this source, torch and flags here)."""
    if "ok" in _state or os.environ.get("TORCHTRACK_NO_BUILD", "") not in ("", "0"):
        return False
    return not _finished(*_library())


def warm_up(stream: TextIO | None = None) -> bool:
    """:func:`available`, before any frame is timed. Where that compiles the operators (tens of seconds, once), one
    line on ``stream`` (default stderr) says so as it starts and how long it took when it ends."""
    if not needs_build():
        return available()
    stream = stream if stream is not None else sys.stderr
    print(
        "torchtrack: building the compiled LK, SIM and alignment operators (first run only)... ",
        end="",
        file=stream,
        flush=True,
    )
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # this line says it instead
        warnings.simplefilter("ignore", RuntimeWarning)
        ok = available()
    took = time.perf_counter() - t0
    done = (
        f"done in {took:.0f} s"
        if ok
        else f"failed after {took:.0f} s ({error()}); using the pure-torch LK, SIM and alignment"
    )
    print(done, file=stream, flush=True)
    return ok


def error() -> str | None:
    """Why the operator is unavailable (None where it loaded or was not tried)."""
    return _state.get("error")


def _register_fake() -> None:
    if _state.get("fake"):
        return

    @torch.library.register_fake("torchtrack::lk_track")
    def _(prev, next, base_prev, base_next, sizes, points, image_index, init, *args) -> tuple[Tensor, Tensor, Tensor]:
        n = points.shape[0]
        return points.new_empty(n, 2), points.new_empty(n, dtype=torch.bool), points.new_empty(n)

    @torch.library.register_fake("torchtrack::shape_index_map")
    def _(depth, K, *args) -> tuple[Tensor, Tensor, Tensor]:
        return torch.empty_like(depth), torch.empty_like(depth, dtype=torch.bool), torch.empty_like(depth)

    @torch.library.register_fake("torchtrack::harris_binomial")
    def _(image, k, passes) -> Tensor:
        return torch.empty_like(image)

    @torch.library.register_fake("torchtrack::dense_fit")
    def _(world, depth, K, T_cw, *args) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return world.new_empty(4, 4), world.new_empty(6), world.new_empty(6, 6), world.new_empty(4)

    @torch.library.register_fake("torchtrack::depth_points")
    def _(depth, region, K, T, mask, stride, max_depth) -> tuple[Tensor, Tensor]:
        p = torch.library.get_ctx().new_dynamic_size()
        return depth.new_empty(p, 3, dtype=torch.float64), depth.new_empty(p, dtype=torch.long)

    @torch.library.register_fake("torchtrack::voxel_add")
    def _(table, keys, sums, n, points, *args) -> tuple[Tensor, Tensor, Tensor, Tensor, int]:
        ctx = torch.library.get_ctx()
        k, g = ctx.new_dynamic_size(), ctx.new_dynamic_size()
        return keys.new_empty(k), keys.new_empty(k), keys.new_empty(g), keys.new_empty(g), 0

    @torch.library.register_fake("torchtrack::voxel_rehash")
    def _(table, keys, n) -> None:
        return None

    @torch.library.register_fake("torchtrack::pool_update")
    def _(keys, xyz, sums, known_keys, known_rows, new_keys, new_rows, b, every) -> tuple[Tensor, Tensor]:
        m = torch.library.get_ctx().new_dynamic_size()
        return keys.new_empty(m), xyz.new_empty(m, 3)

    _state["fake"] = True


def lk_track(
    prev_flat: Tensor,
    next_flat: Tensor,
    base_prev: Tensor,
    base_next: Tensor,
    sizes: Tensor,
    points: Tensor,
    image_index: Tensor,
    init: Tensor,
    *,
    stride: int,
    plane: int,
    pad: int,
    window: int,
    iters: int,
    ic_iters: int,
    eps: float,
    min_eig: float,
    with_residual: bool,
) -> tuple[Tensor, Tensor, Tensor]:
    """``torch.ops.torchtrack.lk_track``: pyramidal LK of P points, each in its own image of the pyramids' batch.

    Args:
        prev_flat, next_flat: the pyramids' flat float32 buffers (``Pyramid.flat``), equal geometry (one channel:
            of any lengths, each point's image addressed by the base tables).
        base_prev, base_next: (L, B) int64 flat index of pixel (0, 0) of level l of image b.
        sizes: (L, 2) int64 (H_l, W_l). points, init: (P, 2) float32 level-0 start and guess. image_index: (P,) int64.

    Returns:
        points (P, 2) in next (the input where not tracked), status (P,) bool, residual (P,) (zeros unless
        with_residual).
    """  # fmt: skip
    return torch.ops.torchtrack.lk_track(
        prev_flat, next_flat, base_prev, base_next, sizes, points, image_index, init,
        stride, plane, pad, window, iters, ic_iters, eps, min_eig, with_residual,
    )  # fmt: skip
