"""fwk view --pick: landmark pairs picked on the template and on a head of another topology,
written in the schema fwk.rig.register.read_landmarks reads. The windows are
``fwk.view.pick_points``, replaced here by a fake that returns the clicks a user would make
(the real one is exercised with a stand-in open3d: its point cloud, its window and its refusals)."""
from __future__ import annotations

import json
import os
import types
from pathlib import Path

import numpy as np
import pytest

import fwk.view
from fwk.errors import FwkError
from fwk.rig.register import read_landmarks

from .conftest import grid_obj, neutral

TEMPLATE_IDS = [9, 14, 27, 40, 52, 60, 33]  # 7 well spread vertices of the 8 x 8 grid
SCAN_IDS = [70, 3, 41, 18, 55, 7, 29]


@pytest.fixture()
def meshes(tmp_path):
    """(run folder holding template.obj, the template .obj, a scan .obj of another vertex count)."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "template.obj").write_text(grid_obj(neutral(np.random.default_rng(0))))
    rng = np.random.default_rng(1)
    extra = rng.standard_normal((20, 3))  # more vertices than the template: another topology
    scan = tmp_path / "head.obj"
    scan.write_text(grid_obj(neutral(rng), extra_v=extra))
    return run, run / "template.obj", scan


class Clicks:
    """A stand-in for ``pick_points``: returns one list of clicks per window, records the windows."""

    def __init__(self, *picks):
        self.picks = list(picks)
        self.windows = []

    def __call__(self, mesh_path, title):
        self.windows.append((str(mesh_path), title))
        return list(self.picks.pop(0))


def test_picks_are_written_in_order_and_read_back(meshes, tmp_path, monkeypatch, capsys):
    run, tpl, scan = meshes
    clicks = Clicks(TEMPLATE_IDS, SCAN_IDS)
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    out = tmp_path / "new" / "lm.json"
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(run)]) == 0
    assert [w[0] for w in clicks.windows] == [str(tpl), str(scan)]  # the template first, then the scan
    data = json.loads(out.read_text())
    assert data == {"landmarks": [{"template": t, "scan": s} for t, s in zip(TEMPLATE_IDS, SCAN_IDS)]}
    V = fwk.view.read_obj(scan)[0]
    ids, points = read_landmarks(out, 64, V)  # what fwk register reads
    assert ids.tolist() == TEMPLATE_IDS and np.array_equal(points, V[SCAN_IDS])
    said = capsys.readouterr().out
    # the instructions: the suggested 10 points as a numbered list, before the template's window
    for k, (name, _) in enumerate(fwk.view.RIGGER_POINTS):
        assert f"{k + 1:2d}. {name}:" in said
    assert said.index("window 1 of 2") < said.index("window 2 of 2") < said.index(f"wrote {out}")
    assert "the same 7 points in the same order" in said


def test_a_template_obj_and_ten_picks_name_the_points_for_the_scan(meshes, tmp_path, monkeypatch, capsys):
    run, tpl, scan = meshes
    ten = list(range(0, 60, 6))
    monkeypatch.setattr(fwk.view, "pick_points", Clicks(ten, [i + 1 for i in ten]))
    out = tmp_path / "lm.json"
    fwk.view.pick_landmarks(scan, out, tpl)
    assert [d["template"] for d in json.loads(out.read_text())["landmarks"]] == ten
    scan_part = capsys.readouterr().out.split("window 2 of 2")[1]
    assert " 1. eye inner right" in scan_part and "10. chin" in scan_part


@pytest.mark.parametrize("form", ["list", "names", "landmark file"])
def test_template_landmarks_skip_the_first_window(meshes, tmp_path, monkeypatch, capsys, form):
    run, tpl, scan = meshes
    names = [f"point {k}" for k in range(len(TEMPLATE_IDS))]
    given = {"list": TEMPLATE_IDS, "names": dict(zip(names, TEMPLATE_IDS)),
             "landmark file": {"landmarks": [{"template": t, "scan": 0} for t in TEMPLATE_IDS]}}[form]
    t_json = tmp_path / "t.json"
    t_json.write_text(json.dumps(given))
    clicks = Clicks(SCAN_IDS)
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    out = tmp_path / "lm.json"
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(run), "--template-landmarks",
                          str(t_json)]) == 0
    assert [w[0] for w in clicks.windows] == [str(scan)]  # one window: the scan
    ids, _ = read_landmarks(out, 64, fwk.view.read_obj(scan)[0])
    assert ids.tolist() == TEMPLATE_IDS
    said = capsys.readouterr().out
    assert (" 7. point 6" in said) == (form == "names")


@pytest.mark.parametrize("template, scan, message", [
    ([], None, "no point picked on the template"),
    ([1, 2, 3, 4], None, "4 point(s) picked on the template, at least 5"),
    ([1, 2, 3, 2, 5], None, "points 2 and 4 on the template are the same vertex 2"),
    (TEMPLATE_IDS, [], "no point picked on the scan"),
    (TEMPLATE_IDS, SCAN_IDS[:-1], "7 points on the template but 6 on the scan"),
    (TEMPLATE_IDS, SCAN_IDS[:-1] + [SCAN_IDS[0]], "points 1 and 7 on the scan are the same vertex 70"),
])
def test_bad_picks_are_one_line_errors_and_write_nothing(meshes, tmp_path, monkeypatch, capsys, template, scan,
                                                          message):
    run, tpl, scan_obj = meshes
    clicks = Clicks(template, scan if scan is not None else [])
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    out = tmp_path / "lm.json"
    assert fwk.view.main([str(scan_obj), "--pick", str(out), "--template", str(run)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert len(clicks.windows) == (1 if scan is None else 2)  # a bad template pick: no scan window
    assert not out.exists()


@pytest.mark.parametrize("case, message", [
    ("out is a folder", "a folder; give the landmark file"),
    ("a file in the way", "a file, not a folder"),
    ("no template", "no template.obj in it"),
    ("template not obj", "not a .json file"),
    ("scan not obj", "not an .obj"),
    ("bad template landmarks", "landmark 2: 9999 is not a template vertex id"),
    ("few template landmarks", "3 point(s) picked in --template-landmarks"),
    ("no --template", "--template RUN"),
    ("with --screenshot", "--screenshot belong to viewing a rig"),
])
def test_refusals_before_any_window(meshes, tmp_path, monkeypatch, capsys, case, message):
    run, tpl, scan = meshes
    clicks = Clicks(TEMPLATE_IDS, SCAN_IDS)
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    out, template, extra, path = tmp_path / "lm.json", str(run), [], str(scan)
    if case == "out is a folder":
        out = tmp_path
    elif case == "a file in the way":
        (tmp_path / "file").write_text("x")
        out = tmp_path / "file" / "lm.json"
    elif case == "no template":
        template = str(tmp_path / "new")
        (tmp_path / "new").mkdir()
    elif case == "template not obj":
        template = str(tmp_path / "t.json")
        (tmp_path / "t.json").write_text("[]")
    elif case == "scan not obj":
        path = str(tpl.with_suffix(".ply"))
        tpl.with_suffix(".ply").write_text("ply")
    elif case in ("bad template landmarks", "few template landmarks"):
        (tmp_path / "t.json").write_text(json.dumps([1, 9999, 3, 4, 5] if case.startswith("bad") else [1, 2, 3]))
        extra = ["--template-landmarks", str(tmp_path / "t.json")]
    elif case == "with --screenshot":
        extra = ["--screenshot", str(tmp_path / "x.png")]
    args = [path, "--pick", str(out)] + (["--template", template] if case != "no --template" else []) + extra
    assert fwk.view.main(args) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert clicks.windows == []


def test_template_without_pick_is_refused(meshes, capsys):
    run, tpl, scan = meshes
    assert fwk.view.main([str(scan), "--template", str(run)]) == 2
    assert "go with --pick" in capsys.readouterr().err


def test_no_display_says_a_real_one_is_needed(meshes, monkeypatch):
    run, tpl, scan = meshes
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(fwk.view.sys, "platform", "linux")
    with pytest.raises(FwkError, match="no display.*xvfb-run is not enough for picking"):
        fwk.view.pick_points(tpl, "t")


def _fake_open3d(window_opens=True, picked=(5, 2, 9)):
    """A stand-in for open3d's module: records the point cloud shown and returns ``picked``."""
    seen = {}

    class Cloud:
        def __init__(self, points):
            self.points = points
            seen["cloud"] = self

        def paint_uniform_color(self, c):
            self.colour = c

    class Vis:
        def create_window(self, window_name, width, height):
            seen["title"] = window_name
            return window_opens

        def add_geometry(self, g):
            return True

        def get_render_option(self):
            return types.SimpleNamespace()

        def run(self):
            seen["ran"] = True

        def destroy_window(self):
            seen["destroyed"] = True

        def get_picked_points(self):
            return list(picked)

    o3d = types.SimpleNamespace(geometry=types.SimpleNamespace(PointCloud=Cloud),
                                utility=types.SimpleNamespace(Vector3dVector=np.asarray),
                                visualization=types.SimpleNamespace(VisualizerWithEditing=Vis))
    return o3d, seen


