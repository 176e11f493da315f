"""Mesh files: OBJ and PLY, with vertex order and count preserved.

Common readers get OBJ files with UVs and quads wrong (DESIGN.md "Data", measured on the
ICT-FaceKit files): trimesh splits vertices on UV seams, open3d drops quads, meshio refuses
files whose ``vt`` count differs from the ``v`` count. This module parses OBJ itself: the
topology is the order of the ``v`` lines; every polygon is fan-triangulated from its first
corner (the same way for every mesh), and the original polygons, ``vt`` coordinates and the
other lines (``mtllib``, ``usemtl``, ``g``, ``s``...) are kept so that a prediction is written
back as an OBJ that drops into the user's pipeline unchanged.

Face lines are parsed once per topology: a file whose face block is byte-identical to one
seen before reuses the parsed Template (the ~158 ICT files share one).

Errors name the file and the line: ``head.obj, line 812: a vertex line with 2 numbers, expected
3 (the file may be cut short)``. A face's every ``v``, ``vt`` and ``vn`` index must name an
existing line (``head.obj, line 9040: a face refers to texture coordinate (vt) 9, but the file
has 3``): a ``vt`` index past the end used to be copied through into the outputs. Line numbers are found only when something is wrong, so that
reading a good file pays nothing for them.
"""
from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from ..cache import atomic_write_bytes, default_cache, memo
from ..errors import DataError, TopologyError, quote
from .template import Template

_V_LINE = re.compile(rb"(?m)^[ \t]*v[ \t]+([^\r\n]*)")
_V_LINE_FULL = re.compile(rb"(?m)^[ \t]*v[ \t][^\n]*(\n|$)")


def _split_lines(data: bytes):
    """(payloads of the ``v`` lines, the other lines: the face block) found at C speed."""
    v_lines = _V_LINE.findall(data)
    rest = _V_LINE_FULL.sub(b"", data)
    face_block = [s for s in (line.strip() for line in rest.splitlines()) if s and not s.startswith(b"#")]
    return v_lines, face_block


def line_number(data: bytes, predicate, nth: int = 0) -> int | None:
    """The 1-based number of the ``nth`` (0-based) line of ``data`` for which ``predicate(line)``
    (a stripped bytes line) holds; None if there is none."""
    seen = 0
    for i, line in enumerate(data.splitlines(), 1):
        if predicate(line.strip()):
            if seen == nth:
                return i
            seen += 1
    return None


def _at(path, data: bytes | None, predicate, nth: int = 0) -> str:
    """``path, line N`` where line N is found, else ``path``."""
    n = line_number(data, predicate, nth) if data is not None else None
    return f"{path}, line {n}" if n is not None else str(path)


def _is_v(line: bytes) -> bool:
    return line.startswith((b"v ", b"v\t"))


def _parse_vertices(v_lines, path, data: bytes | None = None) -> np.ndarray:
    if not v_lines:
        raise DataError(f"{path}: no vertices (no `v` lines)")
    try:
        flat = np.array(b" ".join(v_lines).split(), dtype=np.float64)
        if flat.size % len(v_lines) == 0 and flat.size // len(v_lines) >= 3:
            return np.ascontiguousarray(flat.reshape(len(v_lines), -1)[:, :3])
    except ValueError:
        pass  # a word that is no number: found below, with its line
    # lines of different lengths (some with colours): the first three numbers of each; a line with
    # fewer than three numbers, or a word that is no number, is named with its line number
    out = np.empty((len(v_lines), 3), dtype=np.float64)
    for k, ln in enumerate(v_lines):
        parts = ln.split()
        try:
            nums = [float(x) for x in parts[:3]]
        except ValueError:
            bad = next(x for x in parts[:3] if not _is_float(x)).decode("utf-8", "replace")
            raise DataError(f"{_at(path, data, _is_v, k)}: {bad!r} in a vertex line is not a number") from None
        if len(nums) < 3:
            raise DataError(f"{_at(path, data, _is_v, k)}: a vertex line with {len(nums)} number"
                            f"{'' if len(nums) == 1 else 's'}, expected 3 (is the file cut short?)")
        out[k] = nums
    return out


def _is_float(x: bytes) -> bool:
    try:
        float(x)
        return True
    except ValueError:
        return False


