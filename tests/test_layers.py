"""The layers of the package: the kernels stand alone, and every tensor a stage makes follows its inputs' device.

The kernels (geometry, image, filter, estimators and the front end) are plain batched torch: importing them loads
neither Hydra, OmegaConf, the config schemas nor the data readers (DESIGN.md, Architecture), so a researcher can use
one on its own. Device: a tensor factory called without a ``device`` puts its tensor on the default device whatever
the inputs' device, which breaks a run with the frames on a GPU. A CI machine has no second device, so it is checked
twice: statically (the factories in the source) and at run time, with the default device set to ``meta`` while the
stages run on CPU inputs: a tensor made without the inputs' device lands on ``meta`` and fails the first operation
that mixes it with the inputs, or comes out on ``meta``.
"""

from __future__ import annotations

import ast
import json
import pkgutil
import subprocess
import sys
from pathlib import Path

import torch

import torchtrack

ROOT = Path(torchtrack.__file__).parent
KERNELS = (
    "torchtrack.ops",
    "torchtrack.geometry",
    "torchtrack.image",
    "torchtrack.filter",
    "torchtrack.estimators",
    "torchtrack.frontend",
)
APP = ("hydra", "omegaconf", "torchtrack.config", "torchtrack.data")
# The stages above the kernels (the tracker's pipeline, the map) read the data types but not the app layer either.
STAGES = ("torchtrack.pipeline", "torchtrack.map")
STAGE_APP = ("hydra", "omegaconf", "torchtrack.config")


def kernel_modules(packages: tuple[str, ...] = KERNELS) -> list[str]:
    out = []
    for name in packages:
        out.append(name)
        path = ROOT / name.split(".", 1)[1]
        if path.is_dir():
            out += [f"{name}.{m.name}" for m in pkgutil.iter_modules([str(path)]) if not m.ispkg]
    return sorted(set(out))


PROBE = """
import importlib, json, sys
app = {app!r}
out = {{}}
for name in {modules!r}:
    before = set(sys.modules)
    importlib.import_module(name)
    new = [m for m in set(sys.modules) - before if any(m == a or m.startswith(a + ".") for a in app)]
    if new:
        out[name] = sorted(new)
print(json.dumps(out))
"""


def loaded(modules: list[str], app: tuple[str, ...]) -> dict[str, list[str]]:
    """{module: the ``app`` modules it loaded} for ``modules`` imported in turn in one fresh interpreter."""
    probe = PROBE.format(app=app, modules=modules)
    res = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_kernels_import_no_application_layer():
    """One fresh interpreter imports every kernel module in turn; a module that brings in an application module (of
    its own or through another kernel module it imports first) is named with what it loaded. A module that loads none
    here loads none alone either (the union of imports would hold it)."""
    modules = kernel_modules()
    assert "torchtrack.image.lk" in modules and "torchtrack.frontend" in modules
    assert loaded(modules, APP) == {}


def test_stages_import_no_configs():
    """The pipeline's stages and the map take plain keyword arguments: Hydra and the schemas stay in the app layer."""
    modules = kernel_modules(STAGES)
    assert "torchtrack.pipeline.tracker" in modules and "torchtrack.map.panorama" in modules
    assert loaded(modules, STAGE_APP) == {}


def test_importing_torchtrack_loads_nothing_else():
    code = "import sys, torchtrack; print(sorted(m for m in sys.modules if m.startswith(('torchtrack.', 'hydra'))))"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.strip() == "[]"


# ------------------------------------------------------------------------------------------------ device audit
FACTORIES = {"zeros", "ones", "eye", "full", "empty", "tensor", "arange", "linspace"}


def bare_factories(path: Path) -> list[str]:
    """``file::function: torch.factory`` of each torch tensor factory called without ``device`` (module level:
    ``<module>``). A host tensor on purpose names ``device="cpu"``."""
    rel, out = path.relative_to(ROOT).as_posix(), []

    def visit(node: ast.AST, fn: str) -> None:
        for child in ast.iter_child_nodes(node):
            name = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else fn
            f = getattr(child, "func", None) if isinstance(child, ast.Call) else None
            if (isinstance(f, ast.Attribute) and f.attr in FACTORIES and isinstance(f.value, ast.Name)
                    and f.value.id == "torch" and "device" not in {k.arg for k in child.keywords}):  # fmt: skip
                out.append(f"{rel}::{fn}: torch.{f.attr}")
            visit(child, name)

    visit(ast.parse(path.read_text()), "<module>")
    return out


def test_tensors_are_created_on_the_inputs_device():
    """Every torch.zeros/ones/eye/full/empty/tensor/arange/linspace call in torchtrack names its device (the inputs',
    or ``"cpu"`` for host arithmetic such as a chi-square quantile), so no stage is CPU-only by construction."""
    bare = [h for p in sorted(ROOT.rglob("*.py")) for h in bare_factories(p)]
    assert bare == [], f"bare tensor factories (name the device): {bare}"


