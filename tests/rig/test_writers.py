"""The rig writers' building blocks against naive references: vertex normals, the batched OBJ
writer, glTF's corner splitting, the ARKit renaming."""
import numpy as np
import pytest

from fwk.errors import FwkError

from .conftest import SEAM, W, grid_obj, neutral


def _grid(tmp_path, rng=None):
    from fwk.data.io import read_obj

    p = tmp_path / "g.obj"
    p.write_text(grid_obj(neutral(rng or np.random.default_rng(0))))
    return read_obj(p)


def test_vertex_normals_against_a_per_triangle_loop(tmp_path):
    from fwk.rig import vertex_normals

    V, t = _grid(tmp_path)
    V = np.vstack([V, [[9.0, 9.0, 9.0]]])  # an isolated vertex: (0, 0, 1)
    ref = np.zeros_like(V)
    for tri in t.triangles:
        a, b, c = V[tri]
        for v in tri:
            ref[v] += np.cross(b - a, c - a)
    ref[-1] = [0.0, 0.0, 1.0]
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    assert np.allclose(vertex_normals(V, t.triangles), ref, atol=1e-12)
    stack = np.stack([V, 2.0 * V[:, ::-1]])
    assert np.allclose(vertex_normals(stack, t.triangles)[1], vertex_normals(stack[1], t.triangles), atol=1e-12)


def test_obj_writer_is_byte_identical_to_obj_text(tmp_path):
    from fwk.data.io import ObjWriter
    from fwk.data import Template
    from fwk.data.io import obj_text

    V, t = _grid(tmp_path)
    X = V + np.random.default_rng(1).normal(size=V.shape) * 1e-3
    assert ObjWriter(t).text(X) == obj_text(X, t)
    tri = Template(V[:4], np.array([[0, 1, 2], [0, 2, 3]]))  # no UVs, no material lines
    assert ObjWriter(tri).text(X[:4]) == obj_text(X[:4], tri)
    with pytest.raises(ValueError):
        ObjWriter(t).text(X[:-1])


def test_gltf_corners_split_the_uv_seam_only(tmp_path):
    from fwk.rig.gltf import corners

    _, t = _grid(tmp_path)
    vert, uv, corner = corners(t)
    assert len(vert) == (W + 1) ** 2 + (W + 1)  # the seam column's W+1 vertices twice
    assert np.array_equal(vert[corner], t.poly_vertices) and np.array_equal(uv[corner], t.poly_uvs)
    twice = np.flatnonzero(np.bincount(vert) == 2)
    assert set(twice % (W + 1)) == {SEAM}


def test_arkit_rename():
    from fwk.rig.arkit import ARKIT_NAMES, COMBINED, ICT_TO_ARKIT, rename

    assert len(ARKIT_NAMES) == len(set(ARKIT_NAMES)) == 52
    assert set(ICT_TO_ARKIT.values()) | set(COMBINED) == set(ARKIT_NAMES) - {"tongueOut"}
    N = np.zeros((2, 3))
    shapes = {"eyeBlink_L": N + 1, "cheekPuff_L": N + 2, "cheekPuff_R": N + 3, "mine": N + 4}
    out = rename(shapes, N, "arkit")
    assert list(out) == ["eyeBlinkLeft", "cheekPuff_L", "cheekPuff_R", "mine", "cheekPuff"]
    assert np.array_equal(out["cheekPuff"], N + 5)
    assert rename(shapes, N, "source").keys() == shapes.keys()
    with pytest.raises(FwkError, match="two shapes would be called eyeBlinkLeft"):
        rename({"eyeBlink_L": N, "eyeBlinkLeft": N}, N, "arkit")
    with pytest.raises(FwkError, match="unknown naming"):
        rename(shapes, N, "maya")


@pytest.mark.parametrize("units", ["m", "cm", "mm", "um", "in", "ft", "unit"])
def test_rig_files_carry_the_scale_of_every_stated_unit(tmp_path, units):
    """glTF's node scale and USD's metersPerUnit are the metres in one of the head's units, for
    every unit a dataset (or `fwk apply --units`) may state: a head in inches is not read as metres
    (an unstated unit: 1)."""
    pytest.importorskip("pygltflib")
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from fwk.rig.gltf import write_glb
    from fwk.rig.usd import write_usd

    from .readers import read_glb

    want = {"m": 1.0, "cm": 0.01, "mm": 0.001, "um": 1e-6, "in": 0.0254, "ft": 0.3048, "unit": 1.0}[units]
    V, t = _grid(tmp_path)
    V = V - V.mean(axis=0)
    write_glb(tmp_path / "r.glb", V, t, {"a": V + 0.01}, units=units)
    doc, _ = read_glb(tmp_path / "r.glb")
    assert doc["nodes"][0].get("scale", [1.0] * 3) == pytest.approx([want] * 3)
    assert doc["extras"]["fwk"]["metres_per_unit"] == pytest.approx(want)
    write_usd(tmp_path / "r.usda", V, t, {"a": V + 0.01}, units=units)
    assert UsdGeom.GetStageMetersPerUnit(Usd.Stage.Open(str(tmp_path / "r.usda"))) == pytest.approx(want)
    from fwk.view import load_rig

    # and fwk view reads the unit back (USD stores metres only: an unstated unit reads as metres)
    assert load_rig(tmp_path / "r.usda").units == (units if units != "unit" else "m")
