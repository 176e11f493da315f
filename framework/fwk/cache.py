"""Content-hash keyed cache for derived data (parsed meshes, operators, eigenbases, ...).

A key covers every input that changes the value (arrays are hashed by dtype, shape and bytes).
Every entry is written atomically (temporary file + rename, with the process umask's file mode)
with a check value beside it, written last:

* a pickled value (``<key>.bin``: plugins cache objects such as a sampler's levels) with its
  HMAC-SHA256 (``<key>.hmac``), keyed by a secret of the user's that never lies in the cache
  (``cache_key``: ``$FWK_KEY_FILE``, else ``$XDG_CONFIG_HOME/fwk/cache.key``, else
  ``~/.config/fwk/cache.key``; created with mode 600; refused, one line, when its mode lets others
  in or another user owns it). Unpickling runs code, so an entry is unpickled only when its HMAC
  verifies: one that anyone else wrote (a cache folder received, shared or planted) cannot, and
  is rebuilt instead;
* a large array (``<key>.npy``, memory-mapped; read with ``allow_pickle=False``, so it can hold
  numbers only) with the SHA-256 of its bytes (``<key>.sha256``).

Every read checks the bytes: an entry that does not verify (changed, truncated, half-written by
a killed process, written without the user's key) or cannot be parsed is never used: it is
rebuilt, with one warning line on stderr (an entry without its check value, a write cut short,
or with a check value of an older format, is a plain miss). Temporary files that killed writers
left are removed (after ``STALE_S``) when the folder is next written. Location: ``Cache(root)``,
else ``$FWK_CACHE``, else ``~/.cache/fwk``.

``memo(namespace, key, build)`` is the in-process counterpart (nothing written): values derived
from a topology or a level (edge structures, spirals, factorisations, metric stencils) built once
per process and key, at most ``size`` per namespace.
"""
from __future__ import annotations

import errno
import hashlib
import hmac
import io
import os
import pickle
import re
import secrets
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from .errors import FwkError, WriteError


@runtime_checkable
class ContentHashed(Protocol):
    """A value that states its own key (``fwk.data.Template``: topology and positions)."""

    def content_hash(self) -> str: ...


_PLAIN = (str, bytes, int, float, complex, type(None), np.generic)  # values keyed by their repr


def _feed(h, obj) -> None:
    if isinstance(obj, np.ndarray):
        a = np.ascontiguousarray(obj)
        h.update(f"nd{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif isinstance(obj, (list, tuple)):
        h.update(f"seq{type(obj).__name__}{len(obj)}(".encode())
        for x in obj:
            _feed(h, x)
        h.update(b")")
    elif isinstance(obj, dict):
        h.update(f"map{len(obj)}(".encode())
        for k in sorted(obj, key=repr):
            _feed(h, k)
            _feed(h, obj[k])
        h.update(b")")
    elif not isinstance(obj, _PLAIN) and isinstance(obj, ContentHashed):  # the protocol check is slow
        h.update(f"obj{type(obj).__name__}{obj.content_hash()}".encode())
    else:
        h.update(f"{type(obj).__name__}:{obj!r}".encode())


def content_key(*parts: Any) -> str:
    """A stable hex key of arrays, numbers, strings and (nested) containers."""
    h = hashlib.sha256()
    for p in parts:
        _feed(h, p)
    return h.hexdigest()[:32]


_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process umask (read from /proc on Linux, else set and restored under a lock)."""
    try:
        with open("/proc/self/status", "rb") as f:
            for line in f:
                if line.startswith(b"Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a plain ``open(path, "w")`` would give a new file: 0o666 less the umask."""
    return 0o666 & ~current_umask()


def dir_mode() -> int:
    """The mode a plain ``mkdir`` would give a new folder: 0o777 less the umask (for a folder
    made with ``tempfile.mkdtemp``, 0700, before it is renamed into place)."""
    return 0o777 & ~current_umask()


#: write errors that are the user's to fix (space, quota, permissions): one line, not a traceback
_USER_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EACCES, errno.EPERM, errno.EROFS}


