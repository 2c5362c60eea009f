"""The kernels' signature defaults equal the application's schemas.

The kernels hold their defaults as literals (they do not import :mod:`torchtrack.config`); each schema repeats them
for the CLI. A direct call must behave as the CLI does, so for every schema whose ``_target_`` lives in the kernels,
every field that is a parameter of the target (or of a function the schema configures beside it) has the same
default in the signature.
"""

from __future__ import annotations

import dataclasses
import inspect
from importlib import import_module

import pytest

import torchtrack.config as config

KERNELS = ("torchtrack.geometry.", "torchtrack.image.", "torchtrack.filter.", "torchtrack.estimators.")
KERNELS += ("torchtrack.frontend.",)

# Functions a schema configures besides its ``_target_`` (the pure function behind a thin class, the lower layers it
# passes its keywords to), with the parameters that take a field under another name ({parameter: field}).
PARTNERS: dict[type, tuple[tuple[str, dict[str, str]], ...]] = {
    config.SelectConfig: (
        ("torchtrack.image.select.cornerness_maps", {}),
        ("torchtrack.image.select.patch_shape", {}),
    ),
    config.FlowConfig: (
        ("torchtrack.image.flow.combined_track", {}),
        ("torchtrack.image.flow.prepare_frame", {}),
        ("torchtrack.image.flow.zero_frame", {}),
        ("torchtrack.image.lk.pyramidal_lk", {}),
        ("torchtrack.image.lk.lk_track_flat", {}),
        ("torchtrack.frontend.FrontEnd", {}),  # its levels are the tracker's (the factory passes flow.levels)
    ),
    config.RegionConfig: (("torchtrack.image.object_model.object_mask", {}),),
    config.PaperWeightingConfig: (("torchtrack.filter.weighting.paper_variances", {}),),
    config.ICPConfig: (("torchtrack.estimators.icp.icp", {}),),
    config.CPDConfig: (("torchtrack.estimators.cpd.cpd_rigid", {}),),
}


def resolve(path: str):
    module, _, name = path.rpartition(".")
    return getattr(import_module(module), name)


def kernel_schemas() -> list[type]:
    out = []
    for obj in vars(config).values():
        if dataclasses.is_dataclass(obj) and isinstance(obj, type) and "_target_" in obj.__dataclass_fields__:
            if obj.__dataclass_fields__["_target_"].default.startswith(KERNELS):
                out.append(obj)
    return out


def schema_default(f: dataclasses.Field):
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return f.default


def normalise(v):
    return list(v) if isinstance(v, tuple) else v


def differences(schema: type) -> dict[str, tuple]:
    """{"callable.parameter": (schema default, signature default)} for each disagreement. Skipped: a field whose value
    is an interpolation (``${...}``: another node, not a literal) and a parameter without a default (every caller
    passes it)."""
    fields = {f.name: f for f in dataclasses.fields(schema) if not f.name.startswith("_")}
    targets = ((schema.__dataclass_fields__["_target_"].default, {}), *PARTNERS.get(schema, ()))
    out = {}
    for path, renamed in targets:
        obj = resolve(path)
        for key, p in inspect.signature(obj).parameters.items():
            field = fields.get(renamed.get(key, key))
            if field is None:
                continue
            ours = schema_default(field)
            if isinstance(ours, str) and ours.startswith("${"):
                continue
            if p.default is not inspect.Parameter.empty and normalise(p.default) != normalise(ours):
                out[f"{path}.{key}"] = (ours, p.default)
    return out


def test_every_kernel_schema_is_checked():
    """The schemas of the kernels' stages are found (a renamed target would silently drop out of the check)."""
    names = {s.__name__ for s in kernel_schemas()}
    stages = {"RegionConfig", "SelectConfig", "FlowConfig", "FrontendConfig", "FilterConfig"}
    stages |= {"PaperWeightingConfig", "FixedWeightingConfig", "ICPConfig", "CPDConfig", "HornConfig"}
    assert stages <= names, stages - names
    assert set(PARTNERS) <= set(kernel_schemas())


@pytest.mark.parametrize("schema", kernel_schemas(), ids=lambda s: s.__name__)
def test_signature_defaults_equal_the_schema(schema):
    assert differences(schema) == {}, f"{schema.__name__}: schema vs signature defaults"


def test_a_changed_default_is_caught(monkeypatch):
    """The check's own oracle: a schema whose default differs from a signature's is reported by name, through a
    renamed parameter too."""
    fields = [("_target_", str, "torchtrack.image.flow.CombinedTracker"), ("window", int, 15)]
    changed = dataclasses.make_dataclass("Changed", [*fields, ("lk_iters", int, 10)])
    monkeypatch.setitem(PARTNERS, changed, (("torchtrack.image.lk.pyramidal_lk", {"iters": "lk_iters"}),))
    assert differences(changed) == {
        "torchtrack.image.flow.CombinedTracker.window": (15, 21),
        "torchtrack.image.lk.pyramidal_lk.window": (15, 21),
        "torchtrack.image.lk.pyramidal_lk.iters": (10, 30),
    }
