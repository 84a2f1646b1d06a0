"""Fixtures of the reconstruction tests: one torch thread (tiny nets; avoids oversubscribing 2 cores)."""

import pytest


@pytest.fixture(autouse=True)
def _one_torch_thread():
    try:
        import torch
    except ImportError:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)
