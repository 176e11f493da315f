import numpy as np
import pytest

from fwk.data import Template
from fwk.data.io import read_obj, read_positions, read_ply, write_obj, write_ply
from fwk.errors import DataError, TopologyError

OBJ = """# a quad mesh with UVs and materials
mtllib m.mtl
o thing
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 2 0 0
v 2 1 0
vt 0 0
vt 1 0
vt 1 1
vt 0 1
vt 0.5 0.5
vn 0 0 1
usemtl A
s 1
f 1/1/1 2/2/1 3/3/1 4/4/1
usemtl B
f -5/2 -2/5 -1/3 -4/3
"""


def test_obj_quads_uvs_round_trip(tmp_path):
    p = tmp_path / "q.obj"
    p.write_text(OBJ)
    V, t = read_obj(p)
    assert V.shape == (6, 3) and t.n_polygons == 2
    assert t.triangles.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]]  # fan from the first corner
    assert t.uvs.shape == (5, 2)
    out = tmp_path / "out.obj"
    write_obj(out, V + 1.0, t)
    lines = out.read_text().splitlines()
    src = OBJ.splitlines()
    # the same polygon lines (negative indices resolved), vt lines, material lines, in order
    assert [l for l in lines if l.startswith("f ")] == ["f 1/1 2/2 3/3 4/4", "f 2/2 5/5 6/3 3/3"]
    assert [l for l in lines if l.startswith("vt ")] == [l for l in src if l.startswith("vt ")]
    assert [l for l in lines if l.split(" ")[0] in ("mtllib", "usemtl", "s", "o")] == \
           ["mtllib m.mtl", "o thing", "usemtl A", "s 1", "usemtl B"]
    V2, t2 = read_obj(out)
    assert np.allclose(V2, V + 1.0)
    assert np.array_equal(t2.triangles, t.triangles) and np.array_equal(t2.poly_uvs, t.poly_uvs)


def test_vertex_order_and_count_kept_with_seams(tmp_path):
    # a vertex used with two different vt (a UV seam) stays one vertex
    p = tmp_path / "s.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nvt .9 .9\n"
                 "f 1/1 2/2 3/3\nf 2/5 4/4 3/3\n")
    V, t = read_obj(p)
    assert V.shape == (4, 3) and np.array_equal(V[:, 0], [0, 1, 0, 1])


def test_topology_errors_name_the_file(tmp_path):
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    t = Template(V, np.array([[0, 1, 2], [1, 3, 2]]))
    write_obj(tmp_path / "ok.obj", V, t)
    write_obj(tmp_path / "flip.obj", V, Template(V, np.array([[0, 1, 3], [0, 3, 2]])))
    write_obj(tmp_path / "more.obj", np.vstack([V, [[2, 2, 2]]]), Template(np.vstack([V, [[2, 2, 2]]]), np.array([[0, 1, 2], [1, 3, 4]])))
    assert np.allclose(read_positions(tmp_path / "ok.obj", t), V)
    with pytest.raises(TopologyError, match=r"flip\.obj: a different face list"):
        read_positions(tmp_path / "flip.obj", t)
    with pytest.raises(TopologyError, match=r"more\.obj: 5 vertices, expected 4"):
        read_positions(tmp_path / "more.obj", t)
    with pytest.raises(DataError, match="nope.obj: no such file"):
        read_obj(tmp_path / "nope.obj")
    (tmp_path / "bad.obj").write_text("v 0 0\n")
    with pytest.raises(DataError, match="bad.obj"):
        read_obj(tmp_path / "bad.obj")


def test_ply_round_trip(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1)
    t = Template(m.vertices, m.faces)
    write_ply(tmp_path / "a.ply", t.vertices, t)
    V, t2 = read_ply(tmp_path / "a.ply")
    assert np.allclose(V, t.vertices) and np.array_equal(t2.triangles, t.triangles)


@pytest.mark.parametrize("edit,expect", [
    (lambda L: L[:5] + ["v 1 2"] + L[5:], "line 6: a vertex line with 2 numbers"),
    (lambda L: L[:5] + ["v 1 x 2"] + L[5:], "line 6: 'x' in a vertex line is not a number"),
    (lambda L: L + ["f 1 2"], "line {n}: a face with fewer than 3 corners"),
    (lambda L: L + ["f 1 2 99"], "line {n}: a face refers to vertex 99, but the file has 6 vertices"),
    (lambda L: L + ["vt 0 q"], "line {n}: unreadable texture line 'vt 0 q'"),
    (lambda L: L + ["f 1 2 z"], "line {n}: unreadable face line 'f 1 2 z'"),
])
def test_obj_errors_name_file_and_line(tmp_path, edit, expect):
    """A broken line is named by file and line number (counted in the file as written)."""
    lines = edit(OBJ.splitlines())
    p = tmp_path / "bad.obj"
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as e:
        read_obj(p)
    assert expect.format(n=len(lines)) in str(e.value) and str(e.value).startswith(f"{p}, line ")


def test_obj_v_lines_equal_formatting_value_by_value():
    """obj_text's v block (one C-level format call) against the naive per-value f"{x:.9g}", on
    values across magnitudes, signs, -0.0, integers and 9-digit ties."""
    from fwk.data import Template
    from fwk.data.io import obj_text

    rng = np.random.default_rng(3)
    V = rng.normal(size=(40, 3)) * 10.0 ** rng.integers(-12, 12, size=(40, 3))
    V[0] = [-0.0, 0.0, 1.0]
    V[1] = [123456789.5, 1e-300, 2.0 ** 60]
    V[2] = [0.1, 1 / 3, 12345.6789012345]
    F = np.array([[i, i + 1, i + 2] for i in range(len(V) - 2)])
    text = obj_text(V, Template(V, F))
    v_lines = [ln for ln in text.splitlines() if ln.startswith("v ")]
    assert v_lines == ["v " + " ".join(f"{x:.9g}" for x in row) for row in V]
