"""Cache entries that are corrupt, truncated or half-written are rebuilt, never used (issue 16,
reproduction 1)."""
from __future__ import annotations

import hashlib
import pickle

import numpy as np
import pytest

from fwk.cache import Cache
from tests.faults.common import PCA_RECIPE, assert_complete, fwk_run, killed_at, models, recipe


def _array_entry(root):
    (npy,) = (root / "ns").glob("*.npy")
    return npy


def _build(calls):
    def build():
        calls.append(1)
        return np.arange(4096.0).reshape(64, 64)
    return build


@pytest.mark.parametrize("damage", ["scaled", "garbage-head", "truncated", "hash-garbage"])
def test_damaged_array_entry_is_rebuilt_with_one_warning(tmp_path, capsys, damage):
    c, calls = Cache(tmp_path), []
    ref = np.array(c.memmap_array("ns", ("k",), _build(calls)))
    npy = _array_entry(tmp_path)
    raw = npy.read_bytes()
    if damage == "scaled":  # same dtype and shape, values 5 % off in one row: what the old check missed
        a = np.load(npy, allow_pickle=False)
        a[3] *= 1.05
        np.save(npy, a)
    elif damage == "garbage-head":
        npy.write_bytes(b"\x13" * 4096 + raw[4096:])
    elif damage == "truncated":
        npy.write_bytes(raw[: len(raw) // 2])
    else:
        npy.with_suffix(".sha256").write_text("0" * 64)
    capsys.readouterr()
    got = c.memmap_array("ns", ("k",), _build(calls))
    err = capsys.readouterr().err
    assert len(calls) == 2, "the damaged entry was used"
    assert np.array_equal(got, ref)
    assert err.count("\n") == 1 and err.startswith("fwk: warning: cache entry") and "rebuilt" in err
    # the rebuilt entry verifies: the next read neither rebuilds nor warns
    assert np.array_equal(c.memmap_array("ns", ("k",), _build(calls)), ref) and len(calls) == 2
    assert capsys.readouterr().err == ""


@pytest.mark.parametrize("damage", ["flipped-byte", "truncated", "garbage"])
def test_damaged_pickled_entry_is_rebuilt_with_one_warning(tmp_path, capsys, damage):
    c, calls = Cache(tmp_path), []

    def build():
        calls.append(1)
        return {"x": np.linspace(0, 1, 50)}

    c.get_or_build("ns", ("a",), build)
    (binf,) = (tmp_path / "ns").glob("*.bin")
    raw = bytearray(binf.read_bytes())
    if damage == "flipped-byte":
        at = bytes(raw).find(np.linspace(0, 1, 50).tobytes())
        raw[at + 83] ^= 0x01  # a value inside the array: still unpickles, to a wrong number
        assert not np.array_equal(pickle.loads(bytes(raw))["x"], np.linspace(0, 1, 50))
    elif damage == "truncated":
        raw = raw[: len(raw) // 3]
    else:
        raw = bytearray(b"garbage")
    binf.write_bytes(bytes(raw))
    capsys.readouterr()
    v = c.get_or_build("ns", ("a",), build)
    assert len(calls) == 2 and np.array_equal(v["x"], np.linspace(0, 1, 50))
    assert capsys.readouterr().err.count("fwk: warning: cache entry") == 1


def test_entry_without_its_hash_is_a_silent_miss(tmp_path, capsys):
    """A write cut short between the data and the hash (the hash is written last)."""
    c, calls = Cache(tmp_path), []
    c.memmap_array("ns", ("k",), _build(calls))
    _array_entry(tmp_path).with_suffix(".sha256").unlink()
    c.memmap_array("ns", ("k",), _build(calls))
    assert len(calls) == 2 and capsys.readouterr().err == ""


def test_entries_are_written_with_the_umask_mode(tmp_path):
    import os

    old = os.umask(0o002)
    try:
        c = Cache(tmp_path)
        c.memmap_array("ns", ("k",), _build([]))
        c.get_or_build("ns", ("b",), lambda: 1)
    finally:
        os.umask(old)
    for p in (tmp_path / "ns").iterdir():
        assert p.stat().st_mode & 0o777 == 0o664, p


def test_corrupt_dataset_cache_in_a_run_is_rebuilt(tmp_path, env, capsys, baseline):
    """Reproduction 1: one subject's cached positions scaled by 5 %, same shape: the rerun warns
    once, rebuilds and gives the undisturbed numbers."""
    r = recipe(tmp_path)
    rc, first = fwk_run(r, tmp_path / "runs")
    assert rc == 0
    (npy,) = (tmp_path / "cache" / "synthetic-heads").glob("*.npy")
    a = np.load(npy, allow_pickle=False)
    a[1] *= 1.05
    np.save(npy, a)
    capsys.readouterr()
    rc, second = fwk_run(r, tmp_path / "runs")
    err = capsys.readouterr().err
    assert rc == 0 and err.count("fwk: warning: cache entry") == 1 and str(npy) in err
    assert models(second) == models(first) == baseline()
    assert hashlib.sha256(npy.read_bytes()).hexdigest() == npy.with_suffix(".sha256").read_text()


def test_killed_between_entry_and_hash(tmp_path, env, baseline):
    """Killed while loading data: the dataset's cache entry is written, its hash not. The resumed
    run rebuilds the entry (never uses the unverified one) and gives the undisturbed numbers."""
    d = killed_at("cache-hash", 1, recipe(tmp_path), tmp_path / "runs", env)
    (npy,) = (tmp_path / "cache" / "synthetic-heads").glob("*.npy")
    assert not npy.with_suffix(".sha256").exists()
    npy.write_bytes(npy.read_bytes()[:-800] + b"\0" * 800)  # and what it left is not what a rebuild gives
    assert (d / "RUNNING").exists() and not (d / "metrics.json").exists()
    from tests.faults.common import resume

    assert resume(d) == 0
    assert_complete(d)
    assert models(d) == baseline()
    assert npy.with_suffix(".sha256").exists()


def test_temporary_files_of_killed_writes_are_swept(tmp_path):
    """A write killed between its temporary file and the rename leaves ``.<name>.XXXX.tmp``; the
    next write into that folder removes it once it is stale (a fresh one may be a live writer's)."""
    import os
    import time

    from fwk.cache import STALE_S

    c = Cache(tmp_path)
    c.get_or_build("ns", ("a",), lambda: 1)
    stale, fresh = tmp_path / "ns" / ".x.bin.abc.tmp", tmp_path / "ns" / ".y.bin.def.tmp"
    for p in (stale, fresh):
        p.write_bytes(b"half")
    old = time.time() - STALE_S - 10
    os.utime(stale, (old, old))
    c.get_or_build("ns", ("b",), lambda: 2)
    assert not stale.exists() and fresh.exists()


def test_modes_follow_the_umask():
    import os

    from fwk.cache import current_umask, dir_mode, file_mode

    old = os.umask(0o027)
    try:
        assert current_umask() == 0o027 and file_mode() == 0o640 and dir_mode() == 0o750
    finally:
        os.umask(old)
