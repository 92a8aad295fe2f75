"""Shared test fixtures."""
import pytest
import torch


@pytest.fixture
def one_torch_thread():
    """Shared 2-core machine: one intra-op thread avoids oversubscription (10x slower otherwise)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