class _LineError(Exception):
    """A face-block line that cannot be read: its raw (stripped) text and what is wrong."""

    def __init__(self, raw: bytes, what: str):
        super().__init__(what)
        self.raw, self.what = raw, what


def _parse_topology(face_block, n_vertices: int, path) -> Template:
    uvs, uv_lines, poly_v, poly_t, offsets, extra = [], [], [], [], [0], []
    raws = []  # the face line of every polygon, to name the one that is wrong
    n_vt = n_vn = 0
    poly_n = []  # every corner's normal index (-1: none): checked, not kept (normals are recomputed)
    for raw in face_block:
        line = raw.decode("utf-8", "replace").strip()
        tag, _, rest = line.partition(" ")
        try:
            if tag == "vt":
                parts = rest.split()
                uvs.append([float(parts[0]), float(parts[1]) if len(parts) > 1 else 0.0])
                uv_lines.append(line)
                n_vt += 1
            elif tag == "f":
                corners = rest.split()
                if len(corners) < 3:
                    raise _LineError(raw, f"a face with fewer than 3 corners: {quote(line)} (is the file cut short?)")
                for c in corners:
                    bits = c.split("/")
                    vi = int(bits[0])
                    if not -_MAX_INDEX < vi < _MAX_INDEX:  # past int64: numpy could not hold it
                        raise _LineError(raw, f"a face refers to vertex {quote(bits[0])[1:-1]}, but the file has "
                                              f"{n_vertices} vertices")
                    if vi == 0:
                        raise _LineError(raw, "a face refers to vertex 0, but OBJ indices start at 1")
                    vi = vi - 1 if vi > 0 else n_vertices + vi
                    poly_v.append(vi)
                    poly_t.append(_corner_index(bits, 1, n_vt, raw))
                    poly_n.append(_corner_index(bits, 2, n_vn, raw))
                offsets.append(len(poly_v))
                raws.append(raw)
            elif tag == "vn":
                n_vn += 1  # normals are recomputed; counted for the faces' references
            elif tag in ("vp", "l", "p"):
                continue  # lines and points are not surfaces
            else:
                extra.append((len(offsets) - 1, line))
        except (ValueError, IndexError):
            what = "texture" if tag == "vt" else "face"
            raise _LineError(raw, f"unreadable {what} line {quote(line)}") from None
    if len(offsets) == 1:
        raise DataError(f"{path}: no faces (no `f` lines)")
    poly_v = np.asarray(poly_v, dtype=np.int64)
    offsets = np.asarray(offsets, dtype=np.int64)
    bad = np.flatnonzero((poly_v < 0) | (poly_v >= n_vertices))
    if len(bad):
        p = int(np.searchsorted(offsets, bad[0], side="right") - 1)
        raise _LineError(raws[p], f"a face refers to vertex {int(poly_v[bad[0]]) + 1}, but the file has "
                                  f"{n_vertices} vertices (is the file cut short?)")
    triangles = fan_triangulate(poly_v, offsets)
    poly_t = np.asarray(poly_t, dtype=np.int64)
    for idx, count, what in ((poly_t, n_vt, "texture coordinate (vt)"),
                             (np.asarray(poly_n, dtype=np.int64), n_vn, "normal (vn)")):
        bad = np.flatnonzero(idx >= count)  # a corner without one is -1; relative ones were checked as read
        if len(bad):
            p = int(np.searchsorted(offsets, bad[0], side="right") - 1)
            i = int(idx[bad[0]])
            shown = i + 1 if i < _MAX_INDEX else "beyond 2^62"
            raise _LineError(raws[p], f"a face refers to {what} {shown}, but the file has {count}")
    has_uv = bool(uvs) and (poly_t >= 0).any()
    return Template(
        vertices=np.zeros((n_vertices, 3)),
        triangles=triangles,
        poly_vertices=poly_v,
        poly_offsets=offsets,
        uvs=np.asarray(uvs, dtype=np.float64) if has_uv else None,
        poly_uvs=poly_t if has_uv else None,
        obj_extra=extra,
        name=Path(path).stem,
        uv_lines=uv_lines if has_uv else None,
    )


_MAX_INDEX = 2**62
_CORNER_PART = {1: "texture coordinate (vt)", 2: "normal (vn)"}


