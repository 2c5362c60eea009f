"""The pure-torch references of the compiled operators, run on purpose: the oracle the operators are held to.

:func:`torchtrack.ops.compiled` picks the operator for every CPU tensor where it is built; inside
:func:`references` it answers False, so that a whole stage (an LK call, a voxel map's adds, a dense fit) runs its
reference path, as it does on devices without the operators.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest

from torchtrack import ops


@contextmanager
def references() -> Iterator[None]:
    with pytest.MonkeyPatch.context() as m:
        m.setattr(ops, "compiled", lambda x: False)
        yield


def on_reference(fn, *args, **kwargs):
    """``fn(*args, **kwargs)`` with every compiled operator replaced by its reference."""
    with references():
        return fn(*args, **kwargs)


requires_ops = pytest.mark.skipif(
    not ops.available(),
    reason=f"the compiled operators could not be built here ({ops.error()}); their torch references are tested",
)
