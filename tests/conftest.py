"""Fixtures shared by the test folders."""
import pytest
import torch


@pytest.fixture
def torch_threads():
    """The test may set torch's thread count; it is put back afterwards."""
    n = torch.get_num_threads()
    yield
    torch.set_num_threads(n)
