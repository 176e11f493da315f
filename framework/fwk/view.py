"""``fwk view DIR|FILE``: look at a rig in an open3d window, a slider per expression.

What it opens: a ``.glb`` (the base mesh and its morph targets, read with pygltflib), a USD rig
(``.usda``/``.usdc``/``.usd``: the mesh and its UsdSkel BlendShapes, read with pxr), a folder
that holds one of those (what ``fwk apply --format gltf,usd`` wrote), or a folder of expression
OBJs with ``--neutral NEUTRAL.obj`` (what ``fwk apply`` writes by default); a single ``.obj`` is
shown alone. The mesh is the neutral plus sum_i w_i (expression_i - neutral) with one slider
w_i in [0, 1] per expression, coloured by the displacement from the neutral (``viridis``, the
colour scale fixed over all expressions at weight 1), or, with ``--truth DIR`` (OBJs named as the
expressions: ground truth on the same topology), by the distance to the ground truth blended
with the same weights (``inferno``).

``--screenshot out.png`` renders without a window (open3d's offscreen renderer: EGL or a
software Vulkan; CI runs it under Xvfb): with ``--expression NAME`` (repeatable) or
``--weights name=w,...`` one picture of that blend, else a sheet of the neutral and up to
``--max-tiles`` expressions (``--tiles 'jawOpen,brow*'``: those, by name or shell pattern), each
titled, with the colour bar in the rig's units. The colour
scale is shared by every tile (``--scale shared``: the largest displacement of any expression at
weight 1, so tiles compare), or each tile's own (``--scale per-tile``: its largest value is the
top colour and its title gives that value; a rig whose jaw moves 4 cm and whose brows 3 mm shows
both).

open3d is in the optional extra ``rig`` (``pip install 'fwk[rig]'``); it is imported when a
picture or a window is made (0.9 s of import time, and absent without the extra). Its Linux wheels
also load system libraries that a fresh machine may lack (libusb-1.0 above all: Debian's
``libusb-1.0-0``); when one is missing, the error names it and the package that holds it
(``open3d_error``), rather than saying that open3d is not installed.

``fwk view SCAN.obj --pick LM.json --template RUN`` writes the landmark file of ``fwk register``
and ``fwk apply --landmarks`` (``fwk.rig.register.read_landmarks``'s schema): open3d's editing
window (``pick_points``, ``VisualizerWithEditing``: the mesh's vertices as a lit point cloud, as
it picks points of a point cloud only) opens on the run's ``template.obj`` (a rig model's
template, ``--template ict-face``, written to a temporary OBJ), where the user
shift-clicks 5-15 points (the instructions suggest ``RIGGER_POINTS``), and then on the scan, where
the same points are picked in the same order; pairs in pick order, read back with
``read_landmarks``. ``--template-landmarks T.json`` gives the template's ids instead of the first
window. Too few picks, a vertex twice, counts that differ, no display: one line, nothing written.
"""
from __future__ import annotations

import dataclasses
import os
import re
import sys
from pathlib import Path

import numpy as np

from .data.io import fan_triangulate, read_obj
from .data.template import METRES_PER_UNIT
from .errors import DataError, FwkError, cut
from .evaluation.plots import save_figure
from .paths import check_dir
from .rig import missing, read_json_file, vertex_normals

RIG_SUFFIXES = (".glb", ".usdc", ".usda", ".usd")
#: the system libraries open3d's Linux wheel (0.20: ``ldd open3d/pybind*.so``) loads that a minimal Debian or
#: Ubuntu may lack, and the package of each (``dpkg -S`` on Debian 12)
SYSTEM_PACKAGES = {
    "libusb-1.0.so.0": "libusb-1.0-0", "libEGL.so.1": "libegl1", "libGL.so.1": "libgl1", "libGLX.so.0": "libglx0",
    "libGLdispatch.so.0": "libglvnd0", "libX11.so.6": "libx11-6", "libxcb.so.1": "libxcb1",
    "libudev.so.1": "libudev1", "libgomp.so.1": "libgomp1", "libXau.so.6": "libxau6", "libXdmcp.so.6": "libxdmcp6",
}
#: how the dynamic loader names a shared library it cannot open (glibc's dlopen message)
_NO_LIBRARY = re.compile(r"([\w.+-]+\.so(?:\.[\w]+)*): cannot open shared object file")