def _atomically(path: Path, make) -> None:
    """``make(tmp)`` creates the new file at a temporary name beside ``path`` (``.<name>.<random>.tmp``),
    which is then renamed over ``path``: readers see the old file or the new one, never a part. A full
    disk, a quota, a file-size limit or a permission raises ``WriteError`` (an ``FwkError`` and an
    ``OSError``) naming ``path``; no temporary file stays."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.parent / f".{path.name}.{secrets.token_hex(8)}.tmp"
        make(tmp)
        os.replace(tmp, path)
        tmp = None
    except OSError as exc:
        if exc.errno in _USER_ERRNOS and not isinstance(exc, WriteError):
            raise WriteError(exc.errno, f"{path}: cannot write ({exc.strerror})") from None
        raise
    finally:
        if tmp is not None and os.path.lexists(tmp):
            os.unlink(tmp)


def atomic_write_bytes(path: Path, data) -> None:
    """Write ``data`` (bytes, or a list of bytes-like parts written one after the other) to ``path``
    through a temporary file, flushed to disk, and a rename (``_atomically``: errors as there). The
    file gets the mode the umask gives new files (not the temporary file's 0600)."""

    def write(tmp):
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), file_mode())
            for part in (data if isinstance(data, list) else [data]):
                f.write(part)
            f.flush()
            os.fsync(f.fileno())

    _atomically(path, write)


def atomic_link(src: Path, path: Path) -> None:
    """Make ``path`` the file ``src`` is, atomically (``_atomically``): a hard link made under a
    temporary name and renamed over ``path``. A hard link is a plain file, not a symlink, so nothing
    reading ``path`` is sent elsewhere. Where the file system has no hard links, a copy."""

    def link(tmp):
        try:
            os.link(src, tmp)
        except OSError as exc:
            if exc.errno not in (errno.EPERM, errno.EXDEV, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP):
                raise
            shutil.copyfile(src, tmp)

    _atomically(path, link)


def warn(message: str) -> None:
    """One warning line on stderr: ``fwk: warning: message``."""
    print(f"fwk: warning: {message}", file=sys.stderr, flush=True)


_HEX64 = re.compile(r"^[0-9a-f]{64}$")


def file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes (read in blocks, not whole into memory)."""
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


#: the variable that names the cache key file
KEY_ENV = "FWK_KEY_FILE"
_KEYS: dict[str, bytes] = {}
_NO_KEY_WARNED: set[str] = set()


def key_path() -> Path:
    """Where the user's cache key lives: ``$FWK_KEY_FILE``, else ``$XDG_CONFIG_HOME/fwk/cache.key``,
    else ``~/.config/fwk/cache.key``: never in the cache folder, which others may have written."""
    if os.environ.get(KEY_ENV):
        return Path(os.environ[KEY_ENV]).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config"
    return Path(base).expanduser() / "fwk" / "cache.key"


def _create_key(path: Path) -> None:
    """A new random key at ``path``, mode 600, its folder 700 when made here; made whole in a
    temporary file and linked into place, so that a concurrent creator's key wins untouched."""
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")  # mode 0600
    try:
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(32) + "\n")
            f.flush()
            os.fsync(f.fileno())
        try:
            os.link(tmp, path)
        except FileExistsError:
            pass
    finally:
        os.unlink(tmp)


def cache_key() -> bytes | None:
    """The user's secret that authenticates pickled cache entries (see the module docstring),
    created on first use. ``FwkError`` (one line) when the file is another user's or others may
    read or write it; None, with one warning line, when it cannot be created or read (then
    pickled entries are neither read nor written)."""
    path = key_path()
    found = _KEYS.get(str(path))
    if found is not None:
        return found
    try:
        if not path.exists():
            _create_key(path)
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        with os.fdopen(fd, "rb") as f:
            st = os.fstat(f.fileno())
            if st.st_uid != os.getuid():
                raise FwkError(f"{path}: the cache key belongs to another user (uid {st.st_uid}); fwk trusts "
                               f"only a key file of its own user (${KEY_ENV} chooses another place)")
            if st.st_mode & 0o077:
                raise FwkError(f"{path}: the cache key may be read or written by others (mode "
                               f"{stat_mode(st.st_mode)}); make it private with: chmod 600 {path}")
            secret = f.read(4096).strip()
    except OSError as exc:
        if str(path) not in _NO_KEY_WARNED:
            _NO_KEY_WARNED.add(str(path))
            warn(f"{path}: the cache key cannot be created or read ({exc.strerror or exc}); cached objects "
                 f"are neither read nor written (set ${KEY_ENV} to a private file)")
        return None
    if len(secret) < 32:
        raise FwkError(f"{path}: the cache key is too short ({len(secret)} bytes); remove it and fwk makes a new one")
    _KEYS[str(path)] = secret
    return secret


