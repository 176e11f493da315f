"""Files fwk opens hold data, never code: model states and training checkpoints in one safe format.

A *state* is a nested value of dicts, lists and tuples whose leaves are ``str``, ``int``,
``float``, ``bool``, ``None``, NumPy scalars, NumPy arrays and torch tensors (dense, or sparse
COO: stored as their indices and values) (a model's
``state_dict()``, a Lightning checkpoint). ``save_state`` writes it as a safetensors file: every
array and tensor a named tensor, the structure (with the type of every leaf, so that NumPy arrays
come back as NumPy arrays and tensors as tensors) as JSON in the file's metadata, and the SHA-256
of the tensor bytes beside it; a NumPy array equal to one stored before is a reference to it (stored
once; read back as a copy, and all references together may copy no more bytes than the file's
tensors hold). ``load_state`` verifies all of that before it returns anything;
nothing in the file is ever executed (safetensors parses a JSON header and raw bytes; no pickle).

A value of any other type (a ``Spec``, a custom object, a function) cannot be saved: ``save_state``
raises ``UnsafeStateError`` (a ``TypeError``) naming where in the state it sits; a model stores plain data instead.

Files written by earlier versions of fwk were pickles (``torch.save``): unpickling runs whatever
code the file names, so they are refused (``LegacyFormatError``, one line) with the command that
rewrites a run the user trusts: ``fwk convert RUN --trust`` (``fwk.convert``).

torch is imported when a state is written or read, never at module import (``fwk list`` loads
this module through ``fwk.lifecycle``).
"""
from __future__ import annotations

import hashlib
import json
import secrets
import struct
from pathlib import Path
from typing import Any

import numpy as np

from .errors import DataError

#: the format tag in every file's metadata
FORMAT = "fwk.state/1"
#: the suffix of a model's state file (``models/<label>.safetensors``)
SUFFIX = ".safetensors"
#: the suffix of the pickled model files of earlier versions (``models/<label>.pt``)
LEGACY_SUFFIX = ".pt"

_MAX_HEADER = 100_000_000  # safetensors' own bound on the JSON header


class UnsafeStateError(TypeError):
    """A state holds a value the safe format does not store (an object, a function): the message
    says where it sits. A bug of the model that made it (its contract suite fails on it)."""


class LegacyFormatError(DataError):
    """A pickled file of an earlier fwk (``torch.save``): not opened; ``fwk convert`` rewrites it."""


def run_of(path: Path) -> Path:
    """The outermost run directory (a folder with ``recipe.yaml``) that holds ``path``."""
    path = Path(path)
    found = path.parent
    for p in path.parents:
        if (p / "recipe.yaml").is_file():
            found = p
    return found


def legacy_error(path: Path) -> LegacyFormatError:
    return LegacyFormatError(
        f"{path}: a pickled file of an earlier fwk version, not opened (unpickling can run code); if you "
        f"trust who made the run, rewrite it in the safe format with: fwk convert {run_of(path)} --trust")


HEAD_BYTES = 9  # what is_pickle reads: a safetensors header length (8 bytes) and the JSON's first byte


def is_pickle(head: bytes) -> bool:
    """Whether a file starting with ``head`` (its first ``HEAD_BYTES``) is a ``torch.save``
    pickle (zip or legacy format). A safetensors file starts with its header's length (8 bytes,
    little-endian) and the header's "{": a length whose low byte is 0x80 (one header in 256) must
    not read as pickle protocol 2's first byte."""
    if len(head) >= 9 and head[8:9] == b"{" and 0 < int.from_bytes(head[:8], "little") < 1 << 40:
        return False
    return head[:4] == b"PK\x03\x04" or head[:1] == b"\x80"