@dataclasses.dataclass
class Rig:
    """A neutral and its expressions on one triangulated topology: ``neutral`` (n, 3),
    ``triangles`` (m, 3), ``names`` (E,), ``deltas`` (E, n, 3) from the neutral, ``units``, and
    ``truth`` (E, n, 3) ground-truth positions (NaN where none) or None; ``source`` the file."""

    neutral: np.ndarray
    triangles: np.ndarray
    names: list[str]
    deltas: np.ndarray
    units: str = "unit"
    truth: np.ndarray | None = None
    source: str = ""
    vertex_of: np.ndarray | None = None  # the OBJ vertex of each rig vertex (glTF splits UV seams)

    def weights(self, spec: dict[str, float] | None = None) -> np.ndarray:
        """(E,) weights from {name: weight} (unknown names: a one-line error)."""
        w = np.zeros(len(self.names))
        for k, v in (spec or {}).items():
            if k not in self.names:
                raise FwkError(f"--expression {k}: not in the rig (expressions: {', '.join(self.names)})")
            w[self.names.index(k)] = float(v)
        return w

    def blend(self, w: np.ndarray) -> np.ndarray:
        """(n, 3) the neutral plus the weighted deltas."""
        return self.neutral + np.tensordot(np.asarray(w, dtype=np.float64), self.deltas, axes=1)

    def scalars(self, w: np.ndarray) -> tuple[np.ndarray, str]:
        """(n,) per-vertex colour values and their label: the distance to the blended ground
        truth where every weighted expression has one, else the displacement from the neutral."""
        V = self.blend(w)
        on = np.flatnonzero(np.asarray(w) != 0)
        if self.truth is not None and len(on) and not np.isnan(self.truth[on]).any():
            G = self.neutral + np.tensordot(np.asarray(w)[on], self.truth[on] - self.neutral, axes=1)
            return np.linalg.norm(V - G, axis=1), f"error ({self.units})"
        return np.linalg.norm(V - self.neutral, axis=1), f"displacement ({self.units})"

    def colour_limit(self) -> float:
        """The top of the colour scale: the largest displacement (or error) of any expression at weight 1."""
        top = 0.0
        for i in range(len(self.names)):
            w = np.zeros(len(self.names))
            w[i] = 1.0
            top = max(top, float(self.scalars(w)[0].max()))
        return top or 1.0


# --------------------------------------------------------------------------- reading
def _glb(path: Path) -> Rig:
    try:
        import pygltflib  # deferred: optional extra `rig`, 70 ms of import time
    except ImportError:
        raise missing("pygltflib", "fwk view of a .glb") from None
    g = pygltflib.GLTF2().load(str(path))
    blob = g.binary_blob()

    def acc(i):
        a = g.accessors[i]
        v = g.bufferViews[a.bufferView]
        k = {"SCALAR": 1, "VEC2": 2, "VEC3": 3}[a.type]
        dt = {5126: np.float32, 5125: np.uint32, 5123: np.uint16}[a.componentType]
        arr = np.frombuffer(blob, dt, a.count * k, (v.byteOffset or 0) + (a.byteOffset or 0))
        return arr.reshape(a.count, k) if k > 1 else arr

    if not g.meshes or not g.meshes[0].primitives:
        raise DataError(f"{path}: no mesh in this glTF file")
    mesh = g.meshes[0]
    prim = mesh.primitives[0]
    base = acc(prim.attributes.POSITION).astype(np.float64)
    tris = acc(prim.indices).astype(np.int64).reshape(-1, 3)
    names = list((mesh.extras or {}).get("targetNames") or [f"target{i}" for i in range(len(prim.targets or []))])
    deltas = np.stack([acc(t["POSITION"]).astype(np.float64) for t in (prim.targets or [])]) if prim.targets \
        else np.zeros((0, len(base), 3))
    node = next((n for n in g.nodes if n.mesh == 0), None)
    if node is not None and node.translation:  # fwk's node: scaled to metres, translated to the centre
        s = node.scale[0] if node.scale else 1.0
        base = base + np.asarray(node.translation, dtype=np.float64) / s
    vi = getattr(prim.attributes, "_VERTEX_INDEX", None)  # justified: an application attribute, absent in other files
    units = str(((g.extras or {}).get("fwk") or {}).get("units", "unit"))
    return Rig(base, tris, names, deltas, units, source=str(path),
               vertex_of=acc(vi).astype(np.int64) if vi is not None else None)


