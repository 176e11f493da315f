"""fwk apply: a user's quad OBJ with UVs round-trips (same polygons, same vt lines); wrong
topology, NaNs and unreadable files are refused with nothing written."""
import numpy as np
import pytest
import yaml

from fwk.errors import DataError, FwkError, TopologyError
from fwk.safeio import load_state

W = 7  # (W+1) x (W+1) vertices, W x W quads


def _grid_obj(V, mtl=True) -> str:
    lines = ["mtllib head.mtl", "o head"] if mtl else []
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    lines += [f"vt {i / W:.4f} {j / W:.4f}" for j in range(W + 1) for i in range(W + 1)]
    if mtl:
        lines.append("usemtl skin")
    for j in range(W):
        for i in range(W):
            a = j * (W + 1) + i
            q = [a, a + 1, a + W + 2, a + W + 1]
            lines.append("f " + " ".join(f"{v + 1}/{v + 1}" for v in q))
            if (i, j) == (W // 2, W // 2) and mtl:
                lines.append("usemtl lips")
    return "\n".join(lines) + "\n"


def _neutral(rng):
    x, y = np.meshgrid(np.linspace(-1, 1, W + 1), np.linspace(-1, 1, W + 1))
    z = 0.3 * np.exp(-(x ** 2 + y ** 2)) + 0.05 * rng.standard_normal(x.shape)
    return np.stack([x.ravel() * (1 + 0.1 * rng.standard_normal()), y.ravel(), z.ravel()], 1)


def _smile(V):
    out = V.copy()
    out[:, 2] += 0.2 * np.exp(-4 * (V[:, 0] ** 2 + (V[:, 1] + 0.5) ** 2)) * (1 + V[:, 2])
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from fwk.runs import execute

    root = tmp_path_factory.mktemp("heads")
    rng = np.random.default_rng(0)
    for s in range(8):
        V = _neutral(rng)
        (root / f"s{s}").mkdir()
        (root / f"s{s}" / "neutral.obj").write_text(_grid_obj(V))
        (root / f"s{s}" / "smile.obj").write_text(_grid_obj(_smile(V)))
    recipe = {"name": "apply-test", "task": "blendshapes", "seed": 0,
              "dataset": {"name": "mesh-folder", "root": str(root)},
              "split": {"ratios": [0.6, 0.2, 0.2]},
              "models": {"dt": {"name": "dt", "sources": 0}}, "renders": 0,
              "metrics": ["l1", "l2"]}
    path = root / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return execute(str(path), runs_dir=str(tmp_path_factory.mktemp("runs")), quiet=True)


def test_apply_round_trips_quads_uvs_and_materials(run_dir, tmp_path):
    import torch

    from fwk.apply import apply
    from fwk.data.io import read_obj

    rng = np.random.default_rng(7)
    V = _neutral(rng) * 1.5 + np.array([10.0, -2.0, 5.0])  # another size (within fwk.apply.MAX_SCALE_RATIO) and placement
    src = tmp_path / "me.obj"
    src.write_text(_grid_obj(V))
    out = tmp_path / "out"
    files = apply(run_dir, src, out, log=lambda *_: None)
    assert [f.name for f in files] == ["smile.obj"]
    text_in, text_out = src.read_text().splitlines(), (out / "smile.obj").read_text().splitlines()
    keep = lambda lines: [ln for ln in lines if not ln.startswith("v ")]  # noqa: E731
    assert keep(text_out) == keep(text_in)  # same polygons, vt lines, material lines, in order
    P, tpl = read_obj(out / "smile.obj")
    assert P.shape == V.shape and tpl.n_polygons == W * W
    # the written positions are the model's prediction undone into the user's units
    from fwk.apply import Applier

    app = Applier(run_dir)
    assert np.allclose(app.predict([V])[0]["smile"], P, atol=1e-6)
    assert not np.allclose(P, V)  # something moved
    assert isinstance(load_state(run_dir / "models" / "dt.safetensors"), dict)


def test_apply_a_folder(run_dir, tmp_path):
    from fwk.apply import apply

    rng = np.random.default_rng(3)
    folder = tmp_path / "neutrals"
    folder.mkdir()
    for name in ("anna", "ben"):
        (folder / f"{name}.obj").write_text(_grid_obj(_neutral(rng)))
    files = apply(run_dir, folder, tmp_path / "out", log=lambda *_: None)
    assert sorted(str(f.relative_to(tmp_path / "out")) for f in files) == ["anna/smile.obj", "ben/smile.obj"]


def _refused(run_dir, tmp_path, text, error):
    from fwk.apply import apply

    folder = tmp_path / "in"
    folder.mkdir(parents=True)
    (folder / "good.obj").write_text(_grid_obj(_neutral(np.random.default_rng(1))))
    (folder / "bad.obj").write_text(text)
    out = tmp_path / "out"
    with pytest.raises(error) as exc:
        apply(run_dir, folder, out, log=lambda *_: None)
    assert "bad.obj" in str(exc.value)
    assert not out.exists()  # nothing half-written
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]  # no temporary left


def test_apply_refuses_a_wrong_topology(run_dir, tmp_path):
    V = _neutral(np.random.default_rng(2))
    lines = _grid_obj(V).splitlines()
    f = [i for i, ln in enumerate(lines) if ln.startswith("f ")]
    lines[f[0]], lines[f[1]] = lines[f[1]], lines[f[0]]  # same counts, different face list
    _refused(run_dir, tmp_path, "\n".join(lines) + "\n", TopologyError)


def test_apply_refuses_fewer_vertices(run_dir, tmp_path):
    V = _neutral(np.random.default_rng(2))
    text = "\n".join(f"v {x} {y} {z}" for x, y, z in V[:-3]) + "\nf 1 2 3\n"
    _refused(run_dir, tmp_path, text, TopologyError)


def test_apply_refuses_nans_and_unreadable(run_dir, tmp_path):
    V = _neutral(np.random.default_rng(2))
    V[5, 1] = np.nan
    _refused(run_dir, tmp_path / "a", _grid_obj(V), DataError)
    _refused(run_dir, tmp_path / "b", "v 1 2 three\nf 1 2 3\n", DataError)


def test_apply_names_a_missing_run_or_model(run_dir, tmp_path):
    from fwk.apply import apply

    with pytest.raises(FwkError, match="not a run directory"):
        apply(tmp_path, tmp_path / "x.obj", tmp_path / "out")
    with pytest.raises(FwkError, match="--model nope"):
        apply(run_dir, tmp_path / "x.obj", tmp_path / "out", model="nope")
