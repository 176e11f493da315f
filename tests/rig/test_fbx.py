"""FBX rig files (``fwk.rig.fbx``, issue 29 item 3) read back two ways: by Blender's own FBX
importer into a fresh empty scene (what a user gets from File > Import > FBX: the mesh, its
polygons, UVs and shape keys, and the object's transform that puts it in Blender's metres and
z up), and as raw FBX nodes (Blender's ``parse_fbx``, no importer logic: the file's units and
axes, the Model's transform, the Geometry's vertices and every Shape's offsets). Both must give
the OBJs' positions in cm to 1e-4 cm, every shape key, in order, under its own name; quads stay
quads. Blender's state is global: every test leaves bpy's scene empty.

Needs the optional extra ``fbx`` (bpy 4.2, Python 3.11): skipped without it, except the tests
of the error that says how to install it."""
from __future__ import annotations

import builtins
import contextlib
import io
import sys
from dataclasses import dataclass

import numpy as np
import pytest

from fwk.data.template import METRES_PER_UNIT
from fwk.errors import FwkError

from .conftest import grid_obj, neutral, expression

TOL_CM = 1e-4
#: FBX (y up) -> Blender (z up), as Blender's importer rotates the object: (x, y, z) -> (x, -z, y)
FBX_TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
SHAPES = ("jawOpen", "browInnerUp_L", "face-x")


@pytest.fixture(scope="module")
def bpy():
    return pytest.importorskip("bpy", reason="bpy (Blender 4.2 as a module, Python 3.11 only) is the optional "
                                             "extra fbx: pip install -e '.[fbx]'")


@pytest.fixture
def clean(bpy):
    """bpy, checked empty after the test: write_fbx leaves nothing in Blender's scene. It starts
    from an empty scene too: a freshly imported bpy holds Blender's start-up scene (a cube, a
    camera, a light), which a test refused before any Blender call would otherwise find here (seen
    when such a test was the first of a pytest-xdist worker to use bpy)."""
    with contextlib.redirect_stdout(io.StringIO()):
        bpy.ops.wm.read_factory_settings(use_empty=True)
    yield bpy
    assert not bpy.data.objects and not bpy.data.meshes and not bpy.data.shape_keys


@dataclass
class Readback:
    name: str
    keys: dict  # shape key name -> (n, 3) positions in OBJ axes, cm (Blender's world transform undone)
    matrix: np.ndarray  # the object's 4x4 world matrix in Blender
    offsets: np.ndarray  # (P + 1,) polygon offsets into corners
    corners: np.ndarray  # vertex of every polygon corner
    uvs: np.ndarray | None  # (corners, 2) per corner
    uv_layers: list


def reimport(bpy, path) -> Readback:
    """The FBX at ``path`` through Blender's importer (default options) into an empty scene."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # the importer prints the FBX version
            assert bpy.ops.import_scene.fbx(filepath=str(path)) == {"FINISHED"}
        assert len(bpy.data.objects) == 1 and bpy.data.objects[0].type == "MESH"
        obj = bpy.data.objects[0]
        me = obj.data
        M = np.array(obj.matrix_world, dtype=np.float64)
        n = len(me.vertices)

        def cm(co):  # Blender world (metres, z up) -> OBJ axes in cm
            X = co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]
            return np.stack([X[:, 0], X[:, 2], -X[:, 1]], 1) * 100.0

        keys = {}
        for kb in (me.shape_keys.key_blocks if me.shape_keys else []):
            co = np.empty(3 * n, dtype=np.float32)
            kb.data.foreach_get("co", co)
            keys[kb.name] = cm(co)
        co = np.empty(3 * n, dtype=np.float32)
        me.vertices.foreach_get("co", co)
        keys.setdefault("Basis", cm(co))
        start = np.empty(len(me.polygons), dtype=np.int64)
        total = np.empty(len(me.polygons), dtype=np.int64)
        me.polygons.foreach_get("loop_start", start)
        me.polygons.foreach_get("loop_total", total)
        assert np.array_equal(start, np.concatenate([[0], np.cumsum(total)[:-1]]))
        corners = np.empty(len(me.loops), dtype=np.int64)
        me.loops.foreach_get("vertex_index", corners)
        uvs = None
        if me.uv_layers:
            uvs = np.empty(2 * len(me.loops), dtype=np.float32)
            me.uv_layers[0].data.foreach_get("uv", uvs)
            uvs = uvs.reshape(-1, 2).astype(np.float64)
        return Readback(obj.name, keys, M, np.concatenate([[0], np.cumsum(total)]), corners, uvs,
                        [u.name for u in me.uv_layers])
    finally:
        bpy.ops.wm.read_factory_settings(use_empty=True)


def _props(elem) -> dict:
    """A node's Properties70 as name -> value(s)."""
    out = {}
    for sub in elem.elems:
        if sub.id == b"Properties70":
            for p in sub.elems:
                vals = p.props[4:]
                out[p.props[0].decode()] = vals[0] if len(vals) == 1 else tuple(vals)
    return out


