import numpy as np

from fwk.cache import Cache, content_key


def test_key_covers_content():
    a = np.arange(6.0)
    assert content_key(a) == content_key(a.copy())
    assert content_key(a) != content_key(a + 1e-12)
    assert content_key(a) != content_key(a.astype(np.float32))
    assert content_key({"k": 1, "j": [1, 2]}) == content_key({"j": [1, 2], "k": 1})


def test_get_or_build_and_corrupt_entry_rebuilt(tmp_path):
    c = Cache(tmp_path)
    calls = []

    def build():
        calls.append(1)
        return {"x": np.ones(3)}

    v1 = c.get_or_build("ns", ("a",), build)
    v2 = c.get_or_build("ns", ("a",), build)
    assert len(calls) == 1 and np.array_equal(v1["x"], v2["x"])
    for f in (tmp_path / "ns").glob("*.bin"):
        f.write_bytes(b"garbage")
    v3 = c.get_or_build("ns", ("a",), build)
    assert len(calls) == 2 and np.array_equal(v3["x"], np.ones(3))


def test_memmap_array(tmp_path):
    c = Cache(tmp_path)
    a = c.memmap_array("arr", ("k",), lambda: np.arange(12.0).reshape(3, 4))
    assert isinstance(a, np.memmap) and a.shape == (3, 4)
    for f in (tmp_path / "arr").glob("*.npy"):
        f.write_bytes(b"x")
    b = c.memmap_array("arr", ("k",), lambda: np.arange(12.0).reshape(3, 4))
    assert np.array_equal(b, np.arange(12.0).reshape(3, 4))


def test_disabled_or_unwritable_cache_still_computes(tmp_path):
    c = Cache(tmp_path / "nope", enabled=False)
    assert c.get_or_build("ns", (1,), lambda: 5) == 5


def test_memo_each_builds_only_the_missing_keys_together_and_keeps_at_most_max_bytes():
    from fwk.cache import forget, memo_each

    forget("test.memo_each")
    built = []

    def build(missing):
        built.append(list(missing))
        return [np.full(4, float(keys[i])) for i in missing]  # 32 bytes each

    keys = [1, 2, 2, 3]  # a key twice: built once
    out = memo_each("test.memo_each", keys, build, max_bytes=128)
    assert built == [[0, 1, 3]] and [v[0] for v in out] == [1, 2, 2, 3]
    keys = [3, 4, 1]
    out = memo_each("test.memo_each", keys, build, max_bytes=128)
    assert built[-1] == [1] and [v[0] for v in out] == [3, 4, 1]  # 1 and 3 remembered; 4 fills the 128 bytes
    keys = [5]
    memo_each("test.memo_each", keys, build, max_bytes=128)  # 1, the oldest, dropped for 5
    keys = [1, 2]
    memo_each("test.memo_each", keys, build, max_bytes=128)
    assert built[-1] == [0]  # 1 again; 2 was kept
    keys = list(range(10, 15))  # 160 bytes: more than max_bytes, returned and not kept
    memo_each("test.memo_each", keys, build, max_bytes=128)
    memo_each("test.memo_each", keys, build, max_bytes=128)
    assert built[-2:] == [[0, 1, 2, 3, 4]] * 2
    forget("test.memo_each")


def test_atomic_link_is_the_same_file_and_replaces_the_old_one(tmp_path, monkeypatch):
    """``atomic_link``: ``path`` becomes ``src`` (one file, not a symlink) in place of what it was;
    where hard links fail it is a copy; a missing ``src`` leaves ``path`` and no temporary file."""
    import errno
    import os

    import pytest

    from fwk import cache
    src, path = tmp_path / "epoch003.ckpt", tmp_path / "last.ckpt"
    src.write_bytes(b"new state")
    path.write_bytes(b"old state")
    cache.atomic_link(src, path)
    assert path.samefile(src) and not path.is_symlink() and path.read_bytes() == b"new state"
    src.unlink()  # a pruned epoch file: last.ckpt stays whole
    assert path.read_bytes() == b"new state"

    def no_links(a, b):
        raise OSError(errno.EPERM, "Operation not permitted")

    src.write_bytes(b"copied")
    with monkeypatch.context() as m:
        m.setattr(os, "link", no_links)
        cache.atomic_link(src, path)
    assert path.read_bytes() == b"copied" and not path.samefile(src)
    with pytest.raises(FileNotFoundError):
        cache.atomic_link(tmp_path / "absent", path)
    assert path.read_bytes() == b"copied"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["epoch003.ckpt", "last.ckpt"]
