"""An example third-party dataset: registered meshes stored as one ``.npz`` file (``npz-meshes``).

Registered meshes (every mesh has the same vertices in the same order, as a fitted template
gives them) of S subjects in E shapes are one array of positions P[s, e] in R^{n x 3} on one
polygon list; a NumPy ``.npz`` archive holds them without any mesh files. The file format
(``write_npz_meshes`` writes it; arrays are read with ``allow_pickle=False``, so names are
unicode arrays, never Python objects):

=================  =====================  ==================================================
array              shape, dtype           what
=================  =====================  ==================================================
``positions``      (S, E, n, 3) float     subject s in shape e; (S, n, 3) is one shape per
                                          subject (the neutral); NaN where a mesh is missing
``faces``          (m, k) int, k >= 3     the polygons, 0-based vertex indices: triangles
                                          (k = 3), quads (k = 4), or mixed, a row padded with
                                          -1 after its last corner (a triangle in a quad array)
``subjects``       (S,) str               subject ids, unique (default ``s0000``, ``s0001``...)
``shapes``         (E,) str               shape names, unique, one of them the neutral
                                          (optional with (S, n, 3) positions: ``neutral``)
``present``        (S, E) bool            optional: which meshes exist (default: the meshes
                                          whose positions are all finite)
``landmark_names`` (L,) str               optional: named vertices, with
``landmark_vertices`` (L,) int            their vertex indices
``region_<name>``  (r,) int               optional: a named vertex set (``region_face``)
=================  =====================  ==================================================

Loading builds a ``fwk.data.MeshCollection`` the way the built-in datasets do: positions
float64 (S, E, n, 3) with the neutral first (the recipe's ``neutral`` names it in the file; it is
renamed ``neutral``), then the other shapes in file order (or ``shapes``' order); ``present``
(S, E), every subject with a neutral, a missing mesh all-NaN; a ``fwk.data.Template`` of the
polygon list, fan-triangulated from each polygon's first corner (the original polygons are kept
for writing meshes back), with the first subject's neutral as its reference ``vertices``, the
landmarks, regions and the recipe's ``units``. With a ``fwk.cache.Cache`` (what a task passes;
``None`` when a caller has none) the float64 positions are stored once, keyed by the file's
path, size and modification time, and memory-mapped read-only on every later load, so a large
file is decompressed and checked once and not held in memory.

A missing or unreadable file, a missing or malformed array, a face index out of range, a mesh
with some but not all coordinates non-finite, or a subject without a neutral is a
``fwk.errors.DataError``: one line naming the file and the array (``fwk run`` prints it without
a traceback). Registered through this package's entry point ``example-npz``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fwk.data import MeshCollection, Template, Units, check_units
from fwk.data.io import fan_triangulate
from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.registry import did_you_mean

#: bumped when the cached positions of a file would differ (what ``load`` builds from them)
VERSION = "v1"
REGION_PREFIX = "region_"


def _names(a, what: str, path) -> list[str]:
    a = np.asarray(a)
    if a.ndim != 1 or a.dtype.kind not in "USiu":
        raise DataError(f"{path}: array {what!r} must be a 1-D array of names (strings), got shape {a.shape} "
                        f"dtype {a.dtype}")
    out = [x.decode() if isinstance(x, bytes) else str(x) for x in a.tolist()]
    seen: set[str] = set()
    for x in out:
        if x in seen:
            raise DataError(f"{path}: array {what!r} names {x!r} twice; names must be unique")
        seen.add(x)
    return out


def _polygons(faces: np.ndarray, n: int, path) -> tuple[np.ndarray, np.ndarray]:
    """(poly_vertices, poly_offsets) of an (m, k) face array (rows padded with -1 after their
    last corner), checked: at least 3 corners, indices in [0, n), no corner repeated."""
    if faces.ndim != 2 or faces.shape[1] < 3 or len(faces) == 0 or faces.dtype.kind not in "iu":
        raise DataError(f"{path}: array 'faces' must be (m, k) integers with m >= 1 and k >= 3 corners per "
                        f"polygon, got shape {faces.shape} dtype {faces.dtype}")
    F = faces.astype(np.int64)
    valid = F >= 0
    if (F < -1).any() or (valid[:, 1:] & ~valid[:, :-1]).any():
        raise DataError(f"{path}: array 'faces' has a negative index other than -1 padding after a polygon's "
                        f"last corner")
    sizes = valid.sum(axis=1)
    if (sizes < 3).any():
        r = int(np.flatnonzero(sizes < 3)[0])
        raise DataError(f"{path}: array 'faces', row {r}: {int(sizes[r])} corners, a polygon needs at least 3")
    if F.max() >= n:
        r = int(np.flatnonzero((F >= n).any(axis=1))[0])
        raise DataError(f"{path}: array 'faces', row {r}: vertex {int(F[r].max())} but the meshes have {n} "
                        f"vertices (indices are 0-based)")
    S = np.sort(np.where(valid, F, -1 - np.arange(F.shape[1])), axis=1)  # padding never equals a corner
    dup = (S[:, 1:] == S[:, :-1]).any(axis=1)
    if dup.any():
        r = int(np.flatnonzero(dup)[0])
        raise DataError(f"{path}: array 'faces', row {r}: a polygon repeats a vertex ({F[r][valid[r]].tolist()})")
    return F[valid], np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)


class NpzMeshes:
    """Registered meshes (subjects x shapes) from one .npz file: positions, faces, names.

    The file holds ``positions`` (S, E, n, 3), ``faces`` (m, k), ``subjects`` (S,) and ``shapes``
    (E,), optionally ``present`` (S, E), ``landmark_names`` / ``landmark_vertices`` and
    ``region_<name>`` arrays (module docstring; ``write_npz_meshes`` writes one). ``load(cache)``
    returns the MeshCollection: float64 positions, the neutral first, the ``present`` mask and the
    Template of the polygons.

    Args:
        path (str): the ``.npz`` file.
        neutral (str): the shape name in the file that plays the neutral (renamed ``neutral``).
        shapes (list[str] | None): the shapes to load, in this order after the neutral (None:
            every shape of the file, in file order).
        units (str): the positions' unit, one of ``fwk.data.UNITS`` (``unit``: not stated).
    """

    name = "npz-meshes"

    def __init__(self, path: str, neutral: str = "neutral", shapes: list[str] | None = None, units: Units = "unit"):
        if not isinstance(path, str) or not path:
            raise RecipeError(f"path: the .npz file, got {path!r}")
        if not isinstance(neutral, str) or not neutral:
            raise RecipeError(f"neutral: a shape name, got {neutral!r}")
        if shapes is not None and len(set(shapes)) != len(shapes):
            raise RecipeError(f"shapes: a shape is listed twice in {shapes}")
        self.path, self.neutral, self.units = Path(path).expanduser(), neutral, check_units(units, "units")
        self.shapes = None if shapes is None else [str(s) for s in shapes]

    # ------------------------------------------------------------------ reading
    def _open(self):
        p = self.path
        if not p.exists():
            raise DataError(f"dataset.path: {p} does not exist")
        if not p.is_file():
            raise DataError(f"dataset.path: {p} is a folder, not an .npz file")
        try:
            with open(p, "rb") as f:
                head = f.read(4)
        except OSError as exc:
            raise DataError(f"{p}: cannot be read ({exc.strerror})") from None
        if head != b"PK\x03\x04":  # not a zip archive (np.load would try other formats, pickles included)
            raise DataError(f"{p}: not an .npz file (write one with fwk_example_plugin.npz_meshes.write_npz_meshes)")
        try:
            return np.load(p, allow_pickle=False)
        except Exception as exc:  # a damaged zip archive
            raise DataError(f"{p}: not a readable .npz file ({type(exc).__name__}: {str(exc)[:120]})") from None

    def _array(self, z, key: str, required: bool = True):
        if key not in z.files:
            if not required:
                return None
            raise DataError(f"{self.path}: no array {key!r} (it holds {', '.join(z.files) or 'nothing'}; "
                            f"see `fwk show dataset {self.name}`)")
        try:
            return z[key]
        except ValueError as exc:  # an object array: refused without unpickling
            raise DataError(f"{self.path}: array {key!r} cannot be read without unpickling ({str(exc)[:80]}); "
                            f"store names as a unicode array, np.asarray(names, dtype=str)") from None
        except Exception as exc:  # a damaged member
            raise DataError(f"{self.path}: array {key!r} cannot be read ({type(exc).__name__}: "
                            f"{str(exc)[:120]})") from None

    def _shape(self, z, key: str) -> tuple:
        """The shape of array ``key`` from its header, without reading its data (a cache hit
        then never decompresses the positions)."""
        if key not in z.files:
            self._array(z, key)  # names the missing array
        try:
            with z.zip.open(key + ".npy") as f:
                version = np.lib.format.read_magic(f)
                read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                    np.lib.format.read_array_header_2_0
                return tuple(read(f)[0])
        except Exception:  # an unusual header: read the array itself (which names what is wrong)
            return tuple(np.shape(self._array(z, key)))

    def _layout(self, z, one_shape: bool):
        """(shape names in the file, the order of file shapes to load, subject ids)."""
        file_shapes = self._array(z, "shapes", required=not one_shape)
        file_shapes = ["neutral"] if file_shapes is None else _names(file_shapes, "shapes", self.path)
        if self.neutral not in file_shapes:
            raise DataError(f"{self.path}: no neutral shape {self.neutral!r}{did_you_mean(self.neutral, file_shapes)} "
                            f"(shapes: {', '.join(file_shapes)}); give the neutral's name as dataset.neutral")
        others = [s for s in (file_shapes if self.shapes is None else self.shapes) if s != self.neutral]
        if "neutral" in others:
            raise DataError(f"{self.path}: shape 'neutral' would clash with the neutral {self.neutral!r}, which "
                            f"loads as 'neutral'; list the shapes to load without it in dataset.shapes")
        for s in others:
            if s not in file_shapes:
                raise DataError(f"dataset.shapes: {self.path} has no shape {s!r}{did_you_mean(s, file_shapes)} "
                                f"(shapes: {', '.join(file_shapes)})")
        order = [file_shapes.index(self.neutral)] + [file_shapes.index(s) for s in others]
        return file_shapes, order, ["neutral", *others]

    def _positions(self, z, file_shapes, order, n_subjects) -> np.ndarray:
        """(S, E, n, 3) float64, the loaded shapes in ``order``, checked, NaN where missing."""
        raw = self._array(z, "positions")
        if raw.dtype.kind not in "fiu" or raw.ndim not in (3, 4) or raw.shape[-1] != 3:
            raise DataError(f"{self.path}: array 'positions' must be (subjects, shapes, n, 3) or (subjects, n, 3) "
                            f"numbers, got shape {raw.shape} dtype {raw.dtype}")
        if raw.ndim == 3:
            raw = raw[:, None]
        if raw.shape[:2] != (n_subjects, len(file_shapes)):
            raise DataError(f"{self.path}: array 'positions' has shape {raw.shape}: {raw.shape[0]} subjects x "
                            f"{raw.shape[1]} shapes, but 'subjects' names {n_subjects} and 'shapes' "
                            f"{len(file_shapes)}")
        P = np.ascontiguousarray(raw[:, order], dtype=np.float64)
        finite = np.isfinite(P).all(axis=(2, 3))
        present = self._array(z, "present", required=False)
        if present is None:
            some = np.isfinite(P).any(axis=(2, 3)) & ~finite
            if some.any():
                s, e = map(int, np.argwhere(some)[0])
                raise DataError(f"{self.path}: positions of subject {s}, shape {file_shapes[order[e]]!r} are partly "
                                f"NaN or infinite (a missing mesh is all NaN, or say so in 'present')")
            present = finite
        else:
            present = np.asarray(present)
            if present.dtype != bool or present.shape != (n_subjects, len(file_shapes)):
                raise DataError(f"{self.path}: array 'present' must be ({n_subjects}, {len(file_shapes)}) bool, got "
                                f"shape {present.shape} dtype {present.dtype}")
            present = present[:, order]
            bad = present & ~finite
            if bad.any():
                s, e = map(int, np.argwhere(bad)[0])
                raise DataError(f"{self.path}: subject {s}, shape {file_shapes[order[e]]!r} is marked present but its "
                                f"positions contain NaN or infinite values")
        P[~present] = np.nan
        return P

    def load(self, cache=None) -> MeshCollection:
        """The MeshCollection of the file (module docstring); ``cache`` (a ``fwk.cache.Cache``, or
        None) memory-maps the float64 positions after the first load."""
        with self._open() as z:
            shape = self._shape(z, "positions")
            if len(shape) not in (3, 4) or shape[-1] != 3 or shape[-2] < 3:
                raise DataError(f"{self.path}: array 'positions' must be (subjects, shapes, n, 3) or (subjects, n, 3) "
                                f"with n >= 3 vertices, got shape {shape}")
            file_shapes, order, shape_names = self._layout(z, len(shape) == 3)
            subjects = self._array(z, "subjects", required=False)
            subjects = [f"s{i:04d}" for i in range(shape[0])] if subjects is None else \
                _names(subjects, "subjects", self.path)
            if (shape[0], 1 if len(shape) == 3 else shape[1]) != (len(subjects), len(file_shapes)):
                raise DataError(f"{self.path}: array 'positions' has shape {shape}, but 'subjects' names "
                                f"{len(subjects)} subjects and 'shapes' {len(file_shapes)} shapes")
            faces = np.asarray(self._array(z, "faces"))
            n = int(shape[-2])
            poly_v, poly_off = _polygons(faces, n, self.path)
            landmarks = self._landmarks(z, n)
            regions = self._regions(z, n)

            def build():
                return self._positions(z, file_shapes, order, len(subjects))

            if cache is None:
                P = build()
            else:
                st = self.path.stat()
                key = (str(self.path.resolve()), st.st_size, st.st_mtime_ns, tuple(order), VERSION)
                P = cache.memmap_array(self.name, key, build)
        present = ~np.isnan(np.asarray(P[:, :, 0, 0]))  # a present mesh is finite, a missing one all NaN
        if not present[:, 0].all():
            missing = [subjects[i] for i in np.flatnonzero(~present[:, 0])]
            raise DataError(f"{self.path}: subjects without a neutral ({self.neutral!r}): {', '.join(missing[:5])}"
                            f"{' ...' if len(missing) > 5 else ''}")
        tri = fan_triangulate(poly_v, poly_off)
        template = Template(np.array(P[0, 0], dtype=np.float64), tri, poly_v, poly_off, regions=regions,
                            landmarks=landmarks, units=self.units, name=self.path.stem)
        return MeshCollection(template, subjects, shape_names, P, present, name=self.name)

    def _landmarks(self, z, n: int) -> dict[str, int]:
        names = self._array(z, "landmark_names", required=False)
        idx = self._array(z, "landmark_vertices", required=names is not None)
        if names is None:
            return {}
        names = _names(names, "landmark_names", self.path)
        idx = np.asarray(idx)
        if idx.shape != (len(names),) or idx.dtype.kind not in "iu" or (len(idx) and (idx.min() < 0 or idx.max() >= n)):
            raise DataError(f"{self.path}: array 'landmark_vertices' must be {len(names)} vertex indices in [0, {n}), "
                            f"got shape {idx.shape} dtype {idx.dtype}")
        return {k: int(i) for k, i in zip(names, idx)}

    def _regions(self, z, n: int) -> dict[str, np.ndarray]:
        out = {}
        for key in z.files:
            if key.startswith(REGION_PREFIX):
                ix = np.asarray(self._array(z, key))
                if ix.ndim != 1 or not len(ix) or ix.dtype.kind not in "iu" or ix.min() < 0 or ix.max() >= n:
                    raise DataError(f"{self.path}: array {key!r} must be a non-empty 1-D array of vertex indices in "
                                    f"[0, {n}), got shape {ix.shape} dtype {ix.dtype}")
                out[key[len(REGION_PREFIX):]] = np.unique(ix.astype(np.int64))
        return out


def write_npz_meshes(path, positions, faces, subjects=None, shapes=None, present=None,
                     landmarks: dict | None = None, regions: dict | None = None, compressed: bool = True) -> Path:
    """Write registered meshes as the ``npz-meshes`` format (module docstring) to ``path``
    exactly (no suffix added) and return it.

    positions  (S, E, n, 3) or (S, n, 3) numbers, NaN where a mesh is missing
    faces      (m, k) int polygons (rows padded with -1 for mixed polygon sizes)
    subjects   S names (default s0000, s0001, ...); shapes: E names (default ``neutral``,
               ``shape1``, ...), one of them the neutral
    present    optional (S, E) bool; landmarks {name: vertex}; regions {name: vertex indices}
    compressed ``np.savez_compressed`` (default) or ``np.savez``
    """
    P = np.asarray(positions)
    if P.ndim not in (3, 4) or P.shape[-1] != 3:
        raise ValueError(f"positions: expected (S, E, n, 3) or (S, n, 3), got {P.shape}")
    F = np.asarray(faces)
    if F.ndim != 2 or F.shape[1] < 3 or F.dtype.kind not in "iu":
        raise ValueError(f"faces: expected (m, k >= 3) integers, got shape {F.shape} dtype {F.dtype}")
    S = P.shape[0]
    E = P.shape[1] if P.ndim == 4 else 1
    subjects = [f"s{i:04d}" for i in range(S)] if subjects is None else [str(s) for s in subjects]
    shapes = (["neutral"] + [f"shape{j}" for j in range(1, E)]) if shapes is None else [str(s) for s in shapes]
    if len(subjects) != S or len(shapes) != E:
        raise ValueError(f"{len(subjects)} subjects and {len(shapes)} shapes for positions of shape {P.shape}")
    arrays = {"positions": P, "faces": F.astype(np.int64), "subjects": np.asarray(subjects, dtype=str),
              "shapes": np.asarray(shapes, dtype=str)}
    if present is not None:
        arrays["present"] = np.asarray(present, dtype=bool).reshape(S, E)
    if landmarks:
        arrays["landmark_names"] = np.asarray(list(landmarks), dtype=str)
        arrays["landmark_vertices"] = np.asarray([int(v) for v in landmarks.values()], dtype=np.int64)
    for name, ix in (regions or {}).items():
        arrays[REGION_PREFIX + str(name)] = np.asarray(ix, dtype=np.int64)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    return path


@hookimpl
def fwk_register_datasets():
    return [NpzMeshes]