def _child(elem, name: bytes):
    return next((e for e in elem.elems if e.id == name), None)


def _name(elem) -> str:
    return elem.props[1].split(b"\x00\x01")[0].decode("utf-8")


def parse_raw(path) -> dict:
    """The FBX's nodes, no importer: global settings, the one mesh Model's transform, the
    Geometry's positions (cm, the Model's translation added), polygons and UVs, and each
    BlendShapeChannel (in the order the BlendShape lists them) with its Shape applied."""
    from io_scene_fbx import parse_fbx  # Blender's FBX parser (bpy's add-on path)

    root, version = parse_fbx.parse(str(path))
    top = {e.id: e for e in root.elems}
    settings = _props(top[b"GlobalSettings"])
    objects = {e.props[0]: e for e in top[b"Objects"].elems}
    links = [(c.props[1], c.props[2]) for c in top[b"Connections"].elems]  # (child, parent)
    models = [e for e in objects.values() if e.id == b"Model" and e.props[2] == b"Mesh"]
    assert len(models) == 1
    model = models[0]
    geom = next(objects[c] for c, p in links if p == model.props[0] and objects.get(c) is not None
                and objects[c].id == b"Geometry" and objects[c].props[2] == b"Mesh")
    mp = _props(model)
    T = np.asarray(mp.get("Lcl Translation", (0.0, 0.0, 0.0)), dtype=np.float64)
    base = np.asarray(_child(geom, b"Vertices").props[0], dtype=np.float64).reshape(-1, 3) + T
    pvi = np.asarray(_child(geom, b"PolygonVertexIndex").props[0], dtype=np.int64)
    ends = pvi < 0
    corners = np.where(ends, -pvi - 1, pvi)
    offsets = np.concatenate([[0], np.flatnonzero(ends) + 1])
    uv_elem = _child(geom, b"LayerElementUV")
    uvs = None
    if uv_elem is not None:
        assert _child(uv_elem, b"MappingInformationType").props[0] == b"ByPolygonVertex"
        table = np.asarray(_child(uv_elem, b"UV").props[0], dtype=np.float64).reshape(-1, 2)
        uvs = table[np.asarray(_child(uv_elem, b"UVIndex").props[0], dtype=np.int64)]
    shapes, weights = {}, {}
    blend = [objects[c] for c, p in links if p == geom.props[0] and objects[c].id == b"Deformer"]
    for bs in blend:
        assert bs.props[2] == b"BlendShape"
        for c, p in links:
            if p != bs.props[0]:
                continue
            channel = objects[c]
            assert channel.props[2] == b"BlendShapeChannel"
            shape = next(objects[s] for s, q in links if q == c)
            X = base.copy()
            X[np.asarray(_child(shape, b"Indexes").props[0], dtype=np.int64)] += np.asarray(
                _child(shape, b"Vertices").props[0], dtype=np.float64).reshape(-1, 3)
            shapes[_name(channel)] = X
            weights[_name(channel)] = _child(channel, b"DeformPercent").props[0]
    return dict(version=version, settings=settings, model=mp, model_name=_name(model), base=base,
                offsets=offsets, corners=corners, uvs=uvs, shapes=shapes, weights=weights)


def _grid(tmp_path):
    """A quad grid with a UV seam, then a pentagon without UVs and one loose vertex (read_obj)."""
    from fwk.data.io import read_obj

    V = neutral(np.random.default_rng(3))
    n = len(V)
    extra = np.array([[12.0, 0.0, 0.0], [13.0, 1.0, 0.0], [12.5, 2.0, 0.5], [11.5, 2.0, 0.5], [11.0, 1.0, 0.0],
                      [20.0, 20.0, 20.0]])
    (tmp_path / "grid.obj").write_text(grid_obj(V, extra, [list(range(n, n + 5))]))
    V, t = read_obj(tmp_path / "grid.obj")
    assert np.diff(t.poly_offsets)[-1] == 5 and (t.poly_uvs[-5:] == -1).all()
    return V, t