def _frame(seed: int, H: int = 96, W: int = 128):
    """A frame batch (B=2, duck-typed as the front end reads it): random colour, a bowl of depth (a defined SIM)."""
    from types import SimpleNamespace

    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    depth = (1.0 + 1e-4 * ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) + 0.01 * seed).expand(2, 1, H, W).clone()
    K = torch.tensor([[100.0, 0, W / 2], [0, 100.0, H / 2], [0, 0, 1]]).expand(2, 3, 3)
    rgb = torch.rand(2, 3, H, W, generator=g)
    return SimpleNamespace(rgb=rgb, depth=depth, K=K, K_depth=K, T_color_depth=torch.eye(4).expand(2, 4, 4),
                           gray=rgb.mean(1, keepdim=True))  # fmt: skip


def _on_cpu(*results) -> None:
    for r in results:
        for x in r if isinstance(r, tuple) else (r,):
            assert not isinstance(x, torch.Tensor) or x.device.type == "cpu", x.device


def test_front_end_makes_no_tensor_off_the_inputs_device(kernels):
    """Preparation (registered and warped depth, SIM, pyramids), the object region, the selection and the combined
    tracker, on the compiled operators and on their references, run with stray factories sent to ``meta`` (module docstring)."""
    from torchtrack.frontend import FrontEnd
    from torchtrack.image.flow import combined_track
    from torchtrack.image.object_model import object_mask
    from torchtrack.image.select import select_features

    f0, f1 = _frame(0), _frame(1)
    f1.T_color_depth = f1.T_color_depth.clone()
    f1.T_color_depth[:, 0, 3] = 0.01  # not registered: the depth is warped into the colour camera
    front = FrontEnd(levels=2)
    with torch.device("meta"):
        p0, p1 = front.prepare(f0), front.prepare(f1)
        feats = select_features(p0.gray, p0.depth, f0.K, roi=object_mask(p0.depth), sim=p0.sim)
        track = combined_track(p0.flow, p1.flow, feats.pixels, feats.valid, levels=2, with_residual=True)
    _on_cpu(p1.gray, p1.depth, p1.sim, feats, track)
    assert int(track.valid.sum()) > 0


def test_filter_and_estimators_make_no_tensor_off_the_inputs_device():
    """One fusion EKF frame (both state parametrisations), the paper's weighting and the three baselines, with stray
    factories sent to ``meta`` (module docstring)."""
    from torchtrack.estimators import CPDEstimator, HornEstimator, ICPEstimator
    from torchtrack.filter import FusionEKF, PaperWeighting, WeightingInputs
    from torchtrack.geometry import intrinsics_matrix, make_T, project, se3_exp, se3_log, so3_exp, transform_points

    g = torch.Generator().manual_seed(0)
    X = 0.1 * torch.randn(2, 30, 3, generator=g, dtype=torch.float64)
    K = intrinsics_matrix(525.0, 525.0, 319.5, 239.5, dtype=torch.float64).expand(2, 3, 3)
    T_cd = torch.eye(4, dtype=torch.float64).expand(2, 4, 4)
    T = make_T(so3_exp(torch.tensor([[0.1, 0.2, -0.1], [0.0, -0.3, 0.2]], dtype=torch.float64)),
               torch.tensor([[0.05, -0.02, 1.2], [-0.1, 0.05, 1.8]], dtype=torch.float64))  # fmt: skip
    valid = torch.ones(2, 30, dtype=torch.bool)
    dt = torch.full((2,), 1 / 30, dtype=torch.float64)
    with torch.device("meta"):
        points_d = transform_points(T, X)
        pixels = project(K, points_d)
        inputs = WeightingInputs(torch.rand(2, 30, generator=g, device="cpu"), points_d[..., 2], points_d, valid,
                                 K[:, 0, 0])  # fmt: skip
        var = PaperWeighting()(inputs)
        out = []
        for state in ("se3", "euler"):
            ekf = FusionEKF(state=state)
            prior = ekf.predicted(ekf.initial_state(T), dt)
            update = ekf.updated(prior, X, points_d, pixels, valid, valid, var.var_xyz, var.var_pix, K, T_cd)
            out.append(ekf.injected(prior, update))
        fits = [
            est(X, points_d, valid, T)
            for est in (HornEstimator(), ICPEstimator(max_iters=3), CPDEstimator(max_iters=3))
        ]
        xi = se3_log(se3_exp(torch.zeros(2, 6, dtype=torch.float64, device="cpu")))
    _on_cpu(var, *out, *fits, xi)
