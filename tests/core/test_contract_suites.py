"""fwk.testing, the contract suites themselves (issue 30): a failing suite assert shows actual
against expected, and no suite uses what pytest 10 removes."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest


def test_the_suites_asserts_are_rewritten():
    """pytest rewrites a test module's asserts, not an installed package's: fwk.testing marks its
    submodules (pytest.register_assert_rewrite) before they are imported."""
    import fwk.testing.metric
    from _pytest.assertion.rewrite import AssertionRewritingHook

    if not any(isinstance(h, AssertionRewritingHook) for h in sys.meta_path):
        pytest.skip("pytest runs with --assert=plain")
    assert isinstance(fwk.testing.metric.__loader__, AssertionRewritingHook), type(fwk.testing.metric.__loader__)


def test_a_failing_suite_assert_shows_actual_against_expected(tmp_path):
    """A metric whose scores come back (b, 1): the suite's failure names the shapes it got."""
    (tmp_path / "test_bad_metric.py").write_text(textwrap.dedent('''
        import numpy as np
        from fwk.testing.metric import MetricContract

        class Bad:
            """A metric returning its scores as a column."""
            name, label, units, power, display_scale, default, default_rank = "bad", "Bad", "input", 1, 1.0, False, 9

            def __call__(self, pred, target, template):
                d = np.linalg.norm(np.asarray(pred) - np.asarray(target), axis=-1)
                return d.mean(1, keepdims=True), d

        class TestBad(MetricContract):
            component = Bad
    '''))
    out = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-k",
                          "test_shapes_and_identity", "test_bad_metric.py"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, out.stdout[-3000:] + out.stderr[-3000:]
    assert "(3, 1) == (3,)" in out.stdout, out.stdout[-3000:]


def test_fixed_threads_holds_one_count_through_a_fit_and_puts_everything_back(monkeypatch, torch_threads):
    """A suite's two fits of one seed compare bit for bit, so neither may take its count from the
    machine's load (a trainer's rule where nothing is pinned): 2 threads on an idle 2-core
    machine, 1 beside another process; CI's pytest -n 2 met both."""
    import torch

    from fwk.engine import threads as th
    from fwk.testing import fixed_threads

    for key in ("FWK_THREADS", "FWK_ALLOCATED_CPUS", "OMP_NUM_THREADS"):
        monkeypatch.delenv(key, raising=False)
    torch.set_num_threads(2)
    assert th.pinned() is None and th.thread_budget(cores=2, live=1, outside=0.0)[0] == 2
    with fixed_threads() as n:
        assert n == 1 and torch.get_num_threads() == 1
        assert th.thread_budget(cores=2, live=1, outside=0.0)[0] == 1
        assert th.apply_threads()[0] == 1
    assert th.pinned() is None and torch.get_num_threads() == 2
    monkeypatch.setenv("FWK_THREADS", "2")  # an explicit count wins, as it does in a run
    th.pin(3, "an outer run")
    try:
        with fixed_threads() as n:
            assert n == 2 and torch.get_num_threads() == 2
        assert th.pinned() == (3, "an outer run")
    finally:
        th.unpin()
