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