def stat_mode(mode: int) -> str:
    return f"{mode & 0o777:03o}"


class Cache:
    """Derived data on disk under ``root``, keyed by the content of its inputs (see the module
    docstring)."""

    def __init__(self, root: str | os.PathLike | None = None, enabled: bool = True):
        root = root or os.environ.get("FWK_CACHE") or Path.home() / ".cache" / "fwk"
        self.root = Path(root).expanduser()
        self.enabled = enabled

    def _paths(self, namespace: str, key: str) -> tuple[Path, Path]:
        d = self.root / namespace
        return d / f"{key}.bin", d / f"{key}.hmac"

    @staticmethod
    def _mac(secret: bytes, namespace: str, key: str, data: bytes) -> str:
        """The HMAC-SHA256 of an entry: its namespace and key, then its bytes (an authentic entry
        moved to another key does not verify there)."""
        h = hmac.new(secret, f"fwk-cache/1\0{namespace}\0{key}\0".encode(), hashlib.sha256)
        h.update(data)
        return h.hexdigest()

    def _verified(self, data_p: Path, sum_p: Path, digest: Callable[[], str]) -> bool:
        """Whether the entry at ``data_p`` is whole: ``digest()`` (its bytes' SHA-256, or for a
        pickled entry their HMAC) equals ``sum_p``'s. A missing entry, or one without its check
        value (a write cut short: it is written last), is a plain miss; one whose bytes do not
        match gets one warning line (an entry of an older format, whose check file holds
        something else, is rebuilt silently)."""
        if not data_p.exists():
            return False
        try:
            if not sum_p.exists():  # a write cut short (or under way in another process): a miss
                return False
            expected = sum_p.read_text().strip()
            if not _HEX64.match(expected):
                return False  # an older format's entry: rebuilt without a word
            if hmac.compare_digest(digest(), expected):
                return True
        except OSError as exc:
            warn(f"cache entry {data_p} is unreadable ({exc.strerror}); rebuilt")
            return False
        if sum_p.suffix == ".hmac":
            warn(f"cache entry {data_p} does not verify with this user's cache key (changed, truncated or "
                 f"written by someone else); not unpickled, rebuilt")
        else:
            warn(f"cache entry {data_p} does not match its content hash (changed or truncated); rebuilt")
        return False

    def load(self, namespace: str, key: str) -> Any | None:
        """The value stored under ``key``, or None when missing, corrupt or not authentic (one
        warning line), or disabled. Only bytes whose HMAC verifies with the user's key are
        unpickled."""
        data_p, sum_p = self._paths(namespace, key)
        if not self.enabled:
            return None
        if not data_p.exists():
            return None
        secret = cache_key()
        if secret is None:
            return None
        data = b""

        def digest():
            nonlocal data
            data = data_p.read_bytes()
            return self._mac(secret, namespace, key, data)

        if not self._verified(data_p, sum_p, digest):
            return None
        try:
            return pickle.loads(data)
        except Exception as exc:  # verified bytes that do not unpickle: written by another version
            warn(f"cache entry {data_p} cannot be read ({type(exc).__name__}); rebuilt")
            return None

    def store(self, namespace: str, key: str, value: Any) -> None:
        """Store ``value`` under ``key`` (pickled, with its HMAC under the user's key); a write
        error is ignored (a read-only or full cache must not fail the computation)."""
        if not self.enabled:
            return
        secret = cache_key()
        if secret is None:
            return
        data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        data_p, sum_p = self._paths(namespace, key)
        _sweep(data_p.parent)
        try:
            _remove(sum_p)  # never a new value beside an old check value, should the next write be cut short
            atomic_write_bytes(data_p, data)
            atomic_write_bytes(sum_p, self._mac(secret, namespace, key, data).encode())
        except OSError:
            pass

    def get_or_build(self, namespace: str, key_parts: tuple, build: Callable[[], Any]) -> Any:
        """Return the cached value for ``key_parts`` or build, store and return it."""
        key = content_key(namespace, *key_parts)
        value = self.load(namespace, key)
        if value is None:
            value = build()
            self.store(namespace, key, value)
        return value

    def array_path(self, namespace: str, key_parts: tuple) -> Path:
        """A path for a large .npy array (memory-mapped by the caller) keyed by content."""
        return self.root / namespace / f"{content_key(namespace, *key_parts)}.npy"

    def memmap_array(self, namespace: str, key_parts: tuple, build: Callable[[], np.ndarray]) -> np.ndarray:
        """A read-only memory-mapped cached array, its bytes checked against their SHA-256 on
        every read; rebuilt (one warning line) if they do not verify or cannot be parsed."""
        p = self.array_path(namespace, key_parts)
        sum_p = p.with_suffix(".sha256")
        if self.enabled and self._verified(p, sum_p, lambda: file_sha256(p)):
            try:
                return np.load(p, mmap_mode="r", allow_pickle=False)
            except (ValueError, OSError) as exc:
                warn(f"cache entry {p} cannot be read ({exc}); rebuilt")
        arr = np.ascontiguousarray(build())
        if not self.enabled:
            return arr
        buf = io.BytesIO()
        np.save(buf, arr)
        data = buf.getvalue()
        _sweep(p.parent)
        try:
            _remove(sum_p)
            atomic_write_bytes(p, data)
            atomic_write_bytes(sum_p, hashlib.sha256(data).hexdigest().encode())
            return np.load(p, mmap_mode="r", allow_pickle=False)
        except OSError:
            return arr