def file_is_pickle(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return is_pickle(f.read(HEAD_BYTES))
    except OSError:
        return False


def pickled_files(run_dir) -> list[Path]:
    """Every pickled model file (``models/*.pt``, or a pickle under the new name) and checkpoint
    (``*.ckpt``) of ``run_dir`` and its sub-runs: what ``fwk convert`` rewrites."""
    run_dir = Path(run_dir)
    found = [p for p in run_dir.rglob(f"*{LEGACY_SUFFIX}") if p.parent.name == "models" and p.is_file()]
    found += [p for p in run_dir.rglob(f"*{SUFFIX}") if p.parent.name == "models" and p.is_file()
              and file_is_pickle(p)]
    found += [p for p in run_dir.rglob("*.ckpt") if p.is_file() and file_is_pickle(p)]
    return sorted(set(found))


def refuse_pickled(run_dir) -> None:
    """``LegacyFormatError`` naming the first pickled file of ``run_dir`` (``pickled_files``),
    before anything of the run is opened or written."""
    found = pickled_files(run_dir)
    if found:
        raise legacy_error(found[0])


# ----------------------------------------------------------------------------- encoding

def _where(path: str) -> str:
    return path or "the state"


def _encode(obj, path: str, tensors: dict, torch, seen: dict | None = None) -> Any:
    """The JSON structure of ``obj``; its arrays and tensors go to ``tensors`` (name -> tensor).
    A NumPy array equal (dtype, shape, bytes) to one stored before is stored once: the later ones
    are references to it (``{"r": name}``; a model's triangles and mean neutral sit in several of
    its parts)."""
    seen = {} if seen is None else seen
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, np.generic):  # before int/float: np.float64 is a float
        if obj.dtype.kind not in "biuf":
            raise UnsafeStateError(f"{_where(path)}: a NumPy {obj.dtype} scalar cannot be saved safely")
        return {"s": [obj.dtype.str, obj.item()]}
    if isinstance(obj, int):
        return int(obj)
    if isinstance(obj, float):
        return float(obj)
    if isinstance(obj, np.ndarray):
        if obj.dtype.kind not in "biuf" or obj.dtype.byteorder == ">":
            raise UnsafeStateError(f"{_where(path)}: a NumPy array of dtype {obj.dtype} cannot be saved safely "
                            "(numbers and booleans only)")
        arr = np.array(obj, order="C", copy=True)
        key = (arr.dtype.str, arr.shape, hashlib.sha256(arr.tobytes()).hexdigest())
        if key in seen:
            return {"r": seen[key]}
        name = str(len(tensors))
        tensors[name] = torch.from_numpy(arr)
        seen[key] = name
        return {"n": name}
    if isinstance(obj, torch.Tensor):
        if obj.is_complex() or obj.layout not in (torch.strided, torch.sparse_coo):
            raise UnsafeStateError(f"{_where(path)}: a {obj.dtype} {obj.layout} tensor cannot be saved safely")
        if obj.layout == torch.sparse_coo:  # its indices and values, each a tensor
            c = obj.detach().to("cpu").coalesce()
            i, v = str(len(tensors)), str(len(tensors) + 1)
            tensors[i], tensors[v] = c.indices().contiguous().clone(), c.values().contiguous().clone()
            return {"c": [i, v, list(c.shape)]}
        name = str(len(tensors))
        t = obj.detach().to("cpu").contiguous()
        # read where it lies, unless another tensor of the state lies in the same memory (safetensors
        # refuses shared storage): a copy costs a checkpoint of 450 MB 0.13-0.16 s
        ptr = ("storage", t.untyped_storage().data_ptr())
        if ptr in seen:
            t = t.clone()
        elif ptr[1]:
            seen[ptr] = name
        tensors[name] = t
        return {"t": name}
    if isinstance(obj, dict):
        items = []
        for k, v in obj.items():
            if not (k is None or isinstance(k, (str, int, float, bool))):
                raise UnsafeStateError(f"{_where(path)}: a key of type {type(k).__name__} cannot be saved safely")
            items.append([k, _encode(v, f"{path}.{k}" if path else str(k), tensors, torch, seen)])
        return {"d": items}
    if isinstance(obj, (list, tuple)):
        return {"l" if isinstance(obj, list) else "u":
                [_encode(v, f"{path}[{i}]", tensors, torch, seen) for i, v in enumerate(obj)]}
    raise UnsafeStateError(f"{_where(path)}: a {type(obj).__module__}.{type(obj).__qualname__} cannot be saved safely; "
                    "a state holds tensors, NumPy arrays and plain data (dict, list, tuple, str, int, float, bool, None)")