def _expected_uvs(t):
    st = t.uvs[np.maximum(t.poly_uvs, 0)].copy()
    st[t.poly_uvs < 0] = 0.0
    return st


def test_grid_round_trip_through_blenders_importer(clean, tmp_path):
    """Quads, the pentagon and the loose vertex kept in order, UVs per corner, every shape key in
    cm to 1e-4, under its name, in order; Blender opens it upright at its real size (metres)."""
    from fwk.rig.fbx import write_fbx

    bpy = clean
    V, t = _grid(tmp_path)
    shapes = {e: expression(V, e) for e in SHAPES}
    write_fbx(tmp_path / "grid.fbx", V, t, shapes, units="cm", name="grid")
    back = reimport(bpy, tmp_path / "grid.fbx")
    assert back.name == "grid"
    assert list(back.keys) == ["Basis", *SHAPES]
    assert np.array_equal(back.offsets, t.poly_offsets) and np.array_equal(back.corners, t.poly_vertices)
    assert set(np.diff(back.offsets)) == {4, 5}  # no triangulation
    assert back.uv_layers == ["UVMap"] and np.abs(back.uvs - _expected_uvs(t)).max() < 1e-6
    for key, want in {"Basis": V, **shapes}.items():
        assert back.keys[key].shape == V.shape
        assert np.abs(back.keys[key] - want).max() < TOL_CM, key
    # Blender's importer: 0.01 (the file's cm -> Blender's metres) and y up -> z up, no more
    assert np.allclose(back.matrix[:3, :3], 0.01 * FBX_TO_BLENDER, atol=1e-9)


@pytest.mark.parametrize("units", ["cm", "mm", "m", "in", "unit"])
def test_the_file_holds_centimetres_y_up(clean, tmp_path, units):
    """The raw nodes: UnitScaleFactor 1 (cm), y up, z front; the Model unrotated and unscaled;
    its translation plus the Geometry's vertices, and plus each Shape's offsets, are the OBJs' in
    cm to 1e-4 for a head given in any unit (an unstated unit: metres, as glTF and USD); every
    channel at weight 0, named and ordered as given."""
    from fwk.rig.fbx import write_fbx

    V_cm, t = _grid(tmp_path)
    shapes_cm = {e: expression(V_cm, e) for e in SHAPES}
    k = 1.0 / (METRES_PER_UNIT.get(units, 1.0) * 100.0)  # cm -> the head's units
    write_fbx(tmp_path / "g.fbx", V_cm * k, t, {e: X * k for e, X in shapes_cm.items()}, units=units, name="g")
    raw = parse_raw(tmp_path / "g.fbx")
    s = raw["settings"]
    assert raw["version"] == 7400
    assert s["UnitScaleFactor"] == 1.0 and s["OriginalUnitScaleFactor"] == 1.0
    assert (s["UpAxis"], s["UpAxisSign"], s["FrontAxis"], s["FrontAxisSign"], s["CoordAxis"], s["CoordAxisSign"]) \
        == (1, 1, 2, 1, 0, 1)
    assert tuple(raw["model"].get("Lcl Rotation", (0.0, 0.0, 0.0))) == (0.0, 0.0, 0.0)
    assert tuple(raw["model"].get("Lcl Scaling", (1.0, 1.0, 1.0))) == (1.0, 1.0, 1.0)
    assert raw["model_name"] == "g"
    assert np.array_equal(raw["offsets"], t.poly_offsets) and np.array_equal(raw["corners"], t.poly_vertices)
    assert np.abs(raw["uvs"] - _expected_uvs(t)).max() < 1e-6
    assert np.abs(raw["base"] - V_cm).max() < TOL_CM
    assert list(raw["shapes"]) == list(SHAPES) and set(raw["weights"].values()) == {0.0}
    for e, X in shapes_cm.items():
        assert np.abs(raw["shapes"][e] - X).max() < TOL_CM, e


@pytest.fixture(scope="module")
def synthetic():
    """A synthetic-heads subject (cm, triangles, no UVs): the neutral and its three expressions."""
    from fwk_synthetic_heads import SyntheticHeads

    col = SyntheticHeads(n_subjects=1, n_vertices=1000).load(None)
    P = np.asarray(col.positions[0], dtype=np.float64)
    return P[0], col.template, {s: P[i] for i, s in enumerate(col.shape_names) if s != "neutral"}