#: a temporary file older than this in a cache folder was left by a write a killed process cut short
STALE_S = 3600.0


def _sweep(folder: Path) -> None:
    """Remove the temporary files writes cut short left in ``folder`` (older than ``STALE_S``: a
    write under way in another process is seconds old)."""
    try:
        old = time.time() - STALE_S
        for p in folder.glob(".*.tmp"):
            if p.stat().st_mtime < old:
                p.unlink()
    except OSError:
        pass


def _remove(path: Path) -> None:
    try:
        os.unlink(path)
    except FileNotFoundError:
        pass


_DEFAULT: Cache | None = None


def default_cache() -> Cache:
    """The process-wide cache at ``$FWK_CACHE`` (or ``~/.cache/fwk``), renewed when the variable
    changes."""
    global _DEFAULT
    if _DEFAULT is None or str(_DEFAULT.root) != str(Path(os.environ.get("FWK_CACHE") or Path.home() / ".cache" / "fwk").expanduser()):
        _DEFAULT = Cache()
    return _DEFAULT


_MEMOS: dict[str, dict] = {}


def memo(namespace: str, key, build: Callable[[], Any], size: int = 64) -> Any:
    """The value ``build()`` made for ``key`` (hashable; ``content_key(...)`` for arrays) earlier
    in this process, else build it now. Each namespace keeps at most ``size`` values, the oldest
    dropped first. Nothing is written to disk: ``Cache`` is what persists across runs."""
    table = _MEMOS.setdefault(namespace, {})
    if key in table:
        return table[key]
    value = build()
    while len(table) >= size:
        table.pop(next(iter(table)))
    table[key] = value
    return value


def memo_each(namespace: str, keys: list, build: Callable[[list[int]], list], max_bytes: int) -> list:
    """One value per key, as ``memo`` keeps them but key by key: the values made earlier in this
    process for some of ``keys`` are reused, and ``build(missing)`` makes the others together
    (``missing``: their positions in ``keys``, each key once; it returns their values in that
    order). For results made sample by sample (features of meshes), so that a later call on some
    of the same samples, in another batch, finds them. The namespace keeps at most ``max_bytes``
    of values (``nbytes``), the oldest dropped first; the values of a call that would not fit
    are returned and not kept. Returns the values themselves: copy them before writing into them."""
    table = _MEMOS.setdefault(namespace, {})
    missing, seen = [], set()
    for i, k in enumerate(keys):
        if k not in table and k not in seen:
            missing.append(i)
            seen.add(k)
    made = dict(zip((keys[i] for i in missing), build(missing))) if missing else {}
    out = [table[k] if k in table else made[k] for k in keys]
    size = sum(getattr(v, "nbytes", 0) for v in made.values())
    if made and size <= max_bytes:
        held = sum(getattr(v, "nbytes", 0) for v in table.values())
        while table and held + size > max_bytes:
            held -= getattr(table.pop(next(iter(table))), "nbytes", 0)
        table.update(made)
    return out


def forget(namespace: str | None = None) -> None:
    """Drop the values ``memo`` holds for ``namespace`` (every namespace when None): the next
    ``memo`` builds again (from the disk cache where its ``build`` reads one)."""
    if namespace is None:
        _MEMOS.clear()
    else:
        _MEMOS.pop(namespace, None)