class _Malformed(Exception):
    pass


class _Refs:
    """What references (``{"r": name}``) may copy: only arrays decoded before, and in all no more
    bytes than the file's tensors hold (a file cannot make its reader allocate more than twice
    its size by repeating a reference)."""

    def __init__(self, tensors: dict):
        self.left = sum(t.numel() * t.element_size() for t in tensors.values())


def _decode(node, tensors: dict, used: set, depth: int = 0, refs: _Refs | None = None):
    if depth > 200:
        raise _Malformed("nested too deeply")
    if node is None or isinstance(node, (bool, str, int, float)):
        return node
    if not isinstance(node, dict) or len(node) != 1:
        raise _Malformed(f"unexpected node {str(node)[:80]!r}")
    refs = _Refs(tensors) if refs is None else refs
    (tag, val), = node.items()
    if tag == "r":  # a NumPy array stored once before: a copy of it
        if not isinstance(val, str) or val not in used:
            raise _Malformed(f"a reference {str(val)[:40]!r} to no array decoded before")
        t = tensors[val]
        refs.left -= t.numel() * t.element_size()
        if refs.left < 0:
            raise _Malformed("its references copy more than its tensors hold")
        return t.numpy().copy()
    if tag in ("t", "n"):
        if not isinstance(val, str) or val not in tensors:
            raise _Malformed(f"a tensor {str(val)[:40]!r} the file does not hold")
        if val in used:
            raise _Malformed(f"tensor {val} used twice")
        used.add(val)
        t = tensors[val]
        return t if tag == "t" else t.numpy()
    if tag == "c":  # a sparse COO tensor: indices, values, shape (checked by torch.sparse_coo_tensor)
        if not (isinstance(val, list) and len(val) == 3 and isinstance(val[2], list)
                and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in val[2])):
            raise _Malformed("a malformed sparse tensor")
        import torch

        i, v = (_decode({"t": n}, tensors, used, depth + 1, refs) for n in val[:2])
        try:
            return torch.sparse_coo_tensor(i, v, tuple(val[2]), check_invariants=True).coalesce()
        except (RuntimeError, ValueError, TypeError) as exc:
            raise _Malformed(f"a sparse tensor that does not hold together ({str(exc)[:80]})") from None
    if tag == "s":
        if not (isinstance(val, list) and len(val) == 2 and isinstance(val[0], str)):
            raise _Malformed("a malformed scalar")
        dt = np.dtype(val[0])
        if dt.kind not in "biuf":
            raise _Malformed(f"a scalar of dtype {dt}")
        return dt.type(val[1])
    if tag in ("l", "u"):
        if not isinstance(val, list):
            raise _Malformed("a malformed sequence")
        out = [_decode(v, tensors, used, depth + 1, refs) for v in val]
        return out if tag == "l" else tuple(out)
    if tag == "d":
        if not isinstance(val, list):
            raise _Malformed("a malformed mapping")
        out = {}
        for item in val:
            if not (isinstance(item, list) and len(item) == 2) or isinstance(item[0], (list, dict)):
                raise _Malformed("a malformed mapping entry")
            out[item[0]] = _decode(item[1], tensors, used, depth + 1, refs)
        return out
    raise _Malformed(f"unknown tag {tag[:20]!r}")


def _split(data: bytes) -> tuple[int, dict]:
    """(where the tensor bytes start, the header) of safetensors bytes; ValueError if malformed."""
    if len(data) < 8:
        raise ValueError("shorter than a header")
    (n,) = struct.unpack("<Q", data[:8])
    if n > _MAX_HEADER or 8 + n > len(data):
        raise ValueError("its header runs past the end of the file")
    header = json.loads(data[8:8 + n])
    if not isinstance(header, dict):
        raise ValueError("its header is not a mapping")
    return 8 + n, header