def _usd(path: Path) -> Rig:
    try:
        from pxr import Usd, UsdGeom, UsdSkel  # deferred: optional extra `rig`, 140 ms of import time
    except ImportError:
        raise missing("usd-core", "fwk view of a USD file") from None
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise DataError(f"{path}: not a USD file that usd-core can open")
    mesh = next((UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
    if mesh is None:
        raise DataError(f"{path}: no mesh in this USD file")
    X = mesh.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    P = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64) @ np.asarray(X.ExtractRotationMatrix()) \
        + np.asarray(X.ExtractTranslation())
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(), dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    tris = fan_triangulate(idx, np.concatenate([[0], np.cumsum(counts)]))
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    names = [str(n) for n in (binding.GetBlendShapesAttr().Get() or [])]
    deltas = np.zeros((len(names), len(P), 3))
    for i, target in enumerate(binding.GetBlendShapeTargetsRel().GetTargets()):
        bs = UsdSkel.BlendShape(stage.GetPrimAtPath(target))
        offsets = np.asarray(bs.GetOffsetsAttr().Get(), dtype=np.float64)
        pi = bs.GetPointIndicesAttr().Get()
        if pi is None:  # unauthored: every point
            deltas[i] = offsets
        else:
            deltas[i][np.asarray(pi, dtype=np.int64)] = offsets
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    # the unit whose metres match the stage's (the writers' table); anything else: not stated
    units = next((u for u, m in METRES_PER_UNIT.items() if abs(mpu - m) <= 1e-6 * m), "unit")
    return Rig(P, tris, names, deltas, units, source=str(path))


def _objs(folder: Path, neutral: Path | None) -> Rig:
    if neutral is None:
        raise FwkError(f"{folder}: holds no .glb or USD rig; give the neutral the OBJs were made from with "
                       "--neutral NEUTRAL.obj")
    N, tpl = read_obj(neutral)
    names, D = [], []
    for p in sorted(folder.glob("*.obj")):
        if p.resolve() == Path(neutral).resolve():
            continue
        V, t = read_obj(p)
        if t.n_vertices != tpl.n_vertices:
            raise DataError(f"{p}: {t.n_vertices} vertices, the neutral {neutral} has {tpl.n_vertices}")
        names.append(p.stem)
        D.append(V - N)
    if not names:
        raise DataError(f"{folder}: no expression .obj files")
    return Rig(N, tpl.triangles, names, np.stack(D), tpl.units, source=str(folder))


def load_rig(path, neutral=None, truth=None) -> Rig:
    """The rig at ``path`` (a .glb, a USD file, a folder holding one, a folder of OBJs with
    ``neutral``, or a single OBJ), with the ground truth OBJs of folder ``truth`` if given."""
    path = Path(path)
    if not path.exists():
        raise FwkError(f"{path}: no such file or folder")
    if path.is_dir():
        found = [p for s in RIG_SUFFIXES for p in sorted(path.glob(f"*{s}"))]
        rig = load_rig(found[0]) if found else _objs(path, Path(neutral) if neutral else None)
    elif path.suffix.lower() == ".glb":
        rig = _glb(path)
    elif path.suffix.lower() in RIG_SUFFIXES:
        rig = _usd(path)
    elif path.suffix.lower() == ".obj":
        V, t = read_obj(path)
        rig = Rig(V, t.triangles, [], np.zeros((0, len(V), 3)), t.units, source=str(path))
    else:
        raise FwkError(f"{path}: not a rig (.glb, .usda, .usdc), a folder of them or of OBJs, or an .obj")
    if truth is not None:
        rig.truth = _truth(rig, Path(truth))
    return rig


def _truth(rig: Rig, folder: Path) -> np.ndarray:
    """(E, n, 3) ground truth per expression from ``folder/<expression>.obj`` (NaN where absent)."""
    if not folder.is_dir():
        raise FwkError(f"--truth {folder}: not a folder of ground-truth OBJs named by expression")
    out = np.full(rig.deltas.shape, np.nan)
    n_obj = int(rig.vertex_of.max()) + 1 if rig.vertex_of is not None else len(rig.neutral)
    for i, name in enumerate(rig.names):
        p = folder / f"{name}.obj"
        if p.exists():
            G, t = read_obj(p)
            if t.n_vertices != n_obj:
                raise DataError(f"{p}: {t.n_vertices} vertices, the rig has {n_obj}")
            out[i] = G[rig.vertex_of] if rig.vertex_of is not None else G
    if np.isnan(out).all():
        raise FwkError(f"--truth {folder}: no OBJ named as an expression of the rig ({', '.join(rig.names[:5])}, ...)")
    return out


# --------------------------------------------------------------------------- drawing
def open3d_error(exc: BaseException) -> FwkError:
    """The one-line error for a failed ``import open3d``: the system library that could not be
    loaded and its Debian/Ubuntu package (open3d is installed: only the library is missing), open3d
    not installed, or open3d failing to import for another reason (its own message's first line)."""
    text = str(exc)
    m = _NO_LIBRARY.search(text)
    if m:
        lib = m.group(1)
        pkg = SYSTEM_PACKAGES.get(lib)
        how = (f"install the Debian/Ubuntu package {pkg} (sudo apt-get install {pkg})" if pkg else
               f"install the system package that holds it (Debian/Ubuntu: apt-file search {lib})")
        return FwkError(f"fwk view: open3d is installed, but the system library {lib} that it loads is "
                        f"missing: {how}")
    if isinstance(exc, ModuleNotFoundError) and (exc.name == "open3d" or text == "No module named 'open3d'"):
        return missing("open3d", "fwk view")
    first = text.strip().splitlines()[0] if text.strip() else type(exc).__name__
    return FwkError(f"fwk view: open3d is installed but cannot be imported ({type(exc).__name__}: {cut(first)})")


def _o3d():
    try:
        import open3d  # deferred: optional extra `rig`, 0.9 s of import time
    except (ImportError, OSError) as exc:  # OSError: a library loaded with ctypes
        raise open3d_error(exc) from None
    return open3d


def _colours(values: np.ndarray, top: float, cmap: str) -> np.ndarray:
    from matplotlib import colormaps  # deferred: matplotlib's import (0.3 s) only for colours

    return colormaps[cmap](np.clip(values / top, 0.0, 1.0))[:, :3]


def _mesh(o3d, rig: Rig, w: np.ndarray, top: float):
    V = rig.blend(w)
    values, label = rig.scalars(w)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(rig.triangles))
    m.vertex_colors = o3d.utility.Vector3dVector(_colours(values, top, "inferno" if label.startswith("error") else
                                                          "viridis"))
    m.compute_vertex_normals()
    return m, label


def _camera(rig: Rig):
    lo, hi = rig.neutral.min(0), rig.neutral.max(0)
    centre = (lo + hi) / 2
    size = float(np.linalg.norm(hi - lo))
    return centre, centre + np.array([0.0, 0.0, 1.9 * size]), np.array([0.0, 1.0, 0.0])


