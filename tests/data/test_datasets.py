import numpy as np
import pytest

from fwk.errors import DataError, TopologyError
from fwk.plugins import get_registry
from fwk.testing import ICT_SKIP_REASON, ict_path
from fwk.testing.dataset import DatasetContract

REG = get_registry()
SH = REG.get("dataset", "synthetic-heads")


class TestSyntheticHeadsContract(DatasetContract):
    component = SH
    params = {"n_subjects": 6, "n_vertices": 1200}


def test_synthetic_heads_properties(tmp_path):
    from fwk.cache import Cache

    col = SH(n_subjects=40, n_vertices=1500).load(Cache(tmp_path))
    t = col.template
    assert abs(t.n_vertices - 1500) / 1500 < 0.05
    assert col.shape_names == ["neutral", "face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"]
    # open neck boundary
    from fwk.geometry import edge_topology

    topo = edge_topology(t.triangles, t.n_vertices)
    assert len(topo.border) > 0 and not len(topo.non_manifold)
    # the face is tessellated >= 3x denser than scalp and neck (vertices per unit area)
    import trimesh

    m = trimesh.Trimesh(t.vertices, t.triangles, process=False)
    va = np.zeros(t.n_vertices)
    np.add.at(va, t.triangles.ravel(), np.repeat(m.area_faces / 3, 3))
    density = {r: len(ix) / va[ix].sum() for r, ix in t.regions.items()}
    assert density["face"] >= 3 * density["scalp"] and density["face"] >= 3 * density["neck"], density
    # a head-sized object in cm
    ext = t.vertices.max(0) - t.vertices.min(0)
    assert 12 < ext[0] < 20 and 15 < ext[1] < 40 and 15 < ext[2] < 25
    # expressions are personalised: displacements differ beyond a global scale
    P = np.asarray(col.positions)
    for j in range(1, 4):
        D = (P[:, j] - P[:, 0]).reshape(len(P), -1)
        U = D / np.linalg.norm(D, axis=1, keepdims=True)
        cos = U @ U.T
        assert cos[np.triu_indices(len(P), 1)].min() < 0.999
    # identities differ
    assert np.abs(P[0, 0] - P[1, 0]).max() > 0.1


def test_synthetic_heads_wrinkles_grow_with_age():
    ds = SH(n_subjects=60, n_vertices=3000, seed=1)
    col = ds.load(None)
    flat = SH(n_subjects=60, n_vertices=3000, seed=1, wrinkles=0.0).load(None)
    hf = np.abs(np.asarray(col.positions)[:, 0] - np.asarray(flat.positions)[:, 0]).mean(axis=(1, 2))
    age = ds.identity_params()["age"]
    assert np.corrcoef(age, hf)[0, 1] > 0.8


def test_synthetic_heads_unknown_shape():
    from fwk.errors import RecipeError

    with pytest.raises(RecipeError, match="did you mean mouth-wide"):
        SH(shapes=["mouth-wid"])


def test_mesh_folder(tmp_path):
    from fwk.data import Template
    from fwk.data.io import write_obj

    MF = REG.get("dataset", "mesh-folder")
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    t = Template(V, np.array([[0, 1, 2], [1, 3, 2]]))
    for s in ("a", "b"):
        for e in ("neutral", "smile"):
            write_obj(tmp_path / f"Tester_{s}" / f"pose_{e}.obj", V + len(s + e), t)
    col = MF(root=str(tmp_path), pattern="Tester_{subject}/pose_{shape}.obj").load()
    assert col.subjects == ["a", "b"] and col.shape_names == ["neutral", "smile"]
    bad = Template(V, np.array([[0, 1, 3], [0, 3, 2]]))
    write_obj(tmp_path / "Tester_b" / "pose_smile.obj", V, bad)
    with pytest.raises(TopologyError, match=r"Tester_b/pose_smile\.obj: a different face list"):
        MF(root=str(tmp_path), pattern="Tester_{subject}/pose_{shape}.obj").load()
    write_obj(tmp_path / "Tester_b" / "pose_smile.obj", np.vstack([V, V[:1]]), Template(np.vstack([V, V[:1]]), t.triangles))
    with pytest.raises(TopologyError, match=r"Tester_b/pose_smile\.obj: 5 vertices, not 4"):
        MF(root=str(tmp_path), pattern="Tester_{subject}/pose_{shape}.obj").load()
    with pytest.raises(DataError, match="no file"):
        MF(root=str(tmp_path), pattern="{subject}/x_{shape}.ply").load()


ICT = ict_path()


@pytest.mark.skipif(ICT is None, reason=ICT_SKIP_REASON)
class TestICTContract(DatasetContract):
    component = REG.get("dataset", "ict-facekit")
    params = {"path": str(ICT), "n_subjects": 4}

    def make_cache(self, tmp_path):  # the parsed files are shared; sampling still runs per load
        return _ict_cache()


def _ict_cache():
    import tempfile
    from pathlib import Path

    from fwk.cache import Cache

    return Cache(Path(tempfile.gettempdir()) / "fwk-test-ict-cache")


@pytest.mark.skipif(ICT is None, reason=ICT_SKIP_REASON)
def test_ict_regions_and_personalisation(tmp_path):
    from fwk.cache import Cache

    ICTD = REG.get("dataset", "ict-facekit")
    col = ICTD(path=str(ICT), n_subjects=5).load(_ict_cache())
    assert col.template.n_vertices == 11248 and col.template.n_polygons == 11144
    assert (np.diff(col.template.poly_offsets) == 4).all()
    P = np.asarray(col.positions)
    D = P[:, 1] - P[:, 0]
    assert not np.allclose(D[0], D[1])
    plain = ICTD(path=str(ICT), n_subjects=5, personalise=False).load(_ict_cache())
    Dp = np.asarray(plain.positions)[:, 1] - np.asarray(plain.positions)[:, 0]
    assert np.allclose(Dp[0], Dp[1])
    with pytest.raises(DataError, match="does not exist"):
        ICTD(path=str(tmp_path / "nowhere")).load()