def test_pick_points_shows_the_vertices_in_obj_order(meshes, monkeypatch):
    run, tpl, scan = meshes
    monkeypatch.setenv("DISPLAY", ":0")
    o3d, seen = _fake_open3d()
    monkeypatch.setattr(fwk.view, "_o3d", lambda: o3d)
    assert fwk.view.pick_points(scan, "pick here") == [5, 2, 9]
    assert np.array_equal(seen["cloud"].points, fwk.view.read_obj(scan)[0])  # ids = the OBJ's v order
    assert seen["cloud"].normals.shape == seen["cloud"].points.shape
    assert seen["title"] == "pick here" and seen["ran"] and seen["destroyed"]


def test_a_window_that_cannot_open_is_one_line(meshes, monkeypatch):
    run, tpl, scan = meshes
    monkeypatch.setenv("DISPLAY", ":0")
    o3d, seen = _fake_open3d(window_opens=False)
    monkeypatch.setattr(fwk.view, "_o3d", lambda: o3d)
    with pytest.raises(FwkError, match="could not open a window.*real display"):
        fwk.view.pick_points(tpl, "t")
    assert "ran" not in seen


def test_a_write_that_fails_after_picking_is_one_line(meshes, tmp_path, monkeypatch, capsys):
    run, tpl, scan = meshes
    monkeypatch.setattr(fwk.view, "pick_points", Clicks(TEMPLATE_IDS, SCAN_IDS))

    def refuse(self, *args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(fwk.view.Path, "write_text", refuse)
    out = tmp_path / "lm.json"
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(run)]) == 2
    err = capsys.readouterr().err
    assert f"--pick {out}: cannot be written (Permission denied)" in err and err.count("\n") == 1


