"""Checks of the folders a user gives, before any work starts.

``check_dir(path, what)`` is called up front for every output folder a command takes
(``--runs-dir``, ``$FWK_RUNS_DIR``, ``$FWK_CACHE``, ``--out``): a NUL in the path, a name too
long, a file where a folder should be,
a folder that cannot be created or written (permissions, a read-only or pseudo file system such
as ``/proc``), or a file system with too little space left each raise a one-line ``PathError``
(exit 2) naming the path and the option or variable it came from. Nothing is created: the
nearest existing ancestor is probed with a temporary file that is removed at once.
"""
from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

from .errors import PathError

#: the space a run needs at the least (a smoke run writes ~5 MB, a full one a few hundred)
MIN_FREE_MB = 50


def _existing_ancestor(p: Path) -> Path:
    a = p
    while not os.path.lexists(a) and a != a.parent:
        a = a.parent
    return a


def check_dir(path, what: str, min_free_mb: float | None = None) -> Path:
    """``path`` (``~`` expanded) checked to be, or to be creatable as, a writable folder with at
    least ``min_free_mb`` MB free (default ``MIN_FREE_MB``; 0: no floor); ``what`` names where it came from (``--runs-dir``). Raises
    ``PathError`` with one line, else returns the path (not created)."""
    if not str(path).strip():
        raise PathError(f"{what}: empty path")
    if "\x00" in str(path):
        raise PathError(f"{what} {str(path)!r}: a path cannot contain a NUL character")
    p = Path(path).expanduser()
    where = f"{what} {p}"
    try:
        os.lstat(p)
    except (FileNotFoundError, NotADirectoryError):  # to be created; a file in the way is named below
        pass
    except OSError as exc:  # a name too long, a symlink loop: the ancestor walk would not see them
        raise PathError(f"{where}: {exc.strerror}") from None
    a = _existing_ancestor(p)
    if not a.is_dir():
        if a == p:
            raise PathError(f"{where}: a file, not a folder")
        raise PathError(f"{where}: {a} is a file in the way (not a folder)")
    try:
        fd, probe = tempfile.mkstemp(dir=a, prefix=".fwk-probe-")
        try:
            os.write(fd, b"\0")
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
            raise PathError(f"{where}: no space left to write there ({exc.strerror})") from None
        if exc.errno in (errno.EACCES, errno.EPERM):
            raise PathError(f"{where}: not writable ({a} does not let this user create files)") from None
        if exc.errno == errno.EROFS:
            raise PathError(f"{where}: on a read-only file system") from None
        raise PathError(f"{where}: cannot create files under {a} ({exc.strerror})") from None
    min_free_mb = MIN_FREE_MB if min_free_mb is None else min_free_mb
    try:
        st = os.statvfs(a)
        free_mb = st.f_bavail * st.f_frsize / 2**20
    except (OSError, AttributeError):  # no statvfs (Windows): the probe above must do
        return p
    if free_mb < min_free_mb:
        raise PathError(f"{where}: no space: {free_mb:.0f} MB free on its file system, "
                        f"at least {min_free_mb:.0f} MB needed")
    return p