def render_tiles(rig: Rig, weights: list[np.ndarray], size=(480, 540), tops: list[float] | None = None) -> list[np.ndarray]:
    """One offscreen picture (h, w, 3) uint8 per weight vector (coloured against ``tops[i]``, or
    against the rig's shared ``colour_limit``), front view, lit: open3d's OpenGL
    visualiser in a hidden window (EGL without a display, or an X server such as Xvfb; a few
    seconds on 2 cores, where its Filament renderer on a software Vulkan takes 30 s or more)."""
    o3d = _o3d()
    vis = o3d.visualization.Visualizer()
    if not vis.create_window(window_name="fwk view", width=size[0], height=size[1], visible=False):
        raise FwkError("fwk view --screenshot: open3d cannot open an OpenGL context here; install Mesa's EGL "
                       "(Debian: libegl1 libgl1) or run under xvfb-run")
    try:
        opt = vis.get_render_option()
        opt.background_color = np.array([1.0, 1.0, 1.0])
        opt.mesh_show_back_face = True
        opt.light_on = True
        centre, eye, up = _camera(rig)
        shared = rig.colour_limit() if tops is None else None
        out = []
        mesh = None
        for i, w in enumerate(weights):
            m, _ = _mesh(o3d, rig, w, shared if tops is None else tops[i])
            if mesh is None:
                mesh = m
                vis.add_geometry(mesh)
            else:
                mesh.vertices, mesh.vertex_colors, mesh.vertex_normals = m.vertices, m.vertex_colors, m.vertex_normals
                vis.update_geometry(mesh)
            ctr = vis.get_view_control()
            ctr.set_lookat(centre)
            ctr.set_front((eye - centre) / np.linalg.norm(eye - centre))
            ctr.set_up(up)
            ctr.set_zoom(0.62)
            vis.poll_events()
            vis.update_renderer()
            img = np.asarray(vis.capture_screen_float_buffer(do_render=True))
            out.append((np.clip(img, 0, 1) * 255).astype(np.uint8))
        return out
    finally:
        vis.destroy_window()


SCALES = ("shared", "per-tile")


def select_tiles(names: list[str], patterns: list[str] | None, max_tiles: int) -> tuple[list[str], int]:
    """(the expressions of a sheet, how many were selected): those matching ``patterns`` (names or
    shell patterns such as ``brow*``, case-sensitive; in the patterns' order, each expression once,
    rig order within a pattern), or every expression when there are none; the first
    ``max_tiles - 1`` of them (one tile is the neutral). A pattern that matches nothing is a
    one-line error naming the rig's expressions."""
    import fnmatch

    if not patterns:
        chosen = list(names)
    else:
        chosen = []
        for pat in patterns:
            hits = [n for n in names if fnmatch.fnmatchcase(n, pat)]
            if not hits:
                raise FwkError(f"--tiles {pat}: matches no expression of the rig (expressions: {', '.join(names)})")
            chosen += [n for n in hits if n not in chosen]
    return chosen[:max(0, max_tiles - 1)], len(chosen)


def screenshot(rig: Rig, path, weights: dict[str, float] | None = None, max_tiles: int = 12,
               scale: str = "shared", tiles: list[str] | None = None) -> Path:
    """Write ``path`` (PNG): the blend ``weights`` alone, or a sheet of the neutral and up to
    ``max_tiles - 1`` expressions at weight 1 (those matching ``tiles``, names or shell patterns,
    else the rig's first), titled, with the colour bar (``scale``: one colour scale for all tiles,
    or ``per-tile``: each tile's largest value at the top colour)."""
    if scale not in SCALES:
        raise FwkError(f"--scale {scale}: expected one of {', '.join(SCALES)}")
    if weights and tiles:
        raise FwkError("--tiles makes a sheet of expressions at weight 1: use it without --expression/--weights")
    import matplotlib  # deferred: see _colours

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    more = ""  # a capped sheet's title says how many were selected
    if weights:
        ws, titles = [rig.weights(weights)], [", ".join(f"{k} {v:g}" for k, v in weights.items())]
    else:
        shown, n_selected = select_tiles(rig.names, tiles, max_tiles)
        ws = [np.zeros(len(rig.names))] + [rig.weights({e: 1.0}) for e in shown]
        titles = ["neutral", *shown]
        if n_selected > len(shown):
            more = f" ({len(shown)} of {n_selected} expressions: --max-tiles)"
    label = rig.scalars(ws[-1])[1]
    if scale == "per-tile":
        tops = [float(rig.scalars(w)[0].max()) for w in ws]
        titles = [f"{t}\nmax {top:.3g} {rig.units}" for t, top in zip(titles, tops)]
        tops = [top or 1.0 for top in tops]  # the neutral: nothing moves
        top, label = 1.0, f"{label.split(' (')[0]} / the tile's max"
    else:
        top = rig.colour_limit()
        tops = [top] * len(ws)  # computed once: render_tiles would compute it again
    tiles = render_tiles(rig, ws, tops=tops)
    cols = min(len(tiles), 4)
    rows = -(-len(tiles) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(max(4.8, 2.4 * cols + 1.2), 2.9 * rows + 0.4), squeeze=False)
    fig.subplots_adjust(left=0.01, right=0.80, bottom=0.02, top=0.88, wspace=0.02, hspace=0.12)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, img, title in zip(axes.ravel(), tiles, titles):
        ax.imshow(img)
        ax.set_title(title, fontsize=9)
    cmap = "inferno" if label.startswith("error") else "viridis"
    sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(0, top), cmap=cmap)
    fig.colorbar(sm, cax=fig.add_axes([0.83, 0.2, 0.02, 0.6]), label=label)
    fig.suptitle(Path(rig.source).name + more, fontsize=10)
    return save_figure(fig, path, dpi=100)


