"""Content-hash keyed cache for derived data (parsed meshes, operators, eigenbases, ...).

A key covers every input that changes the value (arrays are hashed by dtype, shape and bytes).
Entries are written atomically (temporary file + rename) with a SHA-256 of their bytes beside
them; a read that does not verify, or cannot be parsed, is treated as a miss and rebuilt.
Location: ``Cache(root)``, else ``$FWK_CACHE``, else ``~/.cache/fwk``.

``memo(namespace, key, build)`` is the in-process counterpart (nothing written): values derived
from a topology or a level (edge structures, spirals, factorisations, metric stencils) built once
per process and key, at most ``size`` per namespace.
"""
from __future__ import annotations

import hashlib
import io
import os
import pickle
import tempfile
from pathlib import Path
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np


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


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: readers see the old file or
    the new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class Cache:
    """Derived data on disk under ``root``, keyed by the content of its inputs (see the module
    docstring)."""

    def __init__(self, root: str | os.PathLike | None = None, enabled: bool = True):
        root = root or os.environ.get("FWK_CACHE") or Path.home() / ".cache" / "fwk"
        self.root = Path(root).expanduser()
        self.enabled = enabled

    def _paths(self, namespace: str, key: str) -> tuple[Path, Path]:
        d = self.root / namespace
        return d / f"{key}.bin", d / f"{key}.sha256"

    def load(self, namespace: str, key: str) -> Any | None:
        """The value stored under ``key``, or None when missing, corrupt or disabled."""
        data_p, sum_p = self._paths(namespace, key)
        if not self.enabled or not data_p.exists() or not sum_p.exists():
            return None
        try:
            data = data_p.read_bytes()
            if hashlib.sha256(data).hexdigest() != sum_p.read_text().strip():
                return None
            return pickle.loads(data)
        except Exception:  # corrupt or unreadable: a miss
            return None

    def store(self, namespace: str, key: str, value: Any) -> None:
        """Store ``value`` under ``key`` (pickled, with its SHA-256); a write error is ignored."""
        if not self.enabled:
            return
        data = pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL)
        data_p, sum_p = self._paths(namespace, key)
        try:
            atomic_write_bytes(data_p, data)
            atomic_write_bytes(sum_p, hashlib.sha256(data).hexdigest().encode())
        except OSError:  # a read-only or full cache must not fail the computation
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
        """A read-only memory-mapped cached array; rebuilt if missing or unreadable."""
        p = self.array_path(namespace, key_parts)
        sum_p = p.with_suffix(".sha256")
        if self.enabled and p.exists() and sum_p.exists():
            try:
                arr = np.load(p, mmap_mode="r")
                meta = f"{arr.dtype.str}{arr.shape}{p.stat().st_size}"
                if sum_p.read_text().strip() == meta:
                    return arr
            except Exception:
                pass
        arr = np.ascontiguousarray(build())
        if not self.enabled:
            return arr
        buf = io.BytesIO()
        np.save(buf, arr)
        try:
            atomic_write_bytes(p, buf.getvalue())
            atomic_write_bytes(sum_p, f"{arr.dtype.str}{arr.shape}{p.stat().st_size}".encode())
            return np.load(p, mmap_mode="r")
        except OSError:
            return arr


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
