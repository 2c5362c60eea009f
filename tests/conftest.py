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