def dumps_state(state, meta: dict | None = None) -> bytes:
    """The bytes of ``state`` (see the module docstring) in the safe format; ``meta`` (JSON data)
    is stored beside it and returned by ``loads_state``. ``UnsafeStateError`` (a ``TypeError``) for a value that is not
    plain data, naming where it sits."""
    return b"".join(_dump_parts(state, meta))


def _dump_parts(state, meta: dict | None = None) -> list:
    """``dumps_state``'s bytes in two parts, the header and a view of the tensor bytes (not copied)."""
    import torch  # deferred: ~1 s of import time that `fwk list` need not pay
    from safetensors.torch import save

    tensors: dict = {}
    structure = _encode(state, "", tensors, torch)
    # the hash of the tensor bytes goes in the header before them: written once with a random
    # placeholder of the hash's length, which is then overwritten in place (the header keeps its
    # length, so every offset holds); the bytes are those of a second save with the hash in it
    placeholder = secrets.token_hex(32)
    fields = {"format": FORMAT, "structure": json.dumps(structure, allow_nan=True),
              "meta": json.dumps(meta or {}, allow_nan=True), "sha256": placeholder}
    data = save(tensors, metadata=fields)
    start, _ = _split(data)
    digest = hashlib.sha256(memoryview(data)[start:]).hexdigest()
    header = bytearray(data[:start])
    at = header.find(placeholder.encode(), 8)
    if at < 0 or header.find(placeholder.encode(), at + 1) >= 0:  # not once in the header: save again
        fields["sha256"] = digest
        return [save(tensors, metadata=fields)]
    header[at:at + len(placeholder)] = digest.encode()
    return [bytes(header), memoryview(data)[start:]]


def loads_state(data: bytes, where: str = "the file") -> tuple[Any, dict]:
    """(state, meta) from bytes ``dumps_state`` wrote, verified: a pickle raises
    ``LegacyFormatError``, anything else that is not a whole, unchanged state file ``DataError``
    naming ``where``."""
    if is_pickle(data[:HEAD_BYTES]):
        raise legacy_error(Path(where))
    try:
        start, header = _split(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"{where}: not a readable fwk state file (truncated or damaged: {exc})") from None
    fields = header.get("__metadata__") or {}
    if not isinstance(fields, dict) or fields.get("format") != FORMAT:
        raise DataError(f"{where}: not an fwk state file (no {FORMAT} format tag)")
    if hashlib.sha256(memoryview(data)[start:]).hexdigest() != fields.get("sha256"):
        raise DataError(f"{where}: its tensor bytes do not match the SHA-256 recorded in it (changed or truncated)")
    from safetensors.torch import load  # deferred: imports torch

    try:
        tensors = load(data)
    except Exception as exc:  # safetensors' own checks of the header's offsets, dtypes and shapes
        raise DataError(f"{where}: not a readable fwk state file ({str(exc)[:160]})") from None
    try:
        used: set = set()
        state = _decode(json.loads(fields.get("structure", "")), tensors, used)
        if used != set(tensors):
            raise _Malformed(f"{len(set(tensors) - used)} tensors not in its structure")
        meta = json.loads(fields.get("meta") or "{}")
        if not isinstance(meta, dict):
            raise _Malformed("its meta is not a mapping")
    except (_Malformed, ValueError, TypeError, RecursionError) as exc:
        raise DataError(f"{where}: its structure is malformed ({str(exc)[:160]})") from None
    return state, meta


def save_state(path, state, meta: dict | None = None) -> Path:
    """Write ``state`` to ``path`` in the safe format, atomically (``fwk.cache.atomic_write_bytes``)."""
    from .cache import atomic_write_bytes

    path = Path(path)
    atomic_write_bytes(path, _dump_parts(state, meta))
    return path


def read_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}: missing") from None
    except IsADirectoryError:
        raise DataError(f"{path}: a folder, not a file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror})") from None