def _packed_model(V, t, folder: Path) -> Path:
    """A minimal rig model folder as fwk pack writes one: a card and its template (``t``'s triangles
    on the vertices ``V``) in stats/template.npz."""
    (folder / "stats").mkdir(parents=True)
    (folder / "card.json").write_text("{}")
    np.savez(folder / "stats" / "template.npz", triangles=t.triangles, n_vertices=np.int64(len(V)), mean_neutral=V)
    return folder


def test_a_packed_rig_model_gives_its_template_to_pick_on(meshes, tmp_path, monkeypatch):
    """--template with a rig model (a folder fwk pack wrote, which keeps no template.obj, or a
    shipped model's name): the window opens on its template's triangles on its mean neutral,
    written to a temporary OBJ, and the ids picked there are the model's; a damaged template
    is one line naming the file."""
    from fwk.data.io import read_obj
    from fwk.rig.shipped import shipped

    run, tpl, scan = meshes
    V, t = read_obj(tpl)
    packed = _packed_model(V, t, tmp_path / "packed")
    got = fwk.view.template_obj(packed)
    V2, t2 = read_obj(got)
    assert np.allclose(V2, V) and np.array_equal(t2.triangles, t.triangles)
    clicks = types.SimpleNamespace(windows=[])

    def fake_pick(path, title):
        clicks.windows.append((str(path), title))
        return TEMPLATE_IDS if len(clicks.windows) == 1 else SCAN_IDS

    monkeypatch.setattr(fwk.view, "pick_points", fake_pick)
    out = tmp_path / "lm.json"
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(packed)]) == 0
    assert [d["template"] for d in json.loads(out.read_text())["landmarks"]] == TEMPLATE_IDS
    np.savez(packed / "stats" / "template.npz", triangles=t.triangles[:, :2], mean_neutral=V)
    with pytest.raises(FwkError, match="is not a rig model's template"):
        fwk.view.template_obj(packed)
    if "ict-face" in shipped():
        V3, t3 = read_obj(fwk.view.template_obj("ict-face"))
        assert V3.shape == (11248, 3) and len(t3.triangles) == 22288


