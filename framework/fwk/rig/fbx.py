"""FBX rig writer (Blender's Python module ``bpy``, the optional extra ``fbx``): the neutral as a
mesh with one shape key per expression, written by Blender's own FBX exporter.

What the file holds (binary FBX 7.4, as Blender 4.2 writes it):

* one Model (a mesh) called ``name``, its Geometry the neutral: the vertices in the OBJ's order
  (loose vertices kept), the polygons as in the OBJ (quads stay quads, n-gons stay n-gons: no
  triangulation), the OBJ's per-corner UVs as the UV set ``UVMap`` (a corner without ``vt``:
  (0, 0)), smooth vertex normals and face smoothing (every face smooth, one group), no material;
* one BlendShape deformer with one BlendShapeChannel (and its Shape) per expression, named as
  given (``--naming``), in the given order, at weight 0; a Shape holds the offsets of the
  vertices that move (and normal offsets, which Blender writes as zeros);
* units: centimetres (GlobalSettings ``UnitScaleFactor`` 1: FBX's own unit and Maya's default)
  and the OBJ's axes (``UpAxis`` y, front z): the file's coordinates are the OBJ's, in cm, with
  no rotation or scale on the Model. The neutral is converted with ``METRES_PER_UNIT`` (a head in
  mm is divided by 10); an unstated unit (``unit``) is taken as metres, as the glTF and USD
  writers take it (the metre is glTF's and USD's default unit), so that the rig files of one
  ``fwk apply`` open at the same size;
* the Model translated to the centre of the neutral's bounding box (``Lcl Translation``, cm,
  rounded to 1/128 m so that it is exact) and the positions relative to it, as in the glTF and
  USD files. Blender holds positions in float32, and its exporter leaves out of a Shape every
  vertex that moved by less than 1e-6 of its own coordinates; both errors then scale with the
  head's size instead of its distance from the origin: about 1e-6 cm and at most 2e-5 cm for a
  head 30 cm across (tested to 1e-4 cm against the OBJs, through Blender's importer and in the
  raw file).

How it is made: in-process with ``bpy`` 4.2 (the PyPI wheel, CPython 3.11 only; ~520 MB, 1.4 GB
installed; imported, ~0.3 s, when the first FBX is written; its import appends Blender's script
folders to ``sys.path`` and changes nothing else: environment, warnings, locale, signal handlers
and floating-point modes are as they were). Blender's state is global, so each call, under a
lock, starts from an empty factory scene (``read_factory_settings(use_empty=True)``) and resets
it to one again when done, whatever happened: nothing leaks from one file into the next, and
whatever else the process had put into bpy's scene is discarded. The mesh is built in Blender's
frame (metres, z up: OBJ (x, y, z) -> (x, -z, y), as Blender's OBJ importer does) and exported
with Blender's default FBX axes and units (forward -z, up y; "All Local" scaling with the unit
scale applied: metres -> cm, ``UnitScaleFactor`` 1) plus ``bake_space_transform``, so that the
axis change and the x100 land in the coordinates rather than as a -90 degree rotation and a 100x
scale on the Model. The exporter's two lines per file are kept off stdout.

Imported with Blender (File > Import > FBX, default options) the head stands upright at its
real size (the object scaled 0.01: Blender works in metres); Maya (cm, y up) opens it 1:1.
"""
from __future__ import annotations

import contextlib
import io
import sys
import threading

import numpy as np

from ..data import Template
from ..errors import FwkError
from . import METRES_PER_UNIT, missing

