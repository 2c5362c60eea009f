"""The command line's first contact: composition errors keep what helps (Hydra's options, the group option that has a
key, the nearest name), ``conf_dir=DIR`` on every console script, ``--help`` without Hydra's group listing.

Oracles: the folders of conf/ (the options a group has), a composition with the suggested fix (it composes), the
config Hydra itself composes and the help template Hydra itself resolves.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import torch
from hydra import compose, initialize_config_dir

from torchtrack.cli import check_overrides, compose_config, tracker_help, with_conf_dir
from torchtrack.config import CONF_DIR


def test_unknown_option_keeps_hydras_options_on_one_line():
    error = check_overrides("config", ["weighting=paperr"])
    assert "\n" not in error
    head, options, hint = re.fullmatch(
        r"(Could not find 'weighting/paperr'); available options in 'weighting': ([\w, ]+); (.*)", error
    ).groups()
    assert set(options.split(", ")) == {p.stem for p in (CONF_DIR / "weighting").glob("*.yaml")}
    assert hint == "did you mean 'paper'?"


def test_a_key_of_another_option_says_which_to_add(tmp_path):
    error = check_overrides("config", [f"data.root={tmp_path}"])
    assert "\n" not in error and error.endswith("data.root is a key of data=tum: add data=tum"), error
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        assert compose("config", overrides=["data=tum", f"data.root={tmp_path}"]).data.root == str(tmp_path)


@pytest.mark.parametrize(
    ("override", "suggested"),
    [("weightng=paper", "weighting"), ("data.max_frame=3", "data.max_frames"), ("plotz=false", "plots")],
)
def test_a_mistyped_name_suggests_the_nearest(override, suggested):
    error = check_overrides("config", [override])
    assert "\n" not in error and error.endswith(f"did you mean '{suggested}'?"), error
    fixed = suggested + "=" + override.partition("=")[2]
    assert check_overrides("config", [fixed]) is None  # the suggestion composes


def test_a_key_of_another_option_is_found_beside_that_options_other_keys(tmp_path):
    """``data.root`` with the synthetic scene's own keys on the line still points at data=tum."""
    error = check_overrides("config", [f"data.root={tmp_path}", "data.scene.frames=6"])
    assert error.endswith("data.root is a key of data=tum: add data=tum"), error


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("filter.iterations=0", "FusionEKF: iterations must be >= 1"),
        ("flow.mode=foo", "flow.mode must be one of combined, intensity, sim, got 'foo'"),
        ("flow.policy=best", "flow.policy must be one of min_tim, fallback, got 'best'"),
        ("filter.gate=1.5", "FusionEKF: gate is a probability in (0, 1), got 1.5"),
        ("weighting=learned", None),
        (
            "select.grid=[4,4]",
            "select.grid fixes the patches, select.roi_fraction sizes them to the region: give select.roi_fraction=null "
            "with select.grid",
        ),
    ],
)
def test_a_stage_value_out_of_range_is_one_line_before_any_data(override, message):
    """The stages' own range checks run in the pre-check (the tracker is built once, without data): one line, the
    stage's message, instead of a traceback after the sequence is loaded."""
    assert check_overrides("config", [override]) == message


def test_keys_that_agree_build():
    assert check_overrides("config", ["select.grid=[4,4]", "select.roi_fraction=null"]) is None


def test_no_suggestion_for_a_name_unlike_any():
    error = check_overrides("config", ["estimator.zzzqqq=1"])
    assert error == "Could not override 'estimator.zzzqqq': Key 'zzzqqq' not in 'EKFBackendConfig'"


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error without CUDA, and this machine has CUDA")
def test_cuda_without_cuda_is_refused_before_running():
    assert re.fullmatch(
        r"device=cuda: CUDA is not available \(.*\); use device=cpu", check_overrides("config", ["device=cuda"])
    )
    assert check_overrides("config", ["device=cpu"]) is None
    assert "use cpu or cuda" in check_overrides("config", ["device=tpu"])


@pytest.fixture
def myconf(tmp_path):
    """A user's config folder with one option of its own: weighting=mine, the paper's weighting with sigma2_pix 7."""
    (tmp_path / "myconf" / "weighting").mkdir(parents=True)
    (tmp_path / "myconf" / "weighting" / "mine.yaml").write_text("defaults:\n  - paper\n  - _self_\nsigma2_pix: 7.0\n")
    return tmp_path / "myconf"


def test_conf_dir_is_hydras_searchpath(myconf, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    assert with_conf_dir(["conf_dir=myconf", "weighting=mine"]) == [
        f"hydra.searchpath=[file://{myconf}]",
        "weighting=mine",
    ]
    cfg = compose_config("config", ["conf_dir=myconf", "weighting=mine"])
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        hydra = compose("config", overrides=["weighting=mine", f"hydra.searchpath=[file://{myconf}]"])
    assert cfg == hydra and cfg.weighting.sigma2_pix == 7.0
    assert cfg.weighting.sigma2_xyz == compose_config("config").weighting.sigma2_xyz  # the rest: paper's
    with pytest.raises(ValueError, match="conf_dir=nowhere: .* is not a folder"):
        with_conf_dir(["conf_dir=nowhere"])


@pytest.mark.slow
@pytest.mark.parametrize("module", ["torchtrack.cli", "torchtrack.learn.train_app"])
def test_conf_dir_on_the_console_scripts(myconf, module, tmp_path):
    """Every console script takes it through cli.py's shared entry: Hydra's --cfg job shows the composed value."""
    env = {**os.environ, "TORCHTRACK_CACHE": str(tmp_path / "cache")}
    args = [sys.executable, "-m", module, f"conf_dir={myconf}", "weighting=mine", "--cfg", "job"]
    done = subprocess.run(args, capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert done.returncode == 0, done.stderr
    assert re.search(r"^weighting:\n(  .*\n)*  sigma2_pix: 7\.0$", done.stdout, re.M), done.stdout
    bad = subprocess.run(args[:3] + ["weighting=mine"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert bad.returncode == 2 and "Could not find 'weighting/mine'" in bad.stderr  # without conf_dir: not found


def test_help_is_hydras_template_resolved():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", return_hydra_config=True)
    assert tracker_help() == cfg.hydra.help.template + "\n"


@pytest.mark.slow
def test_help_imports_neither_the_pipeline_nor_the_runner():
    """(Hydra itself comes with torchtrack.config, which registers the schemas.)"""
    code = (
        "import sys; from torchtrack.cli import main; sys.argv = ['torchtrack', '--help']; main(); "
        "print(sorted(m for m in ('torchtrack.factory', 'torchtrack.pipeline', 'torchtrack.run') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout.splitlines()[-1] == "[]", done.stderr