def test_a_packed_models_temporary_template_is_removed_when_the_process_ends(tmp_path):
    """fwk view --pick --template MODEL writes the model's template to a temporary OBJ for the
    picking window; the process removes it as it ends (it left 1 MB in the temp folder before)."""
    import subprocess
    import sys

    from fwk.rig.shipped import shipped

    if "ict-face" not in shipped():
        pytest.skip("no shipped rig model in this install")
    code = "import fwk.view; p = fwk.view.template_obj('ict-face'); print(p, p.exists())"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "TMPDIR": str(tmp_path)})
    path, existed = out.stdout.split()
    assert out.returncode == 0 and existed == "True", out.stderr[-2000:]
    assert not Path(path).exists() and not Path(path).parent.exists() and not list(tmp_path.iterdir())


def test_a_model_with_its_own_landmarks_opens_the_heads_window_only(meshes, tmp_path, monkeypatch, capsys):
    """A rig model folder with ``landmarks.json`` (fwk.rig.shipped.LANDMARKS) gives the template's
    side: one window, the head's, the points named in the file's order; --template-landmarks wins."""
    from fwk.data.io import read_obj

    run, tpl, scan = meshes
    V, t = read_obj(tpl)
    packed = _packed_model(V, t, tmp_path / "packed")
    names = [f"point {k}" for k in range(len(TEMPLATE_IDS))]
    (packed / "landmarks.json").write_text(json.dumps(dict(zip(names, TEMPLATE_IDS))))
    clicks = Clicks(SCAN_IDS)
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    out = tmp_path / "lm.json"
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(packed)]) == 0
    assert [w[0] for w in clicks.windows] == [str(scan)]
    assert [d["template"] for d in json.loads(out.read_text())["landmarks"]] == TEMPLATE_IDS
    said = capsys.readouterr().out
    assert "the model's own template landmarks" in said and " 7. point 6" in said
    other = tmp_path / "t.json"
    other.write_text(json.dumps(TEMPLATE_IDS[::-1]))
    clicks = Clicks(SCAN_IDS)
    monkeypatch.setattr(fwk.view, "pick_points", clicks)
    assert fwk.view.main([str(scan), "--pick", str(out), "--template", str(packed), "--template-landmarks",
                          str(other)]) == 0
    assert [d["template"] for d in json.loads(out.read_text())["landmarks"]] == TEMPLATE_IDS[::-1]


def test_the_shipped_models_landmarks_are_the_rigger_points_on_its_template():
    """ict-face's landmarks.json: the 10 rigger points (fwk.view.RIGGER_POINTS, in that order), the
    rig tests' RIGGER_LANDMARKS (which their geometric rule finds on ICT-FaceKit's face-head template,
    tests/rig/test_register.py), on a template of that very topology (checked against ICT-FaceKit's
    own triangles when the data is here)."""
    from fwk.data.io import read_obj
    from fwk.rig.shipped import LANDMARKS, shipped

    from .test_register import ICT, RIGGER_LANDMARKS, _rigger_landmarks

    if "ict-face" not in shipped():
        pytest.skip("no shipped rig model in this install")
    lm = json.loads((shipped()["ict-face"] / LANDMARKS).read_text())
    assert list(lm) == [name for name, _ in fwk.view.RIGGER_POINTS]
    assert lm == RIGGER_LANDMARKS
    V, t = read_obj(fwk.view.template_obj("ict-face"))
    assert len(V) == 11248 and max(lm.values()) < len(V)
    if ICT is not None:
        from fwk.plugins import get_registry

        data = get_registry().get("dataset", "ict-facekit")(path=str(ICT), region="face-head", n_subjects=1,
                                                             shapes=["neutral"]).load()
        assert np.array_equal(np.asarray(data.template.triangles), t.triangles)
        assert _rigger_landmarks(data.template.vertices, data.template.triangles) == lm