#: the ``bpy`` the extra ``fbx`` installs (its wheels are for CPython 3.11 only)
BPY = "bpy==4.2.0"
#: the neutral's shape key, as Blender calls it (a shape of this name would come back renamed)
BASIS = "Basis"
#: the longest name (UTF-8 bytes) Blender gives a shape key or object
MAX_NAME_BYTES = 63
#: Debian/Ubuntu packages of the system libraries bpy's wheel links (X11 client, GL): a headless
#: server may lack them
SYSTEM_PACKAGES = "libx11-6 libxrender1 libxxf86vm1 libxfixes3 libxi6 libxkbcommon0 libsm6 libgl1"
#: the FBX exporter's settings (Blender 4.2 ``export_scene.fbx``) besides the file and selection
EXPORT = dict(
    object_types={"MESH"}, axis_forward="-Z", axis_up="Y",
    apply_unit_scale=True, global_scale=1.0, apply_scale_options="FBX_SCALE_NONE",  # m -> cm, UnitScaleFactor 1
    bake_space_transform=True,  # the axis change and the x100 in the coordinates, not on the Model
    use_mesh_modifiers=False, mesh_smooth_type="FACE", use_triangles=False, use_tspace=False,
    use_custom_props=False, add_leaf_bones=False, bake_anim=False, colors_type="NONE",
    path_mode="AUTO", embed_textures=False, use_metadata=True,
)
#: the object's origin lies on this grid (metres): a power of two, so x100 (cm) stays exact in float32
PIVOT_STEP = 2.0 ** -7
_LOCK = threading.Lock()


def missing_bpy() -> FwkError:
    """The one-line error for a missing ``bpy`` (the extra ``fbx``, not ``rig``)."""
    py = "" if sys.version_info[:2] == (3, 11) else (
        f"; its wheels are for Python 3.11 only, this is {sys.version_info[0]}.{sys.version_info[1]}")
    return missing("bpy", "--format fbx", extra="fbx", spec=BPY, note=f" (Blender 4.2 as a module{py})")


def import_bpy():
    """``bpy``, or a one-line FwkError: not installed (``missing_bpy``), or installed but not loading
    (a system library missing: its Debian packages named)."""
    try:
        import bpy  # deferred: optional extra `fbx`, ~0.3 s and ~240 MB resident
    except ModuleNotFoundError as exc:
        if exc.name == "bpy":
            raise missing_bpy() from None
        raise FwkError(f"--format fbx: bpy does not load: {exc}") from None
    except ImportError as exc:  # a shared library of the wheel's that the system lacks
        raise FwkError(f"--format fbx: bpy is installed but does not load ({exc}); on Debian/Ubuntu: "
                       f"apt-get install {SYSTEM_PACKAGES}") from None
    return bpy


def blender_name(name: str, what: str) -> str:
    """``name`` when Blender can hold it unchanged (at most 63 UTF-8 bytes), else a FwkError."""
    name = str(name)
    if len(name.encode("utf-8")) > MAX_NAME_BYTES:
        raise FwkError(f"--format fbx: {what} {name!r} is longer than Blender's {MAX_NAME_BYTES} bytes "
                       f"({len(name.encode('utf-8'))}); rename it")
    return name


def to_blender(V: np.ndarray) -> np.ndarray:
    """OBJ/FBX axes (y up) -> Blender's (z up): (x, y, z) -> (x, -z, y); exact."""
    return np.stack([V[:, 0], -V[:, 2], V[:, 1]], axis=1)


def from_blender(V: np.ndarray) -> np.ndarray:
    """Blender's axes -> OBJ/FBX axes: (x, y, z) -> (x, z, -y); exact (the inverse of ``to_blender``)."""
    return np.stack([V[:, 0], V[:, 2], -V[:, 1]], axis=1)


def pivot(V: np.ndarray) -> np.ndarray:
    """The object's origin for positions V (n, 3) in metres: the centre of their bounding box
    rounded to 1/128 m (``PIVOT_STEP``), exact in float32 and, x100, in the file's cm, so that
    the Model's translation adds no rounding of its own; (0, 0, 0) without vertices."""
    if not len(V):
        return np.zeros(3)
    return np.round((V.min(0) + V.max(0)) / 2 / PIVOT_STEP) * PIVOT_STEP


@contextlib.contextmanager
def blender_session(bpy):
    """An empty factory scene for the duration (the lock held, Python's stdout silenced), reset to
    an empty one again afterwards whatever happened."""
    with _LOCK, contextlib.redirect_stdout(io.StringIO()):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        try:
            yield bpy.context.scene
        finally:
            bpy.ops.wm.read_factory_settings(use_empty=True)


