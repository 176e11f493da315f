"""Folders that cannot take the output, full destinations, and file modes (issue 16,
reproductions 3 and 4): one line and exit 2 before anything is written, or a run that fails
cleanly and resumes; files get the umask's mode."""
from __future__ import annotations

import errno
import os
import resource
import stat

import pytest

import fwk.paths
from fwk.cache import Cache
from fwk.cli import main
from tests.faults.common import (assert_complete, assert_no_temporary_files, fwk_run, models, recipe, resume,
                                 run_dirs)


def _one_line_exit_2(capsys, argv, *expect):
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("fwk: error: "), err
    for e in expect:
        assert e in err, err
    return err


@pytest.mark.parametrize("runs_dir,expect", [
    ("/proc/x", "cannot create files under /proc"),                # not writable (a pseudo file system)
    ("{tmp}/file/runs", "is a file in the way"),                   # a file where a folder should be
    ("{tmp}/file", "a file, not a folder"),
])
def test_bad_runs_dir(tmp_path, env, capsys, runs_dir, expect):
    (tmp_path / "file").write_text("x")
    r = recipe(tmp_path)
    runs_dir = runs_dir.format(tmp=tmp_path)
    _one_line_exit_2(capsys, ["run", str(r), "--runs-dir", runs_dir], f"--runs-dir {runs_dir}", expect)


def test_bad_runs_dir_from_the_environment_and_bad_cache(tmp_path, env, capsys, monkeypatch):
    (tmp_path / "file").write_text("x")
    r = recipe(tmp_path)
    monkeypatch.setenv("FWK_RUNS_DIR", "/proc/x")
    _one_line_exit_2(capsys, ["run", str(r)], "$FWK_RUNS_DIR /proc/x")
    monkeypatch.delenv("FWK_RUNS_DIR")
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "file" / "cache"))
    _one_line_exit_2(capsys, ["run", str(r), "--runs-dir", str(tmp_path / "runs")], "$FWK_CACHE", "file in the way")
    assert run_dirs(tmp_path / "runs") == []
    _one_line_exit_2(capsys, ["eval", str(r), str(r)], "$FWK_CACHE")  # every computing command checks it


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_read_only_runs_dir(tmp_path, env, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        _one_line_exit_2(capsys, ["run", str(recipe(tmp_path)), "--runs-dir", str(ro / "runs")], "not writable")
    finally:
        ro.chmod(0o700)


def test_no_space_is_found_up_front(tmp_path, env, capsys, monkeypatch):
    monkeypatch.setattr(fwk.paths, "MIN_FREE_MB", 1e12)  # more than any disk has: this one is "full"
    _one_line_exit_2(capsys, ["run", str(recipe(tmp_path)), "--runs-dir", str(tmp_path / "runs")], "no space")
    assert run_dirs(tmp_path / "runs") == []


def _limited(limit):
    """RLIMIT_FSIZE (soft) lowered in this process: a write past ``limit`` bytes fails with EFBIG
    (Python ignores SIGXFSZ), as on a full disk."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)

    class Limit:
        def __enter__(self):
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))

        def __exit__(self, *exc):
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))

    return Limit()


def test_full_destination_at_the_first_file(tmp_path, env, capsys):
    """A file-size limit of 0: the up-front probe finds no space; nothing is written."""
    r = recipe(tmp_path)
    capsys.readouterr()
    with _limited(0):
        rc = main(["--quiet", "run", str(r), "--runs-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert rc == 2 and "no space left to write there" in err and err.count("\n") == 1
    assert run_dirs(tmp_path / "runs") == []


def test_full_destination_while_writing_a_model(tmp_path, env, capsys, baseline):
    """Room for the small files, not for the dataset's cache entry nor the model: the cache entry
    is skipped (the computation goes on, nothing half-written is left to be read), the model's
    write stops the run with one line, exit 2, no temporary file, and the run directory (nothing
    in it worth resuming) is removed; with room, the same recipe gives the undisturbed numbers."""
    r = recipe(tmp_path)
    capsys.readouterr()
    with _limited(12_000):
        rc = main(["--quiet", "run", str(r), "--runs-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert rc == 2 and "models/pca.safetensors: cannot write (File too large)" in err and err.count("\n") == 1, err
    assert run_dirs(tmp_path / "runs") == []
    assert_no_temporary_files(tmp_path / "runs")
    cache = tmp_path / "cache"
    assert_no_temporary_files(cache)
    assert not list(cache.rglob("*.npy"))  # the dataset's entry (> 12 kB) could not be written: none is there
    for entry in cache.rglob("*.bin"):  # and the small entries that could be, verify
        assert Cache(cache).load(entry.parent.name, entry.stem) is not None, entry  # its HMAC verifies
    rc, d = fwk_run(r, tmp_path / "runs")
    assert rc == 0 and models(d) == baseline()


def test_full_destination_after_the_model_then_resume(tmp_path, env, capsys, monkeypatch, baseline):
    """The disk fills after the model is saved (metrics.json cannot be written): FAILED with the
    one-line error, the model kept; --resume, with room again, loads it and finishes."""
    import fwk.cache
    import fwk.runs

    real = fwk.cache.atomic_write_bytes

    def full(path, data):
        if str(path).endswith("metrics.json"):
            raise fwk.errors.WriteError(errno.ENOSPC, f"{path}: cannot write (No space left on device)")
        return real(path, data)

    monkeypatch.setattr(fwk.runs, "atomic_write_bytes", full)
    r = recipe(tmp_path)
    rc, d = fwk_run(r, tmp_path / "runs")
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "No space left on device" in err
    assert f"the run so far is kept: fwk run --resume {d}" in err
    assert (d / "FAILED").read_text().startswith(f"{d / 'metrics.json'}: cannot write (No space left on device)")
    assert (d / "models" / "pca.safetensors").exists() and not (d / "metrics.json").exists()
    monkeypatch.setattr(fwk.runs, "atomic_write_bytes", real)
    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline()
    assert "[pca] loading the finished model" in (d / "log.txt").read_text()


@pytest.mark.parametrize("mask,mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_files_get_the_umask_mode(tmp_path, env, mask, mode):
    """Reproduction 4: every file of a run (recipe.yaml, metrics.json, report.md, split.json,
    versions.json, the npz, models/*.safetensors, log.txt) has the mode the umask gives, not 0600."""
    old = os.umask(mask)
    try:
        rc, d = fwk_run(recipe(tmp_path), tmp_path / "runs")
    finally:
        os.umask(old)
    assert rc == 0
    files = [p for p in d.rglob("*") if p.is_file()]
    assert {"recipe.yaml", "metrics.json", "report.md", "split.json", "versions.json", "preprocess.npz",
            "pca.safetensors", "log.txt"} <= {p.name for p in files}
    for p in files:
        assert stat.S_IMODE(p.stat().st_mode) == mode, (p, oct(p.stat().st_mode))


def test_sample_out_is_checked_before_the_run_is_read(tmp_path, capsys):
    """fwk sample --out /proc/x: one line, exit 2, before the run directory is even opened."""
    from fwk.cli import main

    assert main(["sample", str(tmp_path / "no-such-run"), "--out", "/proc/x/samples"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--out /proc/x/samples" in err, err
