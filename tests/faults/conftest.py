"""Fixtures of the fault-injection suite: an own cache per test, and undisturbed baselines."""
from __future__ import annotations

import os

import pytest

from tests.faults.common import PCA_RECIPE, assert_complete, fwk_run, models, recipe


@pytest.fixture
def env(tmp_path, monkeypatch):
    """This test's own cache and the subprocess environment that shares it."""
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("FWK_RUNS_DIR", raising=False)
    return {**os.environ, "FWK_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1", "FWK_THREADS": "1",
            "PYTHONUNBUFFERED": "1"}


@pytest.fixture
def baseline(tmp_path_factory):
    """The PCA recipe's metrics from an undisturbed run (computed once per test that asks)."""
    def make(text: str = PCA_RECIPE) -> dict:
        base = tmp_path_factory.mktemp("baseline")
        old = os.environ.get("FWK_CACHE")
        os.environ["FWK_CACHE"] = str(base / "cache")
        try:
            rc, d = fwk_run(recipe(base, text), base / "runs")
        finally:
            if old is None:
                os.environ.pop("FWK_CACHE")
            else:
                os.environ["FWK_CACHE"] = old
        assert rc == 0
        assert_complete(d)
        return models(d)

    return make