@pytest.mark.parametrize("units", ["cm", "mm"])
def test_synthetic_head_in_cm_and_mm(clean, tmp_path, synthetic, units):
    """A synthetic-heads neutral and its expressions given in cm or in mm both come back in cm."""
    from fwk.rig.fbx import write_fbx

    V, t, shapes = synthetic
    k = {"cm": 1.0, "mm": 10.0}[units]
    write_fbx(tmp_path / "h.fbx", V * k, t, {e: X * k for e, X in shapes.items()}, units=units, name="head")
    back = reimport(clean, tmp_path / "h.fbx")
    assert list(back.keys) == ["Basis", *shapes] and back.uvs is None
    assert np.array_equal(back.corners, t.poly_vertices) and np.array_equal(back.offsets, t.poly_offsets)
    for key, want in {"Basis": V, **shapes}.items():
        err = np.abs(back.keys[key] - want).max()
        assert err < TOL_CM, (key, err)
        if key != "Basis":  # the expressions do move (the exporter drops only unmoved vertices)
            assert np.abs(want - V).max() > 0.1


def test_shape_keys_blend_in_blender(clean, tmp_path):
    """Blender evaluates the re-imported keys at weights as the neutral plus the weighted deltas."""
    from fwk.rig.fbx import write_fbx

    bpy = clean
    V, t = _grid(tmp_path)
    shapes = {e: expression(V, e) + 0.01 * i for i, e in enumerate(SHAPES)}
    write_fbx(tmp_path / "grid.fbx", V, t, shapes, units="cm", name="grid")
    bpy.ops.wm.read_factory_settings(use_empty=True)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            bpy.ops.import_scene.fbx(filepath=str(tmp_path / "grid.fbx"))
        obj = bpy.data.objects[0]
        w = {"jawOpen": 0.7, "browInnerUp_L": -0.25, "face-x": 1.0}
        for name, value in w.items():
            kb = obj.data.shape_keys.key_blocks[name]
            kb.slider_min = -1.0
            kb.value = value
        ev = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
        me = ev.to_mesh()
        co = np.empty(3 * len(me.vertices), dtype=np.float32)
        me.vertices.foreach_get("co", co)
        ev.to_mesh_clear()
        M = np.array(obj.matrix_world, dtype=np.float64)
    finally:
        bpy.ops.wm.read_factory_settings(use_empty=True)
    X = co.reshape(-1, 3).astype(np.float64) @ M[:3, :3].T + M[:3, 3]
    got = np.stack([X[:, 0], X[:, 2], -X[:, 1]], 1) * 100.0
    want = V + sum(w[e] * (shapes[e] - V) for e in SHAPES)
    assert np.abs(got - want).max() < TOL_CM


def test_names_come_back_as_given(clean, tmp_path):
    """Shape names with spaces, dots, dashes, non-ASCII letters and Blender's longest (63 bytes),
    and the object's name, survive Blender's exporter and importer unchanged and in order."""
    from fwk.rig.fbx import write_fbx

    V, t = _grid(tmp_path)
    names = ["mouth wide", "face-compression", "a.b", "été", "Zoë", "x" * 63, "3d", "eyeBlinkLeft", "basis"]
    shapes = {name: V + 0.1 * (i + 1) for i, name in enumerate(names)}
    write_fbx(tmp_path / "n.fbx", V, t, shapes, units="cm", name="my head.v2")
    back = reimport(clean, tmp_path / "n.fbx")
    assert back.name == "my head.v2" and list(back.keys) == ["Basis", *names]
    assert list(parse_raw(tmp_path / "n.fbx")["shapes"]) == names


@pytest.mark.parametrize("bad, match", [("Basis", "a shape called 'Basis' would be renamed"),
                                        ("y" * 64, "longer than Blender's 63 bytes"),
                                        ("é" * 32, "longer than Blender's 63 bytes \\(64\\)")])
def test_names_blender_would_change_are_refused(clean, tmp_path, bad, match):
    from fwk.rig.fbx import write_fbx

    V, t = _grid(tmp_path)
    with pytest.raises(FwkError, match=match) as err:
        write_fbx(tmp_path / "r.fbx", V, t, {"ok": V + 1, bad: V + 2}, units="cm")
    assert "\n" not in str(err.value) and not (tmp_path / "r.fbx").exists()


