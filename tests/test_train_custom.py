"""Any weighting module named by ``_target_`` trains, saves and loads: a module without ``.config`` (defined here,
outside torchtrack) goes through fit's checkpoints and resume, load_checkpoint and the Hydra factory rebuild its
class from the dotted path stored in the file, files without a target load as LearnedWeighting, and a target that
cannot be imported is one line naming it."""

from __future__ import annotations

import inspect
import sys

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch import nn

import torchtrack.learn.checkpoint as ckpt
from torchtrack.config import CONF_DIR
from torchtrack.filter.cues import CUE_NAMES
from torchtrack.filter.fusion import FusionEKF
from torchtrack.filter.weighting import Variances, WeightingInputs
from torchtrack.learn.checkpoint import build_weighting, load_checkpoint, save_checkpoint
from torchtrack.learn.model import LearnedWeighting
from torchtrack.learn.oracle import oracle_windows
from torchtrack.learn.train import TrainConfig, fit

pytestmark = pytest.mark.slow  # training custom weightings

TARGET = f"{__name__}.TinyWeighting"  # importable: pytest puts tests/ on sys.path


class TinyWeighting(nn.Module):
    """A weighting without ``.config``: an MLP on log d_TIM and depth -> log-variance ratios (pixel, 3D)."""

    def __init__(self, hidden: int = 8, sigma2_pix: float = 1.0, sigma2_xyz: float = 4e-6) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(2, hidden), nn.Tanh(), nn.Linear(hidden, 2))
        self.sigma2 = (sigma2_pix, sigma2_xyz)

    def forward(self, inputs: WeightingInputs) -> Variances:
        valid = inputs.valid[..., None]
        x = torch.stack([torch.log1p(inputs.d_tim), inputs.depth], -1).to(self.net[0].weight.dtype)
        s = self.net(torch.where(valid, x, 0.0)).to(inputs.d_tim.dtype)
        s = torch.where(valid, s, 0.0)
        return Variances(self.sigma2[0] * s[..., 0].exp(), self.sigma2[1] * s[..., 1].exp())


def inputs(seed: int = 0) -> WeightingInputs:
    """Plausible inputs with cues (B = 2, N = 9), some features invalid."""
    g = torch.Generator().manual_seed(seed)
    depth = 0.5 + 2 * torch.rand(2, 9, generator=g, dtype=torch.float64)
    points = torch.cat([torch.randn(2, 9, 2, generator=g, dtype=torch.float64), depth[..., None]], -1)
    valid = torch.rand(2, 9, generator=g) > 0.2
    d_tim = torch.rand(2, 9, generator=g, dtype=torch.float64)
    cues = torch.rand(2, 9, len(CUE_NAMES), generator=g)
    return WeightingInputs(d_tim, depth, points, valid, torch.full((2,), 500.0), cues=cues)


def same_outputs(a: nn.Module, b: nn.Module) -> bool:
    x, y = a(inputs()), b(inputs())
    return torch.equal(x.var_pix, y.var_pix) and torch.equal(x.var_xyz, y.var_xyz)


