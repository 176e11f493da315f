"""A run's thread count is fixed when it starts (issue 26): what starts or ends beside it never
changes it; it is printed, recorded in versions.json, metrics.json and the report, and
``--resume`` reuses it. The machine's load is faked (``outside_load``): the count the load rule
would give changes from one call to the next, and the run must not follow it."""
import json
import os
import shutil

import pytest
import yaml

from fwk.engine import threads
from fwk.runs import execute

RECIPE = {"name": "pinned", "task": "reconstruct", "seed": 0,
          "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 10},
          "split": {"ratios": [0.6, 0.2, 0.2]}, "train": {"epochs": 3, "batch_size": 4},
          "models": {"ae": {"name": "ae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}},
                     "ae2": {"name": "ae", "channels": [4], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}},
          "metrics": ["l1"], "renders": 0}


@pytest.fixture
def swinging_load(tmp_path, monkeypatch):
    """An idle machine at the run's first measurement, then one where other work takes a CPU of
    two, then idle again, ...: the load rule alone would give 2, 1, 2, 1, ... threads."""
    import torch

    before = torch.get_num_threads()
    monkeypatch.setenv("FWK_RUNTIME_DIR", str(tmp_path / "procs"))
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    for var in ("FWK_THREADS", "OMP_NUM_THREADS", "FWK_ALLOCATED_CPUS"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(threads, "available_cores", lambda: 2)
    calls = []

    def load(*a, **k):
        calls.append(1)
        return (0.0 if len(calls) % 2 == 1 else 1.0), 2

    monkeypatch.setattr(threads, "outside_load", load)
    yield calls
    threads.unpin()
    threads.unregister()
    torch.set_num_threads(before)


def _run(tmp_path, recipe=RECIPE, **kw):
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    return execute(str(tmp_path / "r.yaml"), runs_dir=str(tmp_path / "runs"), quiet=True, **kw)


def _epoch_threads(run):
    return {p.parent.name: [e["threads"] for e in json.loads(p.read_text())["epochs"]] for p in (run / "curves").glob("*/*.json")}


@pytest.mark.parametrize("side_by_side", [False, True])
def test_the_count_never_changes_during_a_run_and_is_recorded(tmp_path, swinging_load, side_by_side):
    """One after another each model trains with the run's 2 threads; side by side (the default,
    fwk.sidebyside) each with 1 of them, every epoch."""
    run = _run(tmp_path, {**RECIPE, "train": {**RECIPE["train"], "side_by_side": side_by_side}})
    seen = _epoch_threads(run)
    each = 1 if side_by_side else 2
    assert set(seen) == {"ae", "ae2"} and all(v == [each] * 3 for v in seen.values()), seen
    assert len(swinging_load) >= 1  # the rule was asked once, as the run started ...
    assert threads.thread_budget()[0] in (1, 2) and threads.pinned() is None  # ... and the pin ends with the run
    v = json.loads((run / "versions.json").read_text())
    assert v["threads"] == 2 and v["threads_why"] == "1 fwk process on 2 cores"
    assert json.loads((run / "metrics.json").read_text())["threads"] == 2
    report = (run / "report.md").read_text()
    assert "- Threads: 2 per process, fixed when the run started (1 fwk process on 2 cores)" in report
    said = [line for line in (run / "log.txt").read_text().splitlines() if "threads: " in line]
    assert len(said) == 1 and said[0].endswith(
        "threads: 2 (1 fwk process on 2 cores; fixed for this run, fwk run --resume reuses it)"), said


def test_a_resume_reuses_the_recorded_count(tmp_path, swinging_load, monkeypatch):
    run = _run(tmp_path)
    shutil.rmtree(run / "curves" / "ae2")  # as if the run had stopped before its second model
    for p in (run / "models").glob("ae2*"):
        p.unlink()
    monkeypatch.setattr(threads, "outside_load", lambda *a, **k: (1.0, 2))  # the rule now says 1
    assert threads.thread_budget()[0] == 1
    execute(None, resume=str(run), quiet=True)
    # the run's count, 2, shared by the recipe's 2 models side by side: 1 each, also with one left
    assert _epoch_threads(run)["ae2"] == [1, 1, 1]
    log = (run / "log.txt").read_text()
    assert "threads: 2 (as the run started: 1 fwk process on 2 cores; fixed for this run" in log
    v = json.loads((run / "versions.json").read_text())
    assert v["threads"] == 2 and v["resumed"][-1]["threads"] == 2


def test_a_count_given_on_resume_wins_and_is_said(tmp_path, swinging_load, monkeypatch):
    run = _run(tmp_path)
    monkeypatch.setenv("FWK_THREADS", "1")
    execute(None, resume=str(run), quiet=True)
    log = (run / "log.txt").read_text()
    assert ("threads: this run started with 2 and resumes with 1 (FWK_THREADS=1): its numbers now come from "
            "two thread counts (fwk run --resume --threads 2 keeps one)") in log
    v = json.loads((run / "versions.json").read_text())
    assert v["threads"] == 2 and v["resumed"][-1]["threads"] == 1  # the start's record stays


def test_recorded_threads_refuses_what_is_not_a_count(tmp_path):
    for bad in ({"threads": True}, {"threads": 0}, {"threads": "2"}, {"threads": 10 ** 9}, [], {}):
        (tmp_path / "versions.json").write_text(json.dumps(bad))
        assert threads.recorded_threads(tmp_path) is None
    (tmp_path / "versions.json").write_text("{not json")
    assert threads.recorded_threads(tmp_path) is None
    (tmp_path / "versions.json").write_text(json.dumps({"threads": 3}))
    assert threads.recorded_threads(tmp_path) == (3, "recorded in versions.json")
    with pytest.raises(Exception, match="whole number"):
        threads.pin(0, "x")
    before = os.environ.get("FWK_THREADS")
    threads.pin(3, "x")
    try:  # the pin replaces the load rule, not an explicit count, and never writes the environment
        assert threads.thread_budget(env={}) == (3, "x") and threads.thread_budget(env={"FWK_THREADS": "1"})[0] == 1
        assert os.environ.get("FWK_THREADS") == before
    finally:
        threads.unpin()