def write_fbx(path, neutral: np.ndarray, template: Template, shapes: dict[str, np.ndarray],
              units: str = "unit", name: str = "head") -> None:
    """Write the rig to ``path`` (binary FBX): ``neutral`` (n, 3) in ``units`` on ``template``'s
    polygons and UVs, one shape key per entry of ``shapes`` (name -> (n, 3) positions, same
    topology and units), in centimetres; the mesh object is called ``name``."""
    bpy = import_bpy()
    base = np.asarray(neutral, dtype=np.float64)
    n = len(base)
    if base.ndim != 2 or base.shape[1] != 3 or n != template.n_vertices:
        raise FwkError(f"--format fbx: the neutral has shape {base.shape}, the template {template.n_vertices} vertices")
    names = [blender_name(k, "shape name") for k in shapes]
    if BASIS in names:
        raise FwkError(f"--format fbx: a shape called {BASIS!r} would be renamed by Blender, whose name for the "
                       f"neutral's shape key it is; rename it")
    mpu = METRES_PER_UNIT.get(units, 1.0)  # Blender's unit: the metre; unstated: metres, as glTF and USD
    base_m = to_blender(base * mpu)  # metres, Blender's axes
    centre = pivot(base_m)
    off = np.asarray(template.poly_offsets, dtype=np.int64)
    pv = np.asarray(template.poly_vertices, dtype=np.int64)
    polygons = [pv[a:b].tolist() for a, b in zip(off[:-1], off[1:])]
    with blender_session(bpy) as scene:
        mesh = bpy.data.meshes.new((name or "head").encode("utf-8")[:MAX_NAME_BYTES].decode("utf-8", "ignore"))
        mesh.from_pydata((base_m - centre).tolist(), [], polygons, shade_flat=False)
        if template.uvs is not None and template.poly_uvs is not None and len(template.uvs):
            pt = np.asarray(template.poly_uvs, dtype=np.int64)
            st = np.asarray(template.uvs, dtype=np.float64)[np.maximum(pt, 0)]
            st[pt < 0] = 0.0
            layer = mesh.uv_layers.new(name="UVMap")
            layer.data.foreach_set("uv", st.astype(np.float32).reshape(-1))
        mesh.update()
        if len(mesh.vertices) != n or len(mesh.polygons) != len(polygons):
            raise FwkError(f"--format fbx: Blender made {len(mesh.vertices)} vertices and {len(mesh.polygons)} "
                           f"polygons of {n} and {len(polygons)} (degenerate polygons?)")
        obj = bpy.data.objects.new(mesh.name, mesh)
        obj.location = tuple(float(x) for x in centre)
        scene.collection.objects.link(obj)
        if names:
            obj.shape_key_add(name=BASIS, from_mix=False)
            for key, V in zip(names, shapes.values()):
                V = np.asarray(V, dtype=np.float64)
                if V.shape != base.shape:
                    raise FwkError(f"--format fbx: shape {key!r} has shape {V.shape}, the neutral {base.shape}")
                kb = obj.shape_key_add(name=key, from_mix=False)
                if kb.name != key:
                    raise FwkError(f"--format fbx: Blender renamed shape {key!r} to {kb.name!r}")
                kb.data.foreach_set("co", (to_blender(V * mpu) - centre).astype(np.float32).reshape(-1))
                kb.value = 0.0
            mesh.shape_keys.use_relative = True
        bpy.context.view_layer.objects.active = obj
        obj.select_set(True)
        try:
            result = bpy.ops.export_scene.fbx(filepath=str(path), use_selection=True, **EXPORT)
        except RuntimeError as exc:  # the exporter's exception, its traceback in the message
            lines = [ln.strip() for ln in str(exc).splitlines()
                     if ln.strip() and not ln.startswith((" ", "Location:", "Error: Python: Traceback"))]
            raise FwkError(f"--format fbx: Blender could not write {path}: {lines[-1] if lines else exc}") from None
        if result != {"FINISHED"}:
            raise FwkError(f"--format fbx: Blender's FBX exporter did not finish writing {path} ({result})")
