"""Shared test settings."""

import pytest
import torch


@pytest.fixture(autouse=True, scope="session")
def one_thread():
    """The per-frame tensors are small: one intra-op thread is fastest (as the CLI's default) and immune
    to a loaded machine, where two threads oversubscribe the cores ~10x. Restored after the session."""
    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)


@pytest.fixture(params=["compiled", "reference"])
def kernels(request):
    """A test that asks runs twice: on the compiled operators (skipped where they do not build) and on their pure-torch
    references (tests/reference.py)."""
    from reference import references

    from torchtrack import ops

    if request.param == "compiled":
        if not ops.available():
            pytest.skip(f"the compiled operators could not be built here ({ops.error()}); the references are tested")
        yield request.param
    else:
        with references():
            yield request.param
