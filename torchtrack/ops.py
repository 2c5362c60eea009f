"""The compiled CPU operators, built and loaded in one place, and the one decision whether they run.

One library, ``torch.ops.torchtrack``, from four sources, each beside the Python it speeds up:
``lk_track`` (image/csrc/lk.cpp, the LK inner loop of :mod:`torchtrack.image.lk`), ``shape_index_map``
(image/csrc/sim.cpp, the SIM of :mod:`torchtrack.image.shape_index`), ``dense_fit`` and ``depth_points``
(map/csrc/dense.cpp, the alignment and a keyframe's points of :mod:`torchtrack.map.dense_map`), ``voxel_add``,
``voxel_rehash`` and ``pool_update`` (map/csrc/voxel.cpp, the fusion of :mod:`torchtrack.map.voxel_grid` and the
alignment's pool). Each keeps its pure-torch reference beside it, and the tests hold the two equal.

:func:`compiled` decides, per tensor, which runs: the operator for a CPU tensor where the library is built, the
reference for tensors on any other device and where it cannot be built (no compiler or ninja,
``TORCHTRACK_NO_BUILD=1``: one warning line, once).

Build: ``torch.utils.cpp_extension.load`` (ninja, the system C++ compiler, ``-O3``) into
``$TORCHTRACK_CACHE/ext/ops_<hash>`` (default ``~/.cache/torchtrack``), where the hash covers the sources, the flags
and the torch version: a changed source builds anew, an unchanged one loads in milliseconds. Concurrent first use
(two pytest workers, CI) is safe: torch's loader holds a file baton (``lock`` in the build folder) while one process
builds; the others wait for it and then load the same library. A process loads the library once: a second copy (the
same build from another cache folder) would register the operators again, which torch answers by aborting the
process. Nothing is built at pip-install time (an isolated build environment would fetch another torch). A first
build takes tens of seconds: :func:`warm_up` runs it before a run's timed loop and says so on one line.
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

_ROOT = Path(__file__).parent
SOURCES = [_ROOT / "image/csrc/lk.cpp", _ROOT / "image/csrc/sim.cpp", _ROOT / "map/csrc/dense.cpp",
           _ROOT / "map/csrc/voxel.cpp"]  # fmt: skip
# -fopenmp compiles at::parallel_for's OpenMP region; it is not linked: the symbols resolve to torch's own OpenMP
# runtime (linking the system libgomp would load a second one).
CFLAGS = ["-O3", "-fopenmp", "-fno-math-errno"]
_state: dict = {}  # the decision: ok, error, build_s
_fakes: list = []  # the fake kernels registered (once per process, like the library)


def _no_build() -> bool:
    """``TORCHTRACK_NO_BUILD`` set (to anything but 0): the references run, nothing is built."""
    return os.environ.get("TORCHTRACK_NO_BUILD", "") not in ("", "0")


def compiled(x: Tensor) -> bool:
    """Whether the compiled operator runs on ``x``: a CPU tensor and the library built (on the first call); the
    pure-torch reference runs otherwise."""
    return x.device.type == "cpu" and available()


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
    folder = cache_dir() / "ext" / f"ops_{key}"
    return folder, folder / f"torchtrack_ops_{key}.so"


def _finished(folder: Path, library: Path) -> bool:
    """A finished build: the library there and no build holding the lock."""
    return library.is_file() and not (folder / "lock").exists()


def loaded() -> bool:
    """Whether this process holds the operators already (from whichever cache folder they were loaded)."""
    return hasattr(torch.ops.torchtrack, "lk_track")


def _load() -> float:
    """Load the operators, building them first where no finished build is cached; returns the seconds it took. Never a
    second copy: where this process holds them already (say, loaded from another ``TORCHTRACK_CACHE``), nothing.
    A finished build loads directly: torch's loader would import cpp_extension and run the compiler's and ninja's
    checks first (~0.5-1 s of start-up)."""
    t0 = time.perf_counter()
    if loaded():
        return 0.0
    folder, library = _library()
    if _finished(folder, library):
        try:
            torch.ops.load_library(str(library))
            return time.perf_counter() - t0
        except OSError:  # unreadable: build it again below
            pass
    from torch.utils.cpp_extension import load

    folder.mkdir(parents=True, exist_ok=True)
    load(name=library.stem, sources=[str(s) for s in SOURCES], extra_cflags=CFLAGS, build_directory=str(folder),
         is_python_module=False, verbose=False)  # fmt: skip
    return time.perf_counter() - t0


def available() -> bool:
    """Whether the operators are loaded, building them on the first call; where they cannot be built (no compiler,
    no ninja, ``TORCHTRACK_NO_BUILD=1``) one warning line, once, and False."""
    if "ok" not in _state:
        try:
            if _no_build():
                raise RuntimeError("TORCHTRACK_NO_BUILD is set")
            _state["build_s"] = _load()
            _register_fake()
            _state["ok"] = True
        except Exception as e:  # any build failure: the references still work
            _state["ok"], _state["error"] = False, f"{type(e).__name__}: {str(e).strip().splitlines()[-1:]}"
            warnings.warn(f"torchtrack: compiled operators unavailable ({_state['error']}); using the pure-torch "
                          "LK, SIM and dense map (slower)", RuntimeWarning, stacklevel=3)  # fmt: skip
    return _state["ok"]


def needs_build() -> bool:
    """Whether :func:`available` would compile the operators now (first use of these sources, torch and flags here)."""
    if "ok" in _state or _no_build() or loaded():
        return False
    return not _finished(*_library())


def warm_up(stream: TextIO | None = None) -> bool:
    """:func:`available`, before any frame is timed. Where that compiles the operators (tens of seconds, once), one
    line on ``stream`` (default stderr) says so as it starts and how long it took when it ends."""
    if not needs_build():
        return available()
    stream = stream if stream is not None else sys.stderr
    print("torchtrack: building the compiled LK, SIM and dense-map operators (first run only)... ", end="",
          file=stream, flush=True)  # fmt: skip
    t0 = time.perf_counter()
    with warnings.catch_warnings():  # this line says it instead
        warnings.simplefilter("ignore", RuntimeWarning)
        ok = available()
    took = time.perf_counter() - t0
    done = (
        f"done in {took:.0f} s"
        if ok
        else f"failed after {took:.0f} s ({error()}); using the pure-torch LK, SIM and dense map"
    )
    print(done, file=stream, flush=True)
    return ok


def error() -> str | None:
    """Why the operators are unavailable (None where they loaded or were not tried)."""
    return _state.get("error")


def _register_fake() -> None:
    if _fakes:
        return

    @torch.library.register_fake("torchtrack::lk_track")
    def _(prev, next, base_prev, base_next, sizes, points, image_index, init, *args) -> tuple[Tensor, Tensor, Tensor]:
        n = points.shape[0]
        return points.new_empty(n, 2), points.new_empty(n, dtype=torch.bool), points.new_empty(n)

    @torch.library.register_fake("torchtrack::shape_index_map")
    def _(depth, K, *args) -> tuple[Tensor, Tensor, Tensor]:
        return torch.empty_like(depth), torch.empty_like(depth, dtype=torch.bool), torch.empty_like(depth)

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

    _fakes.append(True)