def test_repeated_calls_share_no_state(clean, tmp_path, synthetic):
    """Each file holds its own mesh only: not the previous call's, nor an object the process had
    put into bpy's scene before (write_fbx starts from, and leaves, an empty scene); a mesh
    without shapes is written as a plain mesh."""
    from fwk.rig.fbx import write_fbx

    bpy = clean
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add()  # someone else's object in the scene
    V, t = _grid(tmp_path)
    write_fbx(tmp_path / "a.fbx", V, t, {"jawOpen": expression(V, "jawOpen")}, units="cm", name="a")
    H, ht, _ = synthetic
    write_fbx(tmp_path / "b.fbx", H, ht, {}, units="cm", name="b")
    a, b = parse_raw(tmp_path / "a.fbx"), parse_raw(tmp_path / "b.fbx")  # parse_raw: exactly one mesh Model
    assert a["model_name"] == "a" and list(a["shapes"]) == ["jawOpen"] and len(a["base"]) == len(V)
    assert b["model_name"] == "b" and b["shapes"] == {} and b["uvs"] is None
    assert np.abs(b["base"] - H).max() < TOL_CM


def test_an_unwritable_path_is_one_line(clean, tmp_path):
    from fwk.rig.fbx import write_fbx

    V, t = _grid(tmp_path)
    with pytest.raises(FwkError, match="Blender could not write .*No such file or directory") as err:
        write_fbx(tmp_path / "missing" / "x.fbx", V, t, {"a": V + 1}, units="cm")
    assert "\n" not in str(err.value)


def test_missing_bpy_says_how_to_install(monkeypatch, tmp_path):
    """Without bpy (here: its import blocked) --format fbx fails with one line naming the extra."""
    from fwk.rig.fbx import write_fbx

    monkeypatch.setitem(sys.modules, "bpy", None)  # `import bpy` raises ModuleNotFoundError
    V, t = _grid(tmp_path)
    with pytest.raises(FwkError) as err:
        write_fbx(tmp_path / "x.fbx", V, t, {"a": V + 1}, units="cm")
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith("--format fbx needs the Python package bpy")
    assert "pip install -e '.[fbx]'" in msg and "pip install bpy==4.2.0" in msg
    assert not (tmp_path / "x.fbx").exists()


def test_bpy_without_its_system_libraries_names_the_packages(monkeypatch, tmp_path):
    """An installed bpy that cannot load a shared library (a headless server without X11/GL client
    libraries) is named as such, with the Debian packages, not as missing."""
    from fwk.rig.fbx import write_fbx

    real = builtins.__import__

    def fake(name, *args, **kwargs):
        if name == "bpy":
            raise ImportError("libXi.so.6: cannot open shared object file: No such file or directory")
        return real(name, *args, **kwargs)

    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake)
    V, t = _grid(tmp_path)
    with pytest.raises(FwkError, match=r"bpy is installed but does not load \(libXi\.so\.6.*apt-get install .*libxi6"):
        write_fbx(tmp_path / "x.fbx", V, t, {"a": V + 1}, units="cm")


def test_fwk_apply_writes_an_fbx_equal_to_its_objs(clean, grid_run, tmp_path):
    """``fwk apply --format obj,fbx --naming arkit``: the FBX beside the OBJs holds every OBJ as a
    shape key under its name, to 1e-4 cm through Blender's importer."""
    from fwk.apply import apply
    from fwk.data.io import read_obj

    V = neutral(np.random.default_rng(5)) * 1.05 + np.array([1.0, 2.0, -3.0])
    src = tmp_path / "bo.obj"
    src.write_text(grid_obj(V))
    files = apply(grid_run, src, tmp_path / "out", formats="obj,fbx", naming="arkit", log=lambda *_: None,
                  say=None)
    fbx = tmp_path / "out" / "bo.fbx"
    assert fbx in files
    objs = {p.stem: read_obj(p)[0] for p in files if p.suffix == ".obj"}
    back = reimport(clean, fbx)
    assert back.name == "bo" and list(back.keys)[0] == "Basis" and sorted(back.keys)[1:] == sorted(objs)
    assert np.abs(back.keys["Basis"] - V).max() < TOL_CM  # the run is in cm: the file's cm are the OBJ's
    for name, P in objs.items():
        assert np.abs(back.keys[name] - P).max() < TOL_CM, name


def test_fwk_apply_without_bpy_fails_before_any_work(monkeypatch, grid_run, tmp_path):
    """A missing bpy is one line, said before the run is loaded, and --out is not created."""
    from fwk.apply import apply

    monkeypatch.setitem(sys.modules, "bpy", None)
    src = tmp_path / "bo.obj"
    src.write_text(grid_obj(neutral(np.random.default_rng(5))))
    with pytest.raises(FwkError, match=r"^--format fbx needs the Python package bpy"):
        apply(grid_run, src, tmp_path / "out", formats="obj,fbx", log=lambda *_: None, say=None)
    assert not (tmp_path / "out").exists()