def open_window(rig: Rig, ticks: int | None = None, set_weights: dict[str, float] | None = None) -> dict:
    """The interactive viewer: the mesh in a SceneWidget and a scrollable panel with a slider
    per expression (0 to 1), the colour updated with the blend. ``ticks`` (tests): run that many
    event-loop ticks, apply ``set_weights`` through the sliders' own callbacks, tick again and
    close; returns {"weights": ..., "max_displacement": ...} of the last blend drawn."""
    o3d = _o3d()
    from open3d.visualization import gui, rendering

    app = gui.Application.instance
    app.initialize()
    window = app.create_window(f"fwk view: {Path(rig.source).name}", 1280, 800)
    em = window.theme.font_size
    scene = gui.SceneWidget()
    scene.scene = rendering.Open3DScene(window.renderer)
    scene.scene.set_background([1.0, 1.0, 1.0, 1.0])
    mat = rendering.MaterialRecord()
    mat.shader = "defaultLit"
    top = rig.colour_limit()
    w = np.zeros(len(rig.names))
    state = {}

    def draw():
        m, label = _mesh(o3d, rig, w, top)
        scene.scene.clear_geometry()
        scene.scene.add_geometry("rig", m, mat)
        status.text = f"{label}: 0 (dark) to {top:.3g} (yellow)"
        state.update(weights=w.copy(), max_displacement=float(np.linalg.norm(rig.blend(w) - rig.neutral, axis=1).max()))

    panel = gui.ScrollableVert(0.25 * em, gui.Margins(em, em, em, em))
    status = gui.Label("")
    panel.add_child(status)
    sliders = {}
    for i, name in enumerate(rig.names):
        panel.add_child(gui.Label(name))
        s = gui.Slider(gui.Slider.DOUBLE)
        s.set_limits(0.0, 1.0)

        def changed(value, i=i):
            w[i] = value
            draw()

        s.set_on_value_changed(changed)
        sliders[name] = (s, changed)
        panel.add_child(s)
    window.add_child(scene)
    window.add_child(panel)

    def layout(ctx):
        r = window.content_rect
        width = 18 * em
        scene.frame = gui.Rect(r.x, r.y, r.width - width, r.height)
        panel.frame = gui.Rect(r.get_right() - width, r.y, width, r.height)

    window.set_on_layout(layout)
    draw()
    centre, eye, up = _camera(rig)
    bounds = scene.scene.bounding_box
    scene.setup_camera(30.0, bounds, centre)
    scene.scene.camera.look_at(centre, eye, up)
    if ticks is None:
        app.run()
        return state
    for _ in range(ticks):
        app.run_one_tick()
    for name, value in (set_weights or {}).items():
        if name not in sliders:
            raise FwkError(f"--expression {name}: not in the rig (expressions: {', '.join(rig.names)})")
        s, changed = sliders[name]
        s.double_value = float(value)
        changed(float(value))
    for _ in range(ticks):
        app.run_one_tick()
    window.close()
    app.run_one_tick()
    return state


# --------------------------------------------------------------------------- picking landmarks
#: the points a rigger marks on a face, in the order ``--pick`` suggests (right and left: the
#: face's own, so its right is on your left as it looks at you), each easy to find on any head
RIGGER_POINTS = (
    ("eye inner right", "the inner corner of the right eye (where the eyelids meet, by the nose)"),
    ("eye outer right", "the outer corner of the right eye"),
    ("eye inner left", "the inner corner of the left eye"),
    ("eye outer left", "the outer corner of the left eye"),
    ("mouth corner right", "the right corner of the mouth (where the lips meet)"),
    ("mouth corner left", "the left corner of the mouth"),
    ("nose tip", "the most forward point of the nose"),
    ("upper lip", "the middle of the upper lip (on the midline, its most forward point)"),
    ("lower lip", "the middle of the lower lip (on the midline, its most forward point)"),
    ("chin", "the chin (on the midline, its most forward point below the fold under the lower lip)"),
)
#: how many points --pick asks for (read_landmarks needs 5; more than 15 add little)
PICK_RANGE = (5, 15)
PICK_HOW = ("shift + left click a point to pick it (a sphere marks it), shift + right click removes the last "
            "pick; turn the head with the left mouse button, zoom with the wheel, + / - make the points larger or "
            "smaller (a click between points picks nothing); close the window (q or Esc) when done")