def load_state(path, with_meta: bool = False):
    """The state ``save_state`` wrote to ``path`` (and its meta, with ``with_meta``), verified;
    ``DataError`` (one line naming the file) when it is missing, damaged or not in the safe
    format, ``LegacyFormatError`` for an earlier version's pickle."""
    path = Path(path)
    state, meta = loads_state(read_bytes(path), str(path))
    return (state, meta) if with_meta else state


# ----------------------------------------------------------------------------- packed precision

#: the precisions ``fwk pack`` stores a state in (``narrow``); the first is the default
PRECISIONS = ("float32", "mixed")
#: with ``mixed``: a float array or tensor of at least this many values is stored as float16
MIXED_MIN = 65_536
#: the meta key a narrowed state carries (its precision); ``widen`` undoes the storage types
NARROWED = "narrowed"


def narrow(state, precision: str = "float32"):
    """``state`` as ``fwk pack`` stores it: float64 arrays and tensors as float32, int64 arrays
    whose values fit as int32 (ids, triangles), and with ``mixed`` every float array or tensor of
    at least ``MIXED_MIN`` values (network weights, a basis) as float16; the small ones (means,
    scalers, positions) stay float32. Dense arrays only; a sparse tensor is kept as it is."""
    import torch

    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: one of {', '.join(PRECISIONS)}")
    if isinstance(state, dict):
        return {k: narrow(v, precision) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(narrow(v, precision) for v in state)
    half = precision == "mixed"
    if isinstance(state, np.ndarray):
        if state.dtype.kind == "f" and state.dtype.itemsize >= 4:
            return state.astype(np.float16 if half and state.size >= MIXED_MIN else np.float32)
        if state.dtype == np.int64 and (state.size == 0 or (state.min() >= -2 ** 31 and state.max() < 2 ** 31)):
            return state.astype(np.int32)
        return state
    if isinstance(state, torch.Tensor) and state.layout == torch.strided and state.is_floating_point() \
            and state.element_size() >= 4:
        return state.to(torch.float16 if half and state.numel() >= MIXED_MIN else torch.float32)
    return state


def widen(state):
    """A narrowed state (``narrow``) in the types fwk computes with: float16 and float32 NumPy
    arrays as float64, float16 tensors as float32, int32 NumPy arrays as int64."""
    import torch

    if isinstance(state, dict):
        return {k: widen(v) for k, v in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(widen(v) for v in state)
    if isinstance(state, np.ndarray):
        if state.dtype in (np.float16, np.float32):
            return state.astype(np.float64)
        if state.dtype == np.int32:
            return state.astype(np.int64)
        return state
    if isinstance(state, torch.Tensor) and state.layout == torch.strided and state.dtype == torch.float16:
        return state.to(torch.float32)
    return state


# ----------------------------------------------------------------------------- other run files

def load_npz(path) -> dict:
    """The arrays of an ``.npz`` file of a run (``stats/``), never unpickled: ``DataError`` naming
    the file when it is missing, not an npz, or holds objects."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: missing")
    with open(path, "rb") as f:
        if f.read(4) != b"PK\x03\x04":  # not a zip archive at all (np.load would try it as a pickle)
            raise DataError(f"{path}: not an .npz file (damaged or replaced)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception as exc:  # zipfile, numpy's format checks, an object array (allow_pickle=False)
        raise DataError(f"{path}: not a readable .npz file ({type(exc).__name__}: {str(exc)[:120]})") from None


def load_json(path, kind: type | None = dict):
    """A run's JSON file, parsed: ``DataError`` naming the file when it is missing, not UTF-8 JSON,
    or (with ``kind``) not of that type at its top."""
    path = Path(path)
    text = read_bytes(path)
    try:
        value = json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise DataError(f"{path}: not valid JSON ({str(exc)[:120]})") from None
    if kind is not None and not isinstance(value, kind):
        raise DataError(f"{path}: expected a JSON {'object' if kind is dict else kind.__name__} at the top, "
                        f"found {type(value).__name__}")
    return value
