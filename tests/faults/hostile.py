"""The check every hostile-input case of issue 25 makes (test_recipe_faults, test_mesh_faults,
test_plugin_faults): the command exits 2 within ``LIMIT_S`` seconds, prints one to three lines on
stderr and no traceback, and writes nothing outside the runs folder.

``refused`` runs ``fwk`` in this process (``fwk.cli.main``: quick, and an exception that is not
an FwkError fails the test with its traceback) or, with ``subprocess=True``, as
``python -m fwk.cli`` (for inputs that could block the process, and for plugins, which are found
at start-up)."""
from __future__ import annotations

import contextlib
import io
import os
import subprocess as sp
import sys
import time
from pathlib import Path

from fwk.cli import main

#: the longest a refusal may take (seconds)
LIMIT_S = 20
#: the most lines a refusal may print on stderr
MAX_LINES = 3


def snapshot(root: Path) -> dict[str, tuple]:
    """Every file and folder under ``root``: relative path -> (kind, size, mtime)."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            try:
                st = p.lstat()
            except OSError:
                continue
            out[str(p.relative_to(root))] = (st.st_mode >> 12, st.st_size if name in filenames else 0, st.st_mtime_ns)
    return out


def refused(argv: list[str], tmp_path: Path, *expect: str, runs: Path | None = None, subprocess: bool = False,
            env: dict | None = None, cwd: Path | None = None) -> str:
    """Run ``fwk *argv`` and assert the refusal (see the module docstring); every string of
    ``expect`` must be in the message. ``tmp_path`` is watched: only ``runs`` (when given) may
    change under it. Returns stderr."""
    cwd = cwd or tmp_path
    before = snapshot(tmp_path)
    t0 = time.monotonic()
    if subprocess:
        p = sp.run([sys.executable, "-m", "fwk.cli", *argv], cwd=cwd, env=env, capture_output=True, text=True,
                   timeout=LIMIT_S + 30)
        rc, err = p.returncode, p.stderr
    else:
        buf, old = io.StringIO(), os.getcwd()
        os.chdir(cwd)
        try:
            with contextlib.redirect_stderr(buf):
                rc = main(list(argv))
        finally:
            os.chdir(old)
        err = buf.getvalue()
    elapsed = time.monotonic() - t0
    assert rc == 2, f"exit {rc}, expected 2: {err[-3000:]}"
    lines = err.splitlines()
    assert 1 <= len(lines) <= MAX_LINES, f"{len(lines)} lines on stderr: {err[-3000:]}"
    assert "Traceback" not in err, err[-3000:]
    assert elapsed < LIMIT_S, f"{elapsed:.1f} s"
    for e in expect:
        assert e in err, f"{e!r} not in {err!r}"
    after = snapshot(tmp_path)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    allowed = str(runs.relative_to(tmp_path)) if runs is not None else None
    outside = [k for k in changed if allowed is None or not (k == allowed or k.startswith(allowed + os.sep))]
    assert not outside, f"written outside the runs folder: {outside}"
    return err