def pick_points(mesh_path, title: str) -> list[int]:
    """The vertex ids (0-based, the OBJ's ``v`` order) a user shift-clicks, in order, on the OBJ
    at ``mesh_path`` in open3d's ``VisualizerWithEditing`` window titled ``title``; returns when
    the window is closed. The vertices are shown as a lit point cloud (the editing window picks
    points of a point cloud only, not of a mesh). Needs a display: under ``xvfb-run`` nobody can
    click, and without one open3d falls back to an offscreen context, so it is refused first."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise FwkError("fwk view --pick: no display (DISPLAY is not set): picking needs a window you can click "
                       "on a real display (a desktop session, or ssh -X); xvfb-run is not enough for picking")
    V, tpl = read_obj(mesh_path)
    o3d = _o3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(V))
    cloud.normals = o3d.utility.Vector3dVector(vertex_normals(V, tpl.triangles))
    cloud.paint_uniform_color([0.75, 0.72, 0.68])
    vis = o3d.visualization.VisualizerWithEditing()
    if not vis.create_window(window_name=title, width=1280, height=900):
        raise FwkError("fwk view --pick: open3d could not open a window on this display (an OpenGL window "
                       "is needed; xvfb-run is not enough for picking: run it on a real display)")
    try:
        if not vis.add_geometry(cloud):
            raise FwkError(f"fwk view --pick: open3d could not show {mesh_path}")
        opt = vis.get_render_option()
        opt.point_size = 8.0  # under Xvfb, on an 80 x 80 grid: at open3d's default no click picked, at 8 each did
        opt.light_on = True
        vis.run()
    finally:
        vis.destroy_window()
    return [int(i) for i in vis.get_picked_points()]


def read_template_landmarks(path, n_template: int) -> tuple[list[int], list[str] | None]:
    """(template vertex ids, their names or None) of ``--template-landmarks``: a JSON list of
    ids ``[i, ...]``, an object of names to ids ``{"nose tip": i, ...}`` (in its order), or a
    landmark file ``{"landmarks": [{"template": i, ...}, ...]}`` (its template side); 0-based,
    in range, each once, at least 5. One line naming the file otherwise."""
    where = f"--template-landmarks {path}"
    data = read_json_file(path, where)
    names = None
    if isinstance(data, dict) and isinstance(data.get("landmarks"), list):
        items = data["landmarks"]
        if not all(isinstance(it, dict) and "template" in it for it in items):
            raise FwkError(f'{where}: expected {{"landmarks": [{{"template": ID, ...}}, ...]}}')
        ids = [it["template"] for it in items]
    elif isinstance(data, dict):
        names, ids = [str(k) for k in data], list(data.values())
    elif isinstance(data, list):
        ids = data
    else:
        raise FwkError(f'{where}: expected a list of template vertex ids, {{"name": ID, ...}} or a landmark file')
    for k, i in enumerate(ids):
        if not isinstance(i, int) or isinstance(i, bool) or not 0 <= i < n_template:
            raise FwkError(f"{where}: landmark {k + 1}: {cut(str(i), 40)} is not a template vertex id "
                           f"(0-based, 0..{n_template - 1})")
    _check_picks(ids, "in " + where)
    return ids, names


def _check_picks(ids: list[int], where: str) -> None:
    """At least PICK_RANGE[0] picks, each vertex once."""
    if not ids:
        raise FwkError(f"fwk view --pick: no point picked {where} ({PICK_HOW})")
    if len(ids) < PICK_RANGE[0]:
        raise FwkError(f"fwk view --pick: {len(ids)} point(s) picked {where}, at least {PICK_RANGE[0]} needed "
                       f"({PICK_RANGE[0]}-{PICK_RANGE[1]} well spread ones)")
    seen = {}
    for k, i in enumerate(ids):
        if i in seen:
            raise FwkError(f"fwk view --pick: points {seen[i] + 1} and {k + 1} {where} are the same vertex {i}: "
                           f"pick each point once")
        seen[i] = k


def template_obj(template) -> Path:
    """The template OBJ of ``--template``: an .obj itself, a blendshapes run's ``template.obj``
    (of its first seed's sub-run for a run with ``seeds:``), or, for a rig model (a shipped one's
    name, ``fwk list``, or a folder ``fwk pack`` wrote, which keeps no OBJ), its template's
    triangles on its mean neutral written to a temporary OBJ: the picked ids are what count, and
    they are the model's vertex ids."""
    from .rig.shipped import CARD, shipped_or_path  # deferred: only for --template

    p = shipped_or_path(template)
    if p.is_file():
        if p.suffix.lower() != ".obj":
            raise FwkError(f"--template {p}: a run directory, a rig model or a template .obj, not a "
                           f"{p.suffix or 'suffixless'} file")
        return p
    if not p.is_dir():
        raise FwkError(f"--template {p}: no such run directory, rig model or .obj")
    if (p / CARD).is_file() and (p / "stats" / "template.npz").is_file():
        return _packed_template_obj(p)
    if not (p / "template.obj").exists() and (p / "recipe.yaml").exists():
        from .lifecycle import seed_sub_run  # deferred: 40 ms of import time, only for a run with seeds

        p = seed_sub_run(p)
    if not (p / "template.obj").exists():
        raise FwkError(f"--template {template}: no template.obj in it (not a finished blendshapes run, or one "
                       f"from before template.obj); give the template .obj itself")
    return p / "template.obj"