def _corner_index(bits, k: int, seen: int, raw: bytes) -> int:
    """The 0-based index of part ``k`` of a face corner ``v/vt/vn`` split at ``/`` (-1: not
    given). A relative index (-1 is the last line read so far) must name a line before this one,
    and 0 names none; a positive one is checked against the file's count afterwards."""
    if len(bits) <= k or not bits[k]:
        return -1
    i = int(bits[k])
    if i >= _MAX_INDEX:
        return _MAX_INDEX  # refused with the file's count afterwards
    if i > 0:
        return i - 1
    if i == 0 or seen + i < 0:
        raise _LineError(raw, f"a face refers to {_CORNER_PART[k]} {i}, but "
                              f"{'OBJ indices start at 1' if i == 0 else f'only {seen} precede it'}")
    return seen + i


def fan_triangulate(poly_v: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Triangles (first, i, i+1) of every polygon, in polygon order (vectorised)."""
    sizes = np.diff(offsets)
    n_tri = np.maximum(sizes - 2, 0)
    poly_of_tri = np.repeat(np.arange(len(sizes)), n_tri)
    local = np.arange(n_tri.sum()) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri)
    start = offsets[:-1][poly_of_tri]
    return np.stack([poly_v[start], poly_v[start + local + 1], poly_v[start + local + 2]], axis=1).astype(np.int64)


def read_obj(path, units: str = "unit") -> tuple[np.ndarray, Template]:
    """(V (n, 3) float64, Template) of an OBJ file; the Template's vertices are V."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror})") from None
    v_lines, face_block = _split_lines(data)
    V = _parse_vertices(v_lines, path, data)
    key = hashlib.sha256(b"\n".join(face_block) + str(len(V)).encode()).hexdigest()
    def build():
        try:
            return _parse_topology(face_block, len(V), path)
        except _LineError as exc:
            raise DataError(f"{_at(path, data, lambda line: line == exc.raw)}: {exc.what}") from None

    # parsed once per topology: in memory, and on disk in the content-hash cache (files whose
    # face block is byte-identical share it)
    topo = memo("obj-topology", key, lambda: default_cache().get_or_build("obj-topology", (key, "v2"), build)
                if len(face_block) > 2000 else build())
    t = topo.with_vertices(V)
    t.units = units
    return V, t


def read_ply(path, units: str = "unit") -> tuple[np.ndarray, Template]:
    """(V, Template) of a PLY file (ASCII or binary), vertex order kept (trimesh, process=False)."""
    # deferred: trimesh costs ~0.75 s of import time (measured with python -X importtime); only PLY needs it
    import trimesh

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such file")
    try:
        m = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except Exception as exc:
        raise DataError(f"{path}: unreadable PLY ({exc})") from None
    V = np.asarray(m.vertices, dtype=np.float64)
    F = np.asarray(m.faces, dtype=np.int64)
    if len(F) == 0:
        raise DataError(f"{path}: no faces")
    return V, Template(V, F, units=units, name=path.stem)


def read_mesh(path, units: str = "unit") -> tuple[np.ndarray, Template]:
    """(V, Template) of an OBJ or PLY file."""
    suffix = Path(path).suffix.lower()
    if suffix == ".obj":
        return read_obj(path, units)
    if suffix == ".ply":
        return read_ply(path, units)
    raise DataError(f"{path}: unsupported mesh format {suffix!r} (OBJ and PLY are read)")


def check_topology(template: Template, other: Template, path) -> None:
    """Raise TopologyError naming ``path`` and what differs from ``template``."""
    if other.n_vertices != template.n_vertices:
        raise TopologyError(f"{path}: {other.n_vertices} vertices, expected {template.n_vertices} (the template's)")
    if other.triangles.shape != template.triangles.shape or not np.array_equal(other.triangles, template.triangles):
        if other.n_polygons != template.n_polygons:
            what = f"{other.n_polygons} polygons, expected {template.n_polygons}"
        else:
            diff = np.flatnonzero((other.triangles != template.triangles).any(1)) if other.triangles.shape == template.triangles.shape else [0]
            what = f"a different face list (first difference at triangle {int(diff[0])})"
        raise TopologyError(f"{path}: {what}; every mesh must share the template's topology")


def read_positions(path, template: Template) -> np.ndarray:
    """Vertex positions of a mesh file that must share ``template``'s topology."""
    V, t = read_mesh(path, template.units)
    check_topology(template, t, path)
    if not np.all(np.isfinite(V)):
        raise DataError(f"{path}: vertex positions contain NaN or infinite values")
    return V


def _fmt(a: np.ndarray) -> list[str]:
    return [" ".join(f"{x:.9g}" for x in row) for row in a]


def _v_block(V: np.ndarray) -> str:
    """The ``v`` lines of positions V (n, 3), ``%.9g`` each, in one C-level format call (the
    same text as formatting value by value, 20-50x faster)."""
    V = np.asarray(V, dtype=np.float64)
    return ("v %.9g %.9g %.9g\n" * len(V)) % tuple(V.ravel().tolist())


def _around_v(template: Template) -> tuple[str, str]:
    """The OBJ text of ``template`` before and after its ``v`` block: the header (``mtllib``,
    ``o``), then ``vt``, polygons and material lines where they stood."""
    extra = sorted(template.obj_extra, key=lambda e: e[0]) if template.obj_extra else []
    head = [line for pos, line in extra if pos == 0 and line.split(" ")[0] in ("mtllib", "o")]
    out = []
    if template.uv_lines is not None and len(template.uv_lines) == len(template.uvs):
        out += list(template.uv_lines)
    elif template.uvs is not None:
        out += ["vt " + s for s in _fmt(template.uvs)]
    pv, off = template.poly_vertices + 1, template.poly_offsets
    pt = template.poly_uvs + 1 if template.poly_uvs is not None else None
    ei = 0
    extra_rest = [(pos, line) for pos, line in extra if not (pos == 0 and line.split(" ")[0] in ("mtllib", "o"))]
    for p in range(len(off) - 1):
        while ei < len(extra_rest) and extra_rest[ei][0] <= p:
            out.append(extra_rest[ei][1])
            ei += 1
        a, b = off[p], off[p + 1]
        if pt is not None and (pt[a:b] > 0).all():
            out.append("f " + " ".join(f"{v}/{t}" for v, t in zip(pv[a:b], pt[a:b])))
        else:
            out.append("f " + " ".join(str(v) for v in pv[a:b]))
    out += [line for _, line in extra_rest[ei:]]
    return "".join(line + "\n" for line in head), "".join(line + "\n" for line in out)


def obj_text(V: np.ndarray, template: Template) -> str:
    """OBJ text of positions V on ``template``: its polygons, ``vt`` and material lines."""
    head, tail = _around_v(template)
    return head + _v_block(V) + tail


class ObjWriter:
    """OBJ text of many shapes on one topology (a rig): ``obj_text`` with the lines around the
    ``v`` block formatted once, so each shape costs only its ``v`` lines."""

    def __init__(self, template: Template):
        self.template = template
        self.head, self.tail = _around_v(template)

    def text(self, V: np.ndarray) -> str:
        """The OBJ text of positions V (n, 3)."""
        V = np.asarray(V, dtype=np.float64)
        if V.shape != (self.template.n_vertices, 3):
            raise ValueError(f"ObjWriter: positions of shape {V.shape}, template has {self.template.n_vertices} vertices")
        return self.head + _v_block(V) + self.tail

    def write(self, path: Path, V: np.ndarray) -> Path:
        """Write the OBJ of V to ``path`` (not atomic: for a temporary folder moved into place
        afterwards, as ``fwk apply`` does)."""
        with open(path, "w") as f:
            f.write(self.text(V))
        return path


def write_obj(path, V: np.ndarray, template: Template) -> Path:
    """Write positions V with the template's original polygons, UVs and material lines (atomic)."""
    V = np.asarray(V)
    if V.shape != (template.n_vertices, 3):
        raise ValueError(f"write_obj: positions of shape {V.shape}, template has {template.n_vertices} vertices")
    path = Path(path)
    atomic_write_bytes(path, obj_text(V, template).encode())
    return path


def write_ply(path, V: np.ndarray, template: Template) -> Path:
    """Write positions V on the template's triangles as PLY (atomic)."""
    import trimesh  # deferred: see read_ply

    path = Path(path)
    m = trimesh.Trimesh(np.asarray(V), template.triangles, process=False)
    atomic_write_bytes(path, m.export(file_type="ply"))
    return path


def write_mesh(path, V, template) -> Path:
    """Write positions V as PLY or OBJ, by the file's suffix."""
    return write_ply(path, V, template) if str(path).lower().endswith(".ply") else write_obj(path, V, template)
