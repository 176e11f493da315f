"""Hostile meshes for ``fwk apply`` (issue 25, item 3): a neutral in other units or with a stray
vertex is refused with the measured ratio and the ``--units`` hint (or scaled when ``--units``
asks, the outputs written back in the user's units); OBJ faces whose ``v``/``vt``/``vn`` index
names no line are refused with file and line. Each refusal: exit 2, at most 3 lines on stderr,
no traceback, within 20 s, nothing written (``tests/faults/hostile.py``); the run is not touched.

The run is the rig tests' finished blendshapes run (DT on quad grid heads in cm, with UVs)."""
from __future__ import annotations

import numpy as np
import pytest

from fwk.cli import main
from fwk.data.io import read_obj
from tests.faults.hostile import refused, snapshot
from tests.rig.conftest import grid_obj, grid_run, neutral  # noqa: F401 - grid_run: the rig tests' fixture


@pytest.fixture
def head(tmp_path):
    """A new neutral in the run's units (cm), and a writer of variants of it."""
    V = neutral(np.random.default_rng(21))

    def write(name, X=None, text=None):
        p = tmp_path / name
        p.write_text(text if text is not None else grid_obj(V if X is None else X))
        return p

    return V, write


def _apply_refused(grid_run, tmp_path, path, *expect, extra=()):
    before = snapshot(grid_run)
    err = refused(["--quiet", "apply", str(grid_run), str(path), "--out", str(tmp_path / "out"), *extra], tmp_path,
                  *expect)
    assert not (tmp_path / "out").exists()
    assert snapshot(grid_run) == before
    return err


@pytest.mark.parametrize("scale,expect", [
    (10.0, ["me.obj: 10 times the size of the run's training neutrals (at most 2x either way)",
            "in mm rather than the run's cm? give --units mm"]),
    (0.01, ["me.obj: 0.01 times the size", "give --units m"]),
    (1 / 2.54, ["0.39", "times the size", "in in rather than the run's cm? give --units in"]),  # inches
    (3.7, ["3.7", "times the size", "give its units with --units (the run's are cm;", "or a factor, e.g. --units 0.27"]),
])
def test_a_head_in_other_units_is_refused_with_the_ratio_and_a_hint(grid_run, tmp_path, head, scale, expect):
    V, write = head
    _apply_refused(grid_run, tmp_path, write("me.obj", V * scale), *expect)


def test_stray_and_implausible_vertices(grid_run, tmp_path, head):
    V, write = head
    X = V.copy()
    X[17] = [1e30, 0.0, 0.0]  # line 20: two header lines, then v lines
    _apply_refused(grid_run, tmp_path, write("far.obj", X), "far.obj, line 20: vertex 18 lies at (1e+30, 0, 0)",
                   "beyond ±")
    X = V.copy()
    X[5] += [0.0, 0.0, 200.0]  # 200 cm off a 15 cm head: within the coordinate bound, far from the head
    _apply_refused(grid_run, tmp_path, write("stray.obj", X), "stray.obj, line 8: vertex 6 lies",
                   "a stray vertex?")
    _apply_refused(grid_run, tmp_path, write("moved.obj", V + 1e9), "beyond ±")  # precision lost so far out
    X = V.copy()
    X[3, 2] = np.inf
    _apply_refused(grid_run, tmp_path, write("inf.obj", X), "inf.obj: vertex positions contain NaN or infinite")


def test_a_folder_is_refused_as_a_whole(grid_run, tmp_path, head):
    V, write = head
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.obj").write_text(grid_obj(V))
    (folder / "b.obj").write_text(grid_obj(V * 0.01))  # in metres
    _apply_refused(grid_run, tmp_path, folder, "b.obj: 0.01 times the size", "give --units m")


def test_units_rescale_and_write_back_in_the_users_units(grid_run, tmp_path, head, capsys):
    V, write = head
    ref = tmp_path / "ref"
    assert main(["--quiet", "apply", str(grid_run), str(write("cm.obj", V)), "--out", str(ref)]) == 0
    for units, scale in (("mm", 10.0), ("0.1", 10.0), ("m", 0.01)):
        out = tmp_path / f"out-{units}"
        assert main(["--quiet", "apply", str(grid_run), str(write(f"{units}.obj", V * scale)), "--out", str(out),
                     "--units", units]) == 0, capsys.readouterr().err
        names = sorted(p.name for p in out.iterdir())
        assert names == sorted(p.name for p in ref.iterdir()) and names
        for name in names:
            P, _ = read_obj(out / name)
            R, _ = read_obj(ref / name)
            assert np.allclose(P, R * scale, rtol=1e-6, atol=1e-6 * scale), (units, name)


@pytest.mark.parametrize("units,expect", [
    ("furlongs", "--units 'furlongs': expected a unit (m, cm, mm, um, in, ft) or a factor"),
    ("0", "--units '0': a factor must be a finite number"),
    ("nan", "--units 'nan': a factor must be a finite number"),
    ("-1", "--units '-1': a factor must be"),
    ("mm", "cm.obj: 0.1 times the size of the run's training neutrals after --units mm"),  # the wrong units
])
def test_bad_units(grid_run, tmp_path, head, units, expect):
    V, write = head
    _apply_refused(grid_run, tmp_path, write("cm.obj", V), expect, extra=["--units", units])


def _with_face(text: str, old: int, new: str) -> tuple[str, int]:
    """``text`` with the corner ``old`` of its first face replaced by ``new``; (text, that line)."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith("f "))
    corners = lines[i].split()
    corners[old] = new
    lines[i] = " ".join(corners)
    return "\n".join(lines) + "\n", i + 1


@pytest.mark.parametrize("corner,expect", [
    ("1/999", "a face refers to texture coordinate (vt) 999, but the file has"),
    ("1/0", "a face refers to texture coordinate (vt) 0, but OBJ indices start at 1"),
    ("1/-9999", "a face refers to texture coordinate (vt) -9999, but only"),
    ("1/1/1", "a face refers to normal (vn) 1, but the file has 0"),
    ("0/1", "a face refers to vertex 0, but OBJ indices start at 1"),
    ("99999999999999999999999/1", "a face refers to vertex 99999999999999999999999"),
])
def test_face_indices_that_name_no_line(grid_run, tmp_path, head, corner, expect):
    V, write = head
    text, line = _with_face(grid_obj(V), 1, corner)
    _apply_refused(grid_run, tmp_path, write("bad.obj", text=text), f"bad.obj, line {line}: {expect}")
