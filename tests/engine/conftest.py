"""Fixtures of the engine tests."""
import pytest

from fwk.testing import fixed_threads


@pytest.fixture
def one_thread_count():
    """One thread count for every training of the test (``fwk.testing.fixed_threads``), not the count each
    would take from the load: the tests that use it compare trainings bit for bit, and under pytest -n 2
    two fits could get two counts."""
    with fixed_threads():
        yield
