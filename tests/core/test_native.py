"""fwk.native: plugins' C++ kernels built on first use, refused cleanly where they cannot build,
rebuilt when the shared header changes; torch's stale build locks removed."""
import os
import time
from pathlib import Path

import torch

from fwk import native


def test_a_stale_build_lock_is_removed_and_a_fresh_one_kept(tmp_path):
    lock = tmp_path / "lock"
    lock.write_text("")
    native.clear_stale_lock(tmp_path)
    assert lock.exists(), "a build running now keeps its lock"
    old = time.time() - native.STALE_LOCK_SECONDS - 60
    os.utime(lock, (old, old))
    native.clear_stale_lock(tmp_path)
    assert not lock.exists()


def _extension(tmp_path, body="int twice(int a) { return 2 * a; }\n"):
    src = tmp_path / "k.cpp"
    src.write_text('#include "fwk_native.h"\n' + body
                   + "PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) { m.def(\"twice\", &twice); }\n")
    return native.Extension(f"fwk_test_native_{abs(hash(str(tmp_path))) % 10**8}", [src], label="test",
                            env="FWK_TEST_NATIVE")


def test_no_compiler_is_one_line_and_the_torch_code(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    ext = _extension(tmp_path)
    x = torch.zeros(2)
    assert not ext.usable(x) and not ext.available()
    assert ext.failed
    err = capsys.readouterr().err
    assert err.count("native kernels unavailable") == 1, err
    assert ext.load() is None and capsys.readouterr().err == "", "the reason is printed once"


def test_usable_only_for_float32_cpu_outside_autocast_and_when_enabled(tmp_path, monkeypatch):
    ext = _extension(tmp_path)
    ext._module = object()  # as if built: usable() is about the arguments from here on
    x = torch.zeros(2)
    assert ext.usable(x)
    assert not ext.usable(x.double())
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert not ext.usable(x)
    monkeypatch.setenv("FWK_TEST_NATIVE", "0")
    assert not ext.usable(x) and not ext.available()


def test_the_headers_digest_is_a_build_flag(tmp_path, monkeypatch):
    """torch keys its cache by sources and flags, not included headers: the header's digest is a
    define, so another header gives another build. Checked on the flags, without compiling."""
    import hashlib

    seen = []
    import torch.utils.cpp_extension as ce

    monkeypatch.setattr(ce, "load", lambda **kw: seen.append(kw["extra_cflags"]) or object())
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    header = (native.HEADER_DIR / "fwk_native.h").read_bytes()
    _extension(tmp_path).load()
    assert f"-DFWK_NATIVE_H={hashlib.sha256(header).hexdigest()[:16]}" in seen[0]


def test_processes_that_start_together_take_turns_and_one_says_it_compiles(tmp_path, monkeypatch, capsys):
    """The build lock (flock) lets one build; the next finds the module built and says nothing.
    Two threads with their own Extension objects stand in for two processes (flock locks belong to
    each open file, so they exclude each other within one process too); torch's build is replaced
    by one that takes a second and writes the module."""
    import threading

    import torch.utils.cpp_extension as ce

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    building = []

    def fake_load(name, build_directory, **kw):
        building.append(name)
        assert len(building) == 1 or (Path(build_directory) / f"{name}.so").exists(), "two builds at once"
        time.sleep(1.0)
        (Path(build_directory) / f"{name}.so").write_text("")
        return object()

    monkeypatch.setattr(ce, "load", fake_load)
    exts = [_extension(tmp_path) for _ in range(2)]
    threads = [threading.Thread(target=e.load) for e in exts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(e.failed is None and e._module is not None for e in exts)
    assert capsys.readouterr().err.count("compiling its native kernels") == 1
