"""The example dataset passes fwk's dataset contract suite, loads exactly what
``write_npz_meshes`` wrote (polygons, missing meshes, the renamed neutral, landmarks, regions),
memory-maps its positions through the cache, names the file in one line for every bad file, and
feeds a reconstruct run from a recipe."""
import json

import numpy as np
import pytest

from fwk.cache import Cache
from fwk.errors import DataError, RecipeError
from fwk.plugins import get_registry
from fwk.testing.dataset import DatasetContract
from fwk_example_plugin.npz_meshes import NpzMeshes, write_npz_meshes
from recipe_runs import assert_tested, run_recipe


def grid(nx=6, ny=5):
    """A bumpy nx x ny grid of quads whose first cell is split into two triangles (a mixed
    polygon list: rows padded with -1), and its vertices."""
    x, y = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    V = np.stack([x.ravel(), y.ravel(), 0.1 * np.sin(3 * x.ravel()) * y.ravel()], 1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    quads = np.stack([a, b, c, d], 1)
    tris = np.array([[a[0], b[0], c[0], -1], [a[0], c[0], d[0], -1]])
    return V, np.concatenate([tris, quads[1:]])


def small_file(path, missing=True):
    """4 subjects x 3 shapes ("smile", "rest" = the neutral, "frown"), subject 2's frown missing
    (NaN) unless ``missing`` is false, float32 positions, landmarks and a region."""
    V, F = grid()
    rng = np.random.default_rng(0)
    P = V[None, None] + rng.normal(0, 0.01, (4, 3, len(V), 3))
    P[:, 0] += [0, 0, 0.05]
    if missing:
        P[2, 2] = np.nan
    return write_npz_meshes(path, P.astype(np.float32), F, subjects=["ann", "bob", "cy", "dee"],
                            shapes=["smile", "rest", "frown"], landmarks={"corner": 0, "middle": 14},
                            regions={"left": [0, 6, 12, 18, 24]}), P, F


class TestNpzMeshesContract(DatasetContract):
    component = NpzMeshes
    params: dict = {}

    @pytest.fixture(scope="class", autouse=True)
    @classmethod
    def npz_file(cls, tmp_path_factory):
        """The file the suite loads (the contract's ``params`` name it). Without a missing mesh:
        the suite's test_deterministic compares positions with np.array_equal, which a missing
        mesh's NaN never equals (test_loading_is_deterministic_with_missing_meshes below)."""
        path, _, _ = small_file(tmp_path_factory.mktemp("npz") / "faces.npz", missing=False)
        cls.params = {"path": str(path), "neutral": "rest", "units": "cm"}
        return path


def test_registered_through_its_own_entry_point():
    e = get_registry().entry("dataset", "npz-meshes")
    assert e.component is NpzMeshes and e.plugin == "example-npz"


def test_loads_what_was_written(tmp_path):
    path, P, F = small_file(tmp_path / "faces.npz")
    col = NpzMeshes(str(path), neutral="rest", units="mm").load(None)
    assert col.shape_names == ["neutral", "smile", "frown"]  # the neutral first, renamed, then file order
    assert col.subjects == ["ann", "bob", "cy", "dee"] and col.name == "npz-meshes"
    X = np.asarray(col.positions)
    assert X.dtype == np.float64 and X.shape == (4, 3, 30, 3)
    want = P.astype(np.float32).astype(np.float64)[:, [1, 0, 2]]
    assert np.array_equal(X[col.present], want[col.present])
    assert col.present.tolist() == [[True] * 3, [True] * 3, [True, True, False], [True] * 3]
    assert np.isnan(X[2, 2]).all()  # a missing mesh is all NaN
    t = col.template
    assert t.units == "mm" and np.array_equal(t.vertices, X[0, 0])  # the first subject's neutral
    # the polygons are kept as written (two triangles, then quads) and fan-triangulated
    assert t.n_polygons == len(F) and np.array_equal(t.poly_vertices, F[F >= 0])
    assert np.array_equal(np.diff(t.poly_offsets), (F >= 0).sum(1))
    quad = F[2]
    assert [quad[0], quad[1], quad[2]] in t.triangles.tolist() and [quad[0], quad[2], quad[3]] in t.triangles.tolist()
    assert len(t.triangles) == 2 + 2 * (len(F) - 2)
    assert t.landmarks == {"corner": 0, "middle": 14} and t.regions["left"].tolist() == [0, 6, 12, 18, 24]


def test_loading_is_deterministic_with_missing_meshes(tmp_path):
    path, _, _ = small_file(tmp_path / "faces.npz")
    a = NpzMeshes(str(path), neutral="rest").load(Cache(tmp_path / "a"))
    b = NpzMeshes(str(path), neutral="rest").load(Cache(tmp_path / "b"))
    assert np.array_equal(np.asarray(a.positions), np.asarray(b.positions), equal_nan=True)
    assert a.subjects == b.subjects and np.array_equal(a.present, b.present) and not a.present.all()


def test_shapes_chooses_and_orders(tmp_path):
    path, P, _ = small_file(tmp_path / "faces.npz")
    col = NpzMeshes(str(path), neutral="rest", shapes=["frown", "rest"]).load(None)
    assert col.shape_names == ["neutral", "frown"]
    assert np.allclose(np.asarray(col.positions)[0, 1], P[0, 2], atol=1e-6)
    V, F = grid()
    one = write_npz_meshes(tmp_path / "neutrals.npz", np.stack([V, V + 1]), F[2:])  # (S, n, 3): neutrals only
    col = NpzMeshes(str(one)).load(None)
    assert col.shape_names == ["neutral"] and col.subjects == ["s0000", "s0001"]
    assert col.positions.shape == (2, 1, 30, 3)


def test_cache_memory_maps_the_positions_and_sees_a_new_file(tmp_path):
    path, _, _ = small_file(tmp_path / "faces.npz")
    ds = NpzMeshes(str(path), neutral="rest")
    fresh = ds.load(None)
    cache = Cache(tmp_path / "cache")
    ds.load(cache)
    again = ds.load(cache)
    assert isinstance(again.positions, np.memmap) and not again.positions.flags.writeable
    assert np.array_equal(np.asarray(again.positions), np.asarray(fresh.positions), equal_nan=True)
    assert np.array_equal(again.present, fresh.present)
    V, F = grid()
    write_npz_meshes(path, np.stack([V, V + 2.0]), F, shapes=["rest"])  # the file replaced
    new = ds.load(cache)
    assert new.positions.shape == (2, 1, 30, 3) and np.allclose(np.asarray(new.positions)[1, 0], V + 2.0)


def _variant(tmp_path, **change):
    """A file like small_file's with some arrays replaced (None: left out), written with np.savez."""
    V, F = grid()
    arrays = {"positions": np.stack([np.stack([V, V + 0.1])] * 3), "faces": F,
              "subjects": np.array(["a", "b", "c"]), "shapes": np.array(["neutral", "smile"])}
    arrays.update(change)
    path = tmp_path / "bad.npz"
    with open(path, "wb") as f:
        np.savez(f, **{k: v for k, v in arrays.items() if v is not None})
    return path


def _nan_some(P):
    P = P.copy()
    P[1, 1, 3] = np.nan
    return P


BASE = np.stack([np.stack([grid()[0], grid()[0] + 0.1])] * 3)
BAD = {
    "no faces": ({"faces": None}, "no array 'faces'"),
    "face out of range": ({"faces": np.array([[0, 1, 99]])}, "vertex 99 but the meshes have 30"),
    "repeated corner": ({"faces": np.array([[0, 1, 1]])}, "repeats a vertex"),
    "two corners": ({"faces": np.array([[0, 1, -1, -1]])}, "at least 3"),
    "float faces": ({"faces": np.array([[0.0, 1.0, 2.0]])}, "array 'faces' must be"),
    "flat positions": ({"positions": np.zeros((3, 30))}, "array 'positions' must be"),
    "subject count": ({"subjects": np.array(["a", "b"])}, "'subjects' names 2 subjects"),
    "duplicate subject": ({"subjects": np.array(["a", "b", "a"])}, "names 'a' twice"),
    "no neutral shape": ({"shapes": np.array(["rest", "smile"])}, "no neutral shape 'neutral'"),
    "partly NaN mesh": ({"positions": _nan_some(BASE)}, "partly NaN"),
    "present but NaN": ({"positions": _nan_some(BASE), "present": np.ones((3, 2), bool)}, "marked present"),
    "present of the wrong shape": ({"present": np.ones((2, 2), bool)}, "array 'present' must be"),
    "subject without a neutral": ({"present": np.array([[True, True], [False, True], [True, True]])},
                                  "subjects without a neutral"),
    "object array": ({"subjects": np.array(["a", "b", "c"], dtype=object)}, "without unpickling"),
    "landmark out of range": ({"landmark_names": np.array(["x"]), "landmark_vertices": np.array([30])},
                              "'landmark_vertices' must be"),
    "empty region": ({"region_face": np.zeros(0, np.int64)}, "'region_face' must be"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_file_is_one_line_naming_it(tmp_path, case):
    change, words = BAD[case]
    path = _variant(tmp_path, **change)
    with pytest.raises(DataError) as err:
        NpzMeshes(str(path)).load(Cache(tmp_path / "cache"))
    msg = str(err.value)
    assert words in msg and str(path) in msg and "\n" not in msg


def test_a_missing_or_foreign_file_is_a_data_error(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        NpzMeshes(str(tmp_path / "none.npz")).load(None)
    with pytest.raises(DataError, match="is a folder"):
        NpzMeshes(str(tmp_path)).load(None)
    (tmp_path / "text.npz").write_text("v 0 0 0\n")
    with pytest.raises(DataError, match="not an .npz file"):
        NpzMeshes(str(tmp_path / "text.npz")).load(None)
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04" + b"\0" * 10)
    with pytest.raises(DataError, match="not a readable .npz"):
        NpzMeshes(str(tmp_path / "cut.npz")).load(None)
    path, _, _ = small_file(tmp_path / "faces.npz")
    with pytest.raises(DataError, match="no shape 'frwn'; did you mean frown"):
        NpzMeshes(str(path), neutral="rest", shapes=["frwn"]).load(None)
    with pytest.raises(DataError, match="would clash"):  # the file's own 'neutral' and a renamed neutral
        NpzMeshes(str(write_npz_meshes(tmp_path / "two.npz", BASE, grid()[1], shapes=["neutral", "smile"])),
                  neutral="smile").load(None)


def test_bad_parameters_are_recipe_errors():
    with pytest.raises(RecipeError, match="path"):
        NpzMeshes("")
    with pytest.raises(RecipeError, match="listed twice"):
        NpzMeshes("x.npz", shapes=["a", "a"])
    with pytest.raises(RecipeError, match="units: 'parsec' is not a unit"):
        NpzMeshes("x.npz", units="parsec")


RECIPE = """
task: reconstruct
seed: 0
dataset: {{name: npz-meshes, path: {path}, units: cm}}
split: {{ratios: [0.7, 0.1, 0.2]}}
train: {{epochs: 2, batch_size: 8, lr: 1.0e-3}}
models:
  pca: {{name: pca, n_components: 4}}
  ae: {{name: ae, conv: {{name: cheb, k: 3}}, channels: [8, 16], latent: 8,
        sampler: {{name: quadric, factors: [4, 4]}}}}
metrics: [l1]
renders: 0
"""


def test_npz_meshes_feed_a_reconstruct_run(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    heads = get_registry().get("dataset", "synthetic-heads")(n_subjects=16, n_vertices=300).load(None)
    t = heads.template
    path = write_npz_meshes(tmp_path / "heads.npz", heads.positions, t.triangles, heads.subjects, heads.shape_names,
                            landmarks=t.landmarks, regions=t.regions)
    run_dir = run_recipe(tmp_path, "npz.yaml", RECIPE.format(path=path))
    assert_tested(run_dir, {"pca", "ae"}, only=True)
    split = json.loads((run_dir / "split.json").read_text())  # the file's subject ids, split by subject
    assert sorted(split["train"] + split["val"] + split["test"]) == sorted(heads.subjects)