def test_fit_saves_and_resumes_a_module_without_config(tmp_path):
    """fit with an output folder and the node the module was built from: best.pt/last.pt name the class and hold every
    constructor argument (the node's and the signature's defaults); resuming 1 + 2 epochs equals 3 straight."""
    train, val = oracle_windows(B=8, T=3, N=12, seed=1), oracle_windows(B=4, T=3, N=12, seed=2)
    cfg = TrainConfig(window=3, batch=4, epochs=3, lr=1e-2, gate=None, refit=None, seed=3)
    spec = {"_target_": TARGET, "hidden": 4}

    def run(out, epochs):
        torch.manual_seed(3)
        model = build_weighting(spec)
        tc = TrainConfig(**{**cfg.__dict__, "epochs": epochs})
        fit(model, FusionEKF(jacobian="analytic"), train.windows, tc, val=val.windows, out_dir=out, spec=spec,
            progress=False)  # fmt: skip
        return model

    straight = run(tmp_path / "a", 3)
    run(tmp_path / "b", 1)
    resumed = run(tmp_path / "b", 3)
    assert same_outputs(straight, resumed)
    loaded, meta = load_checkpoint(tmp_path / "b" / "last.pt")
    assert type(loaded) is TinyWeighting and not loaded.training and same_outputs(loaded, resumed)
    defaults = {k: p.default for k, p in inspect.signature(TinyWeighting).parameters.items()}
    assert meta["target"] == TARGET and meta["model"] == {**defaults, "hidden": 4} and meta["epoch"] == 3
    with pytest.raises(ValueError, match="a model with other settings"):  # resuming another architecture
        fit(build_weighting({**spec, "hidden": 5}), FusionEKF(), train.windows, cfg, out_dir=tmp_path / "b",
            spec={**spec, "hidden": 5}, progress=False)  # fmt: skip


def test_a_module_without_config_needs_its_node_to_be_saved(tmp_path):
    """No ``.config`` and no node: refused before the first epoch (one line naming ``spec``), nothing written."""
    cfg = TrainConfig(window=3, epochs=1, gate=None, refit=None)
    with pytest.raises(ValueError, match=r"TinyWeighting has no \.config: pass the node it was built from, spec="):
        fit(TinyWeighting(), FusionEKF(), oracle_windows(B=4, T=3, N=8).windows, cfg, out_dir=tmp_path, progress=False)
    assert list(tmp_path.iterdir()) == []
    fit(TinyWeighting(), FusionEKF(), oracle_windows(B=4, T=3, N=8).windows, cfg, progress=False)  # no folder: fine


def test_files_without_a_target_load_as_learned_weighting(tmp_path):
    """A checkpoint written before checkpoints named their class (the shipped default.pt) is a LearnedWeighting."""
    m = LearnedWeighting(hidden=8, mode="absolute")
    for p in m.parameters():
        nn.init.normal_(p, std=0.1)
    blob = torch.load(save_checkpoint(tmp_path / "new.pt", m), weights_only=True)
    assert blob.pop("target") == "torchtrack.learn.model.LearnedWeighting" and blob["model"] == m.config
    torch.save(blob, tmp_path / "old.pt")
    loaded, meta = load_checkpoint(tmp_path / "old.pt")
    assert type(loaded) is LearnedWeighting and loaded.config == m.config and same_outputs(loaded, m)
    assert meta["target"] == "torchtrack.learn.model.LearnedWeighting"


