"""Template (one shared topology) and MeshCollection (shapes by subject x shape name)."""
from __future__ import annotations

import dataclasses
import hashlib
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal, get_args

import numpy as np

from ..errors import DataError, RecipeError
from ..geometry.topology import connected_components, edges
from ..registry import did_you_mean


#: The units a dataset's meshes may be in (``unit``: not stated). Reports and metrics write
#: distances in them; a dataset parameter ``units`` is checked against this list when the
#: recipe is validated, and every MeshCollection's on construction.
Units = Literal["unit", "m", "cm", "mm", "um", "in", "ft"]
UNITS: tuple[str, ...] = get_args(Units)
#: metres per unit of every stated unit (``unit``, not stated, has none): the rig files' scale and
#: ``fwk apply --units``
METRES_PER_UNIT = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "in": 0.0254, "ft": 0.3048}


def check_units(units, key: str = "dataset.units") -> str:
    """``units`` when it is one of ``UNITS``, else a RecipeError naming ``key``."""
    if units not in UNITS:
        raise RecipeError(f"{key}: {units!r} is not a unit fwk knows (units: {', '.join(UNITS)}; "
                          f"unit: not stated)")
    return units


@dataclass(eq=False)
class Template:
    """The shared topology of a dataset, and a reference shape on it.

    vertices      (n, 3) float64, a reference shape (the dataset's generic neutral or mean)
    triangles     (m, 3) int64, every polygon fan-triangulated from its first corner
    poly_vertices flat int64 vertex indices of the original polygons, in file order
    poly_offsets  (P + 1,) int64: polygon p is poly_vertices[poly_offsets[p]:poly_offsets[p+1]]
    uvs           (t, 2) float64 texture coordinates (OBJ ``vt``), or None
    poly_uvs      flat int64 ``vt`` indices aligned with poly_vertices (-1: none), or None
    uv_lines      the original ``vt`` lines (text), so UVs are written back byte for byte
    obj_extra     OBJ lines that are not v/vt/f (mtllib, usemtl, g, o, s ...) as
                  (number of polygons written before the line, line) so a mesh is written back
                  exactly as the user's file had it
    regions       name -> vertex indices (e.g. ``face``, ``eyes``)
    landmarks     name -> vertex index
    units         the input units, one of ``UNITS`` (``cm``, ``mm``, ``unit``: not stated)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    poly_vertices: np.ndarray | None = None
    poly_offsets: np.ndarray | None = None
    uvs: np.ndarray | None = None
    poly_uvs: np.ndarray | None = None
    obj_extra: list[tuple[int, str]] = field(default_factory=list)
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    landmarks: dict[str, int] = field(default_factory=dict)
    units: str = "unit"
    name: str = "template"
    uv_lines: list[str] | None = None  # the file's own ``vt`` lines, written back verbatim

    def __post_init__(self):
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        self.triangles = np.ascontiguousarray(self.triangles, dtype=np.int64)
        if self.poly_vertices is None:  # a triangle mesh: the polygons are the triangles
            self.poly_vertices = self.triangles.reshape(-1).copy()
            self.poly_offsets = np.arange(0, 3 * len(self.triangles) + 1, 3, dtype=np.int64)

    @property
    def n_vertices(self) -> int:
        """The number of vertices."""
        return int(self.vertices.shape[0])

    @property
    def n_polygons(self) -> int:
        """The number of polygons of the original file (before triangulation)."""
        return int(len(self.poly_offsets) - 1)

    @cached_property
    def edges(self) -> np.ndarray:
        """(e, 2) unique undirected edges of the triangulation, i < j, sorted."""
        return edges(self.triangles, self.n_vertices).copy()  # a copy: the topology cache keeps its own

    @cached_property
    def components(self) -> np.ndarray:
        """(n,) int64 connected-component label of every vertex (isolated vertices get their own)."""
        return connected_components(self.triangles, self.n_vertices)

    @property
    def n_components(self) -> int:
        """The number of connected components."""
        return int(self.components.max()) + 1 if self.n_vertices else 0

    def topology_hash(self) -> str:
        """Hash of what defines the topology (vertex count and polygons), not the positions."""
        h = hashlib.sha256()
        h.update(np.int64(self.n_vertices).tobytes())
        h.update(np.ascontiguousarray(self.triangles).tobytes())
        return h.hexdigest()[:16]

    def content_hash(self) -> str:
        """Hash of topology and reference positions (for cached geometry of this shape)."""
        h = hashlib.sha256(self.topology_hash().encode())
        h.update(np.ascontiguousarray(self.vertices).tobytes())
        return h.hexdigest()[:16]

    def with_vertices(self, vertices: np.ndarray) -> "Template":
        """The same topology and metadata on other positions."""
        return dataclasses.replace(self, vertices=np.asarray(vertices, dtype=np.float64))


def template_from_arrays(state) -> Template:
    """The Template a run or rig model keeps in ``stats/template.npz`` (``mean_neutral`` (n, 3),
    finite; ``triangles`` (m, 3), ids below n): a KeyError or ValueError saying what is wrong
    otherwise (a swapped or damaged file), for the caller to name the file."""
    V = np.asarray(state["mean_neutral"], dtype=np.float64)
    F = np.asarray(state["triangles"], dtype=np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise ValueError(f"mean_neutral of shape {V.shape}, expected (n, 3) finite")
    if F.ndim != 2 or F.shape[1] != 3 or not len(F) or F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"triangles of shape {F.shape} (expected (m, 3) ids below {len(V)})")
    return Template(V, F)


@dataclass(eq=False)
class MeshCollection:
    """Shapes of many subjects on one template.

    positions  (S, E, n, 3) float64 (may be a read-only memmap), in the dataset's units
    present    (S, E) bool: which subject has which shape (a missing shape is all-NaN)
    subjects   S subject ids; shape_names E shape names, ``neutral`` first where present
    """

    template: Template
    subjects: list[str]
    shape_names: list[str]
    positions: np.ndarray
    present: np.ndarray | None = None
    name: str = "collection"

    def __post_init__(self):
        S, E = len(self.subjects), len(self.shape_names)
        if self.positions.shape[:2] != (S, E) or self.positions.shape[2:] != (self.template.n_vertices, 3):
            raise ValueError(
                f"positions has shape {self.positions.shape}, expected ({S}, {E}, {self.template.n_vertices}, 3)"
            )
        if self.present is None:
            self.present = np.ones((S, E), dtype=bool)
        check_units(self.template.units, f"dataset {self.name}: units")

    @property
    def units(self) -> str:
        """The input units of the meshes (the template's)."""
        return self.template.units

    def shape_index(self, shape: str) -> int:
        """The index of shape ``shape`` in ``shape_names`` (a DataError naming the choices if none)."""
        try:
            return self.shape_names.index(shape)
        except ValueError:
            raise DataError(
                f"dataset {self.name} has no shape {shape!r}{did_you_mean(shape, self.shape_names)} "
                f"(shapes: {', '.join(self.shape_names)})"
            ) from None

    def shape(self, shape: str) -> np.ndarray:
        """(S, n, 3) one shape of every subject."""
        return self.positions[:, self.shape_index(shape)]

    def select(self, subject_idx) -> "MeshCollection":
        """The collection of the subjects ``subject_idx`` (positions copied into memory)."""
        idx = np.asarray(subject_idx, dtype=np.int64)
        return MeshCollection(
            self.template,
            [self.subjects[i] for i in idx],
            list(self.shape_names),
            np.asarray(self.positions[idx]),
            self.present[idx],
            self.name,
        )
