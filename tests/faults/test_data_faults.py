"""Broken mesh files and values the data refutes: the right file and line are named, before
any training, and no run directory is left (issue 16, reproductions 5 and 6)."""
from __future__ import annotations

import numpy as np
import pytest

from fwk.cli import main
from fwk.data import Template
from fwk.data.io import write_obj
from tests.faults.common import recipe, run_dirs


def _folder(tmp_path, n=9):
    """A mesh folder of ``n`` subjects' neutrals on one quad topology (s00 first in sorted order)."""
    rng = np.random.default_rng(0)
    k = 6
    u, v = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    V = np.stack([u.ravel(), v.ravel(), np.zeros(k * k)], 1)
    F = np.array([[i * k + j, i * k + j + 1, (i + 1) * k + j + 1] for i in range(k - 1) for j in range(k - 1)] +
                 [[i * k + j, (i + 1) * k + j + 1, (i + 1) * k + j] for i in range(k - 1) for j in range(k - 1)])
    t = Template(V, F)
    root = tmp_path / "data"
    for s in range(n):
        write_obj(root / f"s{s:02d}" / "neutral.obj", V + rng.normal(0, 0.02, V.shape), t)
    return root


def _recipe(tmp_path, root, models="{pca: {name: pca, n_components: 2}}", units="mm"):
    return recipe(tmp_path, f"task: reconstruct\ndataset: {{name: mesh-folder, root: {root}, units: {units}}}\n"
                            f"split: {{ratios: [0.8, 0.1, 0.1]}}\nmodels: {models}\nmetrics: [l1]\nrenders: 0\n")


def _fails(tmp_path, capsys, r, *expect):
    capsys.readouterr()
    assert main(["--quiet", "run", str(r), "--runs-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1, err
    for e in expect:
        assert e in err, err
    assert run_dirs(tmp_path / "runs") == []
    return err


def test_truncated_first_file_is_the_one_named(tmp_path, env, capsys):
    """Reproduction 5a: the first file (sorted) cut in its face block; the good second file used
    to be blamed. Now the topology most files share is the template's."""
    root = _folder(tmp_path)
    first = root / "s00" / "neutral.obj"
    lines = first.read_text().splitlines(keepends=True)
    first.write_text("".join(lines[:-10]))  # the last ten faces gone, ends on a whole line
    err = _fails(tmp_path, capsys, _recipe(tmp_path, root), "s00/neutral.obj: 40 polygons, not 50",
                 "s01/neutral.obj and 7 other files")
    assert "s01/neutral.obj:" not in err


def test_line_cut_mid_file_names_file_and_line(tmp_path, env, capsys):
    """Reproduction 5b: a vertex line cut to two numbers in the middle of a file: the file and its
    line number, not numpy's "inhomogeneous shape"."""
    root = _folder(tmp_path)
    p = root / "s04" / "neutral.obj"
    lines = p.read_text().splitlines(keepends=True)
    i = next(n for n, line in enumerate(lines) if line.startswith("v ")) + 7
    lines[i] = " ".join(lines[i].split()[:3]) + "\n"  # `v x y`
    p.write_text("".join(lines))
    err = _fails(tmp_path, capsys, _recipe(tmp_path, root), f"s04/neutral.obj, line {i + 1}: a vertex line with 2 numbers")
    assert "inhomogeneous" not in err


def test_face_line_cut_names_file_and_line(tmp_path, env, capsys):
    root = _folder(tmp_path)
    p = root / "s03" / "neutral.obj"
    lines = p.read_text().splitlines(keepends=True)
    lines[-1] = lines[-1].rsplit(" ", 1)[0] + "\n"  # the last face keeps two corners
    p.write_text("".join(lines))
    _fails(tmp_path, capsys, _recipe(tmp_path, root), f"s03/neutral.obj, line {len(lines)}: a face with fewer than 3 corners")


def test_two_files_disagree_without_a_majority(tmp_path, env, capsys):
    root = _folder(tmp_path, n=2)
    first = root / "s00" / "neutral.obj"
    first.write_text("".join(first.read_text().splitlines(keepends=True)[:-10]))
    _fails(tmp_path, capsys, _recipe(tmp_path, root), "s00/neutral.obj and s01/neutral.obj differ", "one of them is wrong")


def test_too_many_components_refused_before_training(tmp_path, env, capsys):
    """Reproduction 6a: n_components 500 with 7 training meshes: refused before the model is
    fitted, naming the recipe key and the most the training set carries (no run directory)."""
    root = _folder(tmp_path)
    r = _recipe(tmp_path, root, "{pca: {name: pca, n_components: 500}}")
    _fails(tmp_path, capsys, r, "models.pca.n_components: 500 components, but the training split holds 7 meshes",
           "n_components <= 6")


def test_too_many_components_refused_before_any_model_trains(tmp_path, env, capsys, monkeypatch):
    """The check runs before the first model of the recipe trains, not when pca's turn comes: a
    network listed first is never fitted (fwk.lifecycle.build_models, the ChecksData role)."""
    import fwk_reconstruct

    fitted = []
    monkeypatch.setattr(fwk_reconstruct, "fit_models", lambda models, *a, **k: fitted.extend(models) or {})
    root = _folder(tmp_path)
    r = _recipe(tmp_path, root, "{mlp: {name: mlp-vae, latent: 4, hidden: [16]}, pca: {name: pca, n_components: 500}}")
    _fails(tmp_path, capsys, r, "models.pca.n_components: 500 components")
    assert fitted == [], "no model trains before the recipe's values are checked"


def test_unknown_units_refused_when_validating(tmp_path, env, capsys):
    """Reproduction 6b: dataset.units=furlongs, in a mesh-folder recipe and as a synthetic-heads
    override (both declare ``units: Units``: the check is the recipe's)."""
    root = _folder(tmp_path)
    _fails(tmp_path, capsys, _recipe(tmp_path, root, units="furlongs"), "dataset.units: expected one of",
           "'cm', 'mm'", "got 'furlongs'")
    capsys.readouterr()
    assert main(["--quiet", "run", str(recipe(tmp_path)), "dataset.units=furlongs", "--runs-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert "dataset.units: expected one of" in err and "got 'furlongs'" in err, err


def test_unknown_units_of_a_collection_built_in_python():
    from fwk.data import MeshCollection
    from fwk.errors import RecipeError

    t = Template(np.eye(3), np.array([[0, 1, 2]]), units="furlongs")
    with pytest.raises(RecipeError, match="'furlongs' is not a unit"):
        MeshCollection(t, ["a"], ["neutral"], np.zeros((1, 1, 3, 3)))
