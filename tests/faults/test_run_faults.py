"""Runs killed, crashed or interrupted at every stage, and runs side by side: a run directory is
complete or says why not, ``--resume`` gives the undisturbed numbers, and nothing half-written
is read (issue 16, reproduction 2 and the killed-run faults)."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

import fwk.evaluation as ev
from fwk.cli import main
from fwk.errors import FwkError
from fwk.lifecycle import open_run
from fwk.runs import RunLock, run_state
from fwk.safeio import load_state
from tests.faults.common import (HARNESS, PCA_RECIPE, TRAIN_RECIPE, assert_complete, assert_no_temporary_files,
                                 fwk_run, killed_at, models, recipe, resume, run_dirs)


def _refused_while_incomplete(d, capsys, state: str) -> None:
    """Readers of a run directory refuse it until it is complete: fwk report and open_run."""
    assert run_state(d)[0] == state
    capsys.readouterr()
    assert main(["report", str(d)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"fwk run --resume {d}" in err
    with pytest.raises(FwkError, match="--resume"):
        open_run(d)


# ------------------------------------------------------------------ crashes that are not fwk errors

@pytest.mark.parametrize("exc", [RuntimeError("a bug in a metric"), KeyboardInterrupt()])
def test_crash_marks_the_run_failed_and_resume_finishes_it(tmp_path, env, monkeypatch, capsys, baseline, exc):
    """Reproduction 2: an exception that is not an FwkError (a bug; Ctrl-C) during evaluation,
    after the model was saved: the directory carries FAILED (the error, its traceback, the
    resume command), readers refuse it, and --resume finishes it to the undisturbed numbers."""
    real = ev.evaluate_summary

    def broken(*a, **k):
        raise exc

    monkeypatch.setattr(ev, "evaluate_summary", broken)
    r = recipe(tmp_path)
    if isinstance(exc, KeyboardInterrupt):
        assert fwk_run(r, tmp_path / "runs")[0] == 130  # `fwk: interrupted`
    else:
        with pytest.raises(type(exc)):  # a bug shows its traceback
            fwk_run(r, tmp_path / "runs")
    (d,) = run_dirs(tmp_path / "runs")
    failed = (d / "FAILED").read_text()
    first = failed.splitlines()[0]
    assert (first == "interrupted (Ctrl-C)") if isinstance(exc, KeyboardInterrupt) else (first == "RuntimeError: a bug in a metric")
    assert f"fwk run --resume {d}" in failed and "Traceback" in failed
    assert not (d / "RUNNING").exists() and not (d / "metrics.json").exists() and (d / "models" / "pca.safetensors").exists()
    assert_no_temporary_files(d)
    _refused_while_incomplete(d, capsys, "failed")
    monkeypatch.setattr(ev, "evaluate_summary", real)
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline()
    assert "resuming a run that failed (RuntimeError" in (d / "log.txt").read_text() or isinstance(exc, KeyboardInterrupt)


def test_user_error_before_any_work_leaves_no_directory(tmp_path, env, monkeypatch):
    """An FwkError found while running, before a model or checkpoint exists: the directory this
    invocation created is removed (nothing in it is worth resuming)."""
    from fwk.errors import DataError

    def bad(*a, **k):
        raise DataError("s01/neutral.obj: unreadable")

    monkeypatch.setattr("fwk_reconstruct.split_and_preprocess", bad)
    rc, d = fwk_run(recipe(tmp_path), tmp_path / "runs")
    assert rc == 2 and d is None and run_dirs(tmp_path / "runs") == []


# ------------------------------------------------------------------ SIGKILL at each stage

@pytest.mark.parametrize("point,n,left", [
    ("evaluate", 2, "models/pca.safetensors"),   # evaluation: the model saved, one split evaluated
    ("report", 1, "metrics.json"),      # report: metrics.json written, report.md's temporary file not renamed
])
def test_killed_then_resumed(tmp_path, env, capsys, baseline, point, n, left):
    d = killed_at(point, n, recipe(tmp_path), tmp_path / "runs", env)
    assert (d / left).exists() and not (d / "report.md").exists()
    assert (d / "RUNNING").exists() and not (d / "FAILED").exists()
    if point == "report":  # the write cut short left its temporary file; the resume removes it
        assert [p.name.startswith(".report.md.") for p in d.glob("*.tmp")] == [True]
    _refused_while_incomplete(d, capsys, "killed")
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline()
    assert "resuming a run whose process was killed" in (d / "log.txt").read_text()


def test_sigterm_marks_the_run_failed(tmp_path, env, capsys, baseline):
    """SIGTERM (a scheduler's time limit) during evaluation: exit 143, FAILED says so (RUNNING is
    gone), and --resume finishes the run to the undisturbed numbers."""
    d = killed_at("term", 2, recipe(tmp_path), tmp_path / "runs", env, status=143)
    assert (d / "FAILED").read_text().splitlines()[0] == "terminated (SIGTERM)"
    assert not (d / "RUNNING").exists() and (d / "models" / "pca.safetensors").exists()
    _refused_while_incomplete(d, capsys, "failed")
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline()


@pytest.mark.slow
def test_killed_during_training_then_resumed(tmp_path, env, capsys, baseline):
    """Killed after the first training checkpoint of the network: resume continues from it and
    every metric equals an undisturbed run's."""
    d = killed_at("train", 1, recipe(tmp_path, TRAIN_RECIPE), tmp_path / "runs", env)
    assert (d / "models" / "pca.safetensors").exists() and not (d / "models" / "mlp.safetensors").exists()
    assert any((d / "checkpoints").rglob("*.ckpt"))
    _refused_while_incomplete(d, capsys, "killed")
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline(TRAIN_RECIPE)
    (curve,) = (d / "curves" / "mlp").glob("*.json")
    curves = json.loads(curve.read_text())
    assert curves["finished"] and curves["epochs_run"] == 3


