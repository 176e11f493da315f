import json

import numpy as np
import pytest

from fwk.cli import main
from fwk.data import Template
from fwk.data.io import write_obj
from fwk.testing import ICT_SKIP_REASON, ict_path
from fwk.testing.metric import small_mesh


def test_eval_two_meshes_json(tmp_path, capsys):
    V, t = small_mesh()
    write_obj(tmp_path / "a.obj", V + 0.01, t)
    write_obj(tmp_path / "b.obj", V, t)
    assert main(["eval", str(tmp_path / "a.obj"), str(tmp_path / "b.obj"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r) == {"l1", "l2", "euclidean", "dame", "fmpd"}
    assert r["l1"]["mean"] == pytest.approx(0.01)
    assert r["dame"]["mean"] == pytest.approx(0, abs=1e-7)  # a translation (OBJ keeps 9 digits)


def test_eval_folders_and_maps(tmp_path, capsys):
    V, t = small_mesh()
    for d, off in (("pred", 0.02), ("gt", 0.0)):
        for name in ("x/one.obj", "two.obj"):
            write_obj(tmp_path / d / name, V + off, t)
    write_obj(tmp_path / "gt" / "only_here.obj", V, t)
    assert main(["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--maps", str(tmp_path / "maps")]) == 0
    cap = capsys.readouterr()
    assert "2 mesh pair(s)" in cap.out and "dame" in cap.out
    assert "only_here.obj" in cap.err and "skipped" in cap.err
    maps = sorted((tmp_path / "maps").glob("*.npz"))
    assert [p.name for p in maps] == ["two.obj.npz", "x__one.obj.npz"]
    z = np.load(maps[0], allow_pickle=False)
    assert set(z.files) == {"l1", "l2", "euclidean", "dame", "fmpd"} and z["l1"].shape == (len(V),)
    assert np.allclose(z["l1"], 0.02)


def test_eval_same_count_different_faces(tmp_path, capsys):
    V, t = small_mesh()
    write_obj(tmp_path / "a.obj", V, t)
    F = t.triangles.copy()
    F[3] = F[3][[1, 2, 0]][::-1]  # same vertices, opposite orientation
    write_obj(tmp_path / "b.obj", V, Template(V, F))
    assert main(["eval", str(tmp_path / "a.obj"), str(tmp_path / "b.obj")]) == 2
    err = capsys.readouterr().err
    assert "a.obj" in err and "b.obj" in err and "triangle 3" in err


def test_eval_errors_name_files(tmp_path, capsys):
    V, t = small_mesh()
    write_obj(tmp_path / "a.obj", V, t)
    other = Template(V[:-1], t.triangles[t.triangles.max(1) < len(V) - 1])
    write_obj(tmp_path / "b.obj", other.vertices, other)
    assert main(["eval", str(tmp_path / "a.obj"), str(tmp_path / "b.obj")]) == 2
    err = capsys.readouterr().err
    assert "a.obj" in err and "b.obj" in err
    assert main(["eval", str(tmp_path / "a.obj"), str(tmp_path / "missing.obj")]) == 2
    assert "missing.obj" in capsys.readouterr().err
    (tmp_path / "bad.obj").write_text("v 1 2\nf 1 2 3\n")
    assert main(["eval", str(tmp_path / "bad.obj"), str(tmp_path / "a.obj")]) == 2
    assert "bad.obj" in capsys.readouterr().err


def test_eval_ict_meshes(tmp_path, capsys):
    folder = ict_path()
    if folder is None:
        pytest.skip(ICT_SKIP_REASON)
    assert main(["eval", str(folder / "identity000.obj"), str(folder / "generic_neutral_mesh.obj"), "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert set(r) == {"l1", "l2", "euclidean", "dame", "fmpd"}
    assert all(np.isfinite(v["mean"]) and v["mean"] > 0 for v in r.values())


def test_report_rebuild_and_combine(tmp_path, capsys):
    from fwk.evaluation.cli_report import _Dir
    from fwk.evaluation.report import write_report

    for name, v in (("a", 0.001), ("b", 0.002)):
        ctx = _Dir(tmp_path / name)
        write_report(ctx, name, {"models": {"pca": {"test": {"l1": {"mean": v}, "dame": {"mean": 2 * v}}}}})
    (tmp_path / "a" / "report.md").unlink()
    assert main(["report", str(tmp_path / "a")]) == 0
    assert (tmp_path / "a" / "report.md").exists()
    assert main(["report", str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "c")]) == 0
    text = (tmp_path / "c" / "report.md").read_text()
    assert "a:pca" in text and "b:pca" in text and "scatter" in text
    assert main(["report", str(tmp_path / "nothing")]) == 2