def test_a_target_that_does_not_import_is_one_line_naming_it(tmp_path, monkeypatch):
    """No such module, no such name in the module, a module whose own import fails, a dotted path that is not one,
    a target that is not a module, and weights that do not fit the rebuilt class."""
    cases = {
        "nowhere_pkg.Weighting": r"'nowhere_pkg\.Weighting' is not importable: no module 'nowhere_pkg'",
        f"{__name__}.Missing": rf"'{__name__}\.Missing' is not importable: {__name__} has no 'Missing'",
        "broken_ext.W": r"'broken_ext\.W': importing broken_ext failed: No module named 'not_installed_dep'",
        "Weighting": r"'Weighting' is not a dotted path",
    }
    (tmp_path / "broken_ext.py").write_text("import not_installed_dep\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for target, message in cases.items():
        with pytest.raises(ImportError, match=message) as e:
            build_weighting({"_target_": target})
        assert "\n" not in str(e.value)
    with pytest.raises(TypeError, match=r"'torch\.nn\.functional\.relu' built a Tensor, not a torch\.nn\.Module"):
        build_weighting({"_target_": "torch.nn.functional.relu", "input": torch.zeros(1)})
    path = save_checkpoint(tmp_path / "w.pt", TinyWeighting(), spec={"_target_": TARGET})
    blob = torch.load(path, weights_only=True)
    torch.save({**blob, "target": "nowhere_pkg.Weighting"}, tmp_path / "moved.pt")
    with pytest.raises(ImportError, match=r"moved\.pt: weighting _target_ 'nowhere_pkg\.Weighting' is not importable"):
        load_checkpoint(tmp_path / "moved.pt")
    torch.save({**blob, "model": {**blob["model"], "hidden": 5}}, tmp_path / "wider.pt")
    with pytest.raises(
        ValueError, match=rf"wider\.pt: the weights do not fit {TARGET}\(.*\): size mismatch for net\.0\.weight"
    ) as e:
        load_checkpoint(tmp_path / "wider.pt")
    assert "\n" not in str(e.value)
    sys.modules.pop("broken_ext", None)


def test_saving_a_class_defined_in_a_script_is_refused(tmp_path):
    class Local(LearnedWeighting):
        pass

    with pytest.raises(ValueError, match="defined in a script or a function: define it in an importable module"):
        save_checkpoint(tmp_path / "w.pt", Local())


def test_the_factory_and_the_cli_config_rebuild_the_custom_class(tmp_path):
    """``weighting=learned weighting.checkpoint=PATH`` builds the checkpoint's class, frozen, with its weights;
    constructor values given in the config are checks against the checkpoint's (not overrides)."""
    torch.manual_seed(0)
    m = TinyWeighting(hidden=6)
    path = save_checkpoint(tmp_path / "w.pt", m, spec={"_target_": TARGET, "hidden": 6})
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=["weighting=learned", f"weighting.checkpoint={path}", "weighting.hidden=6"])
        bad = compose("config", overrides=["weighting=learned", f"weighting.checkpoint={path}", "weighting.hidden=7"])
    w = instantiate(cfg.weighting)
    assert type(w) is TinyWeighting and not any(p.requires_grad for p in w.parameters()) and same_outputs(w, m)
    with pytest.raises(Exception, match=r"trained with other settings \(hidden: config 7 vs checkpoint 6\)"):
        instantiate(bad.weighting)
    with pytest.raises(ValueError, match=r"unknown arguments \['mode'\]"):
        ckpt.learned_weighting(str(path), mode="absolute")


def test_train_model_target_and_arguments_from_the_command_line():
    """``train.model._target_=... train.model.hidden=16`` composes without a ``+`` and builds that class with those
    arguments (LearnedWeighting's keys, null in the recipe, stay out); the default node builds the shipped
    LearnedWeighting with its defaults, ``train.model.mode=absolute`` sets its mode; a LearnedWeighting key set for a
    class that does not take it is an error, not ignored."""

    def built(*overrides: str) -> nn.Module:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = compose("learn", overrides=list(overrides))
        return build_weighting(TrainConfig(**OmegaConf.to_container(cfg.train, resolve=True)).model)

    m = built(f"train.model._target_={TARGET}", "train.model.hidden=16")
    assert type(m) is TinyWeighting and m.net[0].out_features == 16
    d = built()
    assert type(d) is LearnedWeighting and d.config == LearnedWeighting().config
    assert built("train.model.mode=absolute").config == LearnedWeighting(mode="absolute").config
    with pytest.raises(TypeError, match="mode"):
        built(f"train.model._target_={TARGET}", "train.model.mode=absolute")


@pytest.mark.slow
def test_torchtrack_train_with_a_target_that_does_not_import_exits_with_one_line(tmp_path):
    """Before recording anything: exit code 2 and the one line naming the target."""
    import subprocess

    cmd = [sys.executable, "-m", "torchtrack.learn.train_app", "train.model._target_=nowhere_pkg.Weighting",
           "dataset=synthetic_tiny", f"observations={tmp_path / 'obs'}", f"hydra.run.dir={tmp_path / 'run'}"]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 2
    assert "weighting _target_ 'nowhere_pkg.Weighting' is not importable" in done.stdout + done.stderr
    assert not (tmp_path / "obs").exists()