@pytest.mark.slow
def test_killed_with_a_checkpoint_queued_then_resumed(tmp_path, env, capsys, baseline):
    """Killed while the network's first checkpoint waits for its write (or is being written, on the
    checkpoints' thread): no epoch file, or no whole one, is there to resume from, yet nothing half
    written is taken for one; resume trains the network again and every metric equals an undisturbed
    run's."""
    d = killed_at("train-queued", 1, recipe(tmp_path, TRAIN_RECIPE), tmp_path / "runs", env)
    assert not (d / "models" / "mlp.safetensors").exists()
    for p in (d / "checkpoints").rglob("*.ckpt"):  # whatever reached its name reads whole
        assert "state_dict" in load_state(p)
    _refused_while_incomplete(d, capsys, "killed")
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline(TRAIN_RECIPE)


# ------------------------------------------------------------------ side by side

def test_two_runs_started_together_into_one_folder(tmp_path, env, baseline):
    """Two processes, same recipe, same runs folder, same second: two directories, both complete,
    the same numbers (the dataset's cache entry built by both at once verifies)."""
    r, runs = recipe(tmp_path), tmp_path / "runs"
    cmd = [sys.executable, str(HARNESS), "never", "0", "--quiet", "run", str(r), "--runs-dir", str(runs)]
    procs = [subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
    assert not any("fwk: warning: cache entry" in o[1] for o in outs), [o[1] for o in outs]
    a, b = run_dirs(runs)
    for d in (a, b):
        assert_complete(d)
    assert models(a) == models(b) == baseline()


def test_resume_of_a_run_another_process_writes_is_refused(tmp_path, env, capsys):
    rc, d = fwk_run(recipe(tmp_path), tmp_path / "runs")
    assert rc == 0
    before = {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    lock = RunLock(d)
    lock.acquire()  # another writer (a lock is per open file: this process's own resume is refused too)
    try:
        capsys.readouterr()
        assert run_state(d)[0] == "running"
        assert resume(d) == 2
        err = capsys.readouterr().err
        assert "another fwk process is writing this run" in err and err.count("\n") == 1
        assert main(["report", str(d)]) == 2 and "still running" in capsys.readouterr().err
    finally:
        lock.release()
    after = {p: p.read_bytes() for p in d.rglob("*") if p.is_file()}
    assert after == before  # the refused resume wrote nothing


def test_run_directories_made_at_once_are_distinct(tmp_path):
    """Sixteen run directories of one name asked for in the same second, from sixteen threads:
    sixteen distinct folders (mkdir is the arbiter), none shared."""
    from concurrent.futures import ThreadPoolExecutor

    from fwk.runs import new_run_dir

    with ThreadPoolExecutor(16) as pool:
        made = list(pool.map(lambda _: new_run_dir(tmp_path / "runs", "same"), range(16)))
    assert len(set(made)) == 16 and sorted(made) == run_dirs(tmp_path / "runs")


def test_work_of_sub_runs_is_worth_keeping(tmp_path):
    """An fwk error late in a run removes its directory only when nothing in it would be reused:
    a sub-run's trained model (edit's reconstruct/models/) counts."""
    from fwk.runs import _worth_keeping

    d = tmp_path / "run"
    (d / "figures").mkdir(parents=True)
    (d / "figures" / "a.png").write_bytes(b"x")
    assert not _worth_keeping(d)
    (d / "reconstruct" / "models").mkdir(parents=True)
    assert not _worth_keeping(d)  # an empty folder is no work
    (d / "reconstruct" / "models" / "vae.safetensors").write_bytes(b"x")
    assert _worth_keeping(d)