def _packed_template_obj(folder: Path) -> Path:
    """A temporary OBJ of a packed rig model's template (``stats/template.npz``: its triangles on
    the mean neutral), read with ``fwk.safeio.load_npz`` (arrays only, checked); removed when this
    process ends."""
    import atexit
    import shutil
    import tempfile

    from .data.io import write_obj
    from .data.template import template_from_arrays
    from .safeio import load_npz

    path = folder / "stats" / "template.npz"
    state = load_npz(path)
    try:
        t = template_from_arrays(state)
    except Exception as exc:  # a damaged or swapped file: one line naming it
        raise FwkError(f"--template {folder}: {path} is not a rig model's template "
                       f"({type(exc).__name__}: {cut(str(exc), 100)})") from None
    tmp = Path(tempfile.mkdtemp(prefix="fwk-template-"))
    atexit.register(shutil.rmtree, tmp, ignore_errors=True)  # the process's own: gone when it ends
    return write_obj(tmp / f"{folder.name}-template.obj", t.vertices, t)


def _numbered(names) -> str:
    return "\n".join(f"  {k + 1:2d}. {n}" for k, n in enumerate(names))


def pick_landmarks(scan, out, template, template_landmarks=None, say=print) -> Path:
    """``fwk view SCAN --pick OUT --template RUN``: the user picks landmarks on the template
    (skipped with ``template_landmarks``) and then the same ones, in the same order, on the scan
    (``pick_points``); writes ``OUT`` in ``fwk.rig.register.read_landmarks``'s schema (template
    id, scan id pairs in pick order) and reads it back with it. ``say``: the instructions."""
    from .rig.register import read_landmarks  # deferred: 70 ms of import time (scipy.spatial), only here

    scan, out = Path(scan), Path(out)
    if scan.suffix.lower() != ".obj" or not scan.is_file():
        raise FwkError(f"fwk view --pick: {scan}: {'not an .obj' if scan.is_file() else 'no such file'} "
                       f"(the scan to pick on: an .obj, whose vertex ids the landmarks name)")
    if out.is_dir():
        raise FwkError(f"--pick {out}: a folder; give the landmark file to write, e.g. {out / 'lm.json'}")
    check_dir(out.parent, f"--pick {out}: its folder", min_free_mb=0)
    tpl_path = template_obj(template)
    n_template = read_obj(tpl_path)[1].n_vertices
    V_scan = read_obj(scan)[0]
    suggested = [f"{n}: {d}" for n, d in RIGGER_POINTS]
    if template_landmarks is None:  # a rig model that carries its own template landmarks (fwk.rig.shipped)
        from .rig.shipped import CARD, LANDMARKS, shipped_or_path

        m = shipped_or_path(template)
        if m.is_dir() and (m / CARD).is_file() and (m / LANDMARKS).is_file():
            template_landmarks = m / LANDMARKS
            say(f"fwk view --pick: the model's own template landmarks ({template_landmarks}; "
                f"--template-landmarks to give others)")
    if template_landmarks is not None:
        ids, names = read_template_landmarks(template_landmarks, n_template)
        say(f"fwk view --pick: {len(ids)} template landmarks from {template_landmarks}")
    else:
        say(f"fwk view --pick, window 1 of 2: the template {tpl_path}.\nPick {PICK_RANGE[0]}-{PICK_RANGE[1]} "
            f"well spread points that are easy to find on both heads, in an order you will repeat on the scan; "
            f"suggested, these {len(RIGGER_POINTS)} in this order:\n{_numbered(suggested)}\n{PICK_HOW}.")
        ids, names = pick_points(tpl_path, f"fwk view --pick: template {tpl_path.name}: pick the landmarks, "
                                           f"then close"), None
        _check_picks(ids, "on the template")
    n = len(ids)
    order = names if names is not None else (
        [n_ for n_, _ in RIGGER_POINTS] if n == len(RIGGER_POINTS) and template_landmarks is None else None)
    if order is not None:
        which = (f"the same {n} points in the same order" + (" (if you picked the suggested ones)"
                 if names is None else "") + f":\n{_numbered(order)}")
    else:
        which = (f"the same {n} points in the same order as on the template" if template_landmarks is None else
                 f"the {n} points of {template_landmarks}, in its order")
    say(f"fwk view --pick, {'window 2 of 2' if template_landmarks is None else 'the window'}: the scan {scan}.\n"
        f"Pick {which}\n{PICK_HOW}.")
    picks = pick_points(scan, f"fwk view --pick: {scan.name}: pick the same {n} points in order, then close")
    if not picks:
        raise FwkError(f"fwk view --pick: no point picked on the scan {scan} ({PICK_HOW})")
    if len(picks) != n:
        raise FwkError(f"fwk view --pick: {n} points on the template but {len(picks)} on the scan {scan} "
                       f"(scan ids {', '.join(map(str, picks))}): pick the same points on both, in the same order")
    _check_picks(picks, "on the scan")
    text = '{"landmarks": [\n' + ",\n".join(
        f'  {{"template": {t}, "scan": {s}}}' for t, s in zip(ids, picks)) + "\n]}\n"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise FwkError(f"--pick {out}: cannot be written ({exc.strerror or exc})") from None
    read_landmarks(out, n_template, V_scan)  # the file as fwk register and fwk apply --landmarks read it
    say(f"fwk view --pick: wrote {out} ({n} landmarks); next: fwk register {scan} --template {template} "
        f"--landmarks {out} --out reg/")
    return out


# --------------------------------------------------------------------------- command
def _weights(args) -> dict[str, float]:
    out = {e: 1.0 for e in (args.expression or [])}
    for item in (args.weights.split(",") if args.weights else []):
        name, _, value = item.partition("=")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise FwkError(f"--weights {item}: expected name=weight, e.g. jawOpen=0.5") from None
    return out


def add_view_parser(subparsers):
    """``fwk view``'s arguments (cli.EXTRA_COMMANDS)."""
    p = subparsers.add_parser(
        "view", help="look at a rig (.glb, USD, a folder from fwk apply) with a slider per expression; "
                     "--pick: landmarks for fwk register",
        description="Open a rig in an open3d window with a slider per expression, coloured by displacement (or by "
                    "error against --truth); --screenshot renders a picture without a window; --pick LM.json "
                    "--template RUN picks landmark pairs on the template and on a head of any topology "
                    "(the file fwk register and fwk apply --landmarks read).")
    p.add_argument("path", help="a .glb, .usda/.usdc, a folder holding one (fwk apply --out), a folder of OBJs "
                   "(with --neutral), or an .obj (with --pick: the head to pick landmarks on)")
    p.add_argument("--neutral", help="the neutral OBJ, for a folder of expression OBJs")
    p.add_argument("--truth", help="a folder of ground-truth OBJs named by expression: colour by error")
    p.add_argument("--screenshot", metavar="PNG", help="write a picture instead of opening a window")
    p.add_argument("--expression", action="append", help="with --screenshot: this expression at weight 1 (repeatable)")
    p.add_argument("--weights", help="with --screenshot: a blend, name=weight,... (e.g. jawOpen=0.6,eyeBlinkLeft=1)")
    p.add_argument("--tiles", help="with --screenshot: the sheet's expressions, names or shell patterns, "
                   "comma-separated (e.g. 'jawOpen,brow*'; default: the rig's first)")
    p.add_argument("--max-tiles", type=int, default=12, help="with --screenshot: tiles of the sheet, the neutral "
                   "included (default 12)")
    p.add_argument("--scale", choices=SCALES, default="shared",
                   help="with --screenshot: one colour scale for all tiles (default), or each tile's own")
    p.add_argument("--pick", metavar="LM.json", help="pick landmarks for fwk register / fwk apply --landmarks: PATH "
                   "is your head's .obj; a window on the template (--template) and then one on your head, where you "
                   "shift-click the same 5-15 points in the same order (eye corners, mouth corners, nose tip, lip "
                   "midpoints, chin: the list is printed), closing each; writes LM.json as "
                   '{"landmarks": [{"template": ID, "scan": ID}, ...]}. Needs a real display (not xvfb-run)')
    p.add_argument("--template", metavar="RUN", help="with --pick: a finished blendshapes run (its template.obj), a "
                   "rig model (a shipped one's name, e.g. ict-face, or a folder from fwk pack) or a template .obj")
    p.add_argument("--template-landmarks", metavar="T.json", help="with --pick: the template's vertex ids from this "
                   'file ([id, ...], {"name": id, ...} or an earlier landmark file) instead of the first window: you '
                   "pick on your head only")
    return p


def run_view(args) -> int:
    """``fwk view``'s entry (cli.EXTRA_COMMANDS)."""
    pick = getattr(args, "pick", None)
    if pick is None and (getattr(args, "template", None) or getattr(args, "template_landmarks", None)):
        raise FwkError("--template and --template-landmarks go with --pick LM.json (picking landmarks)")
    if pick is not None:
        if not args.template:
            raise FwkError("--pick: give the run (or template .obj) to pick on with --template RUN")
        used = [f for f, v in (("--screenshot", args.screenshot), ("--neutral", args.neutral), ("--truth", args.truth),
                               ("--expression", args.expression), ("--weights", args.weights), ("--tiles", args.tiles))
                if v]
        if used:
            raise FwkError(f"--pick picks landmarks; {', '.join(used)} belong to viewing a rig")
        pick_landmarks(args.path, pick, args.template, args.template_landmarks)
        return 0
    rig = load_rig(args.path, args.neutral, args.truth)
    if args.screenshot:
        tiles = [t.strip() for t in args.tiles.split(",") if t.strip()] if args.tiles else None
        out = screenshot(rig, args.screenshot, _weights(args), args.max_tiles, args.scale, tiles)
        print(out)
        return 0
    if args.tiles:
        raise FwkError("--tiles chooses the tiles of a --screenshot sheet; the window has a slider per expression")
    open_window(rig)
    return 0


def main(argv=None) -> int:
    """``python -m fwk.view PATH [...]``: the same as ``fwk view`` (one-line errors, exit 2)."""
    import argparse
    import sys

    parser = argparse.ArgumentParser(prog="fwk")
    add_view_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["view", *(sys.argv[1:] if argv is None else argv)])
    try:
        return run_view(args)
    except FwkError as exc:
        print(f"fwk: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover - run as a module by the tests until cli.py lists it
    raise SystemExit(main())
