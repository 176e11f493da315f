"""fwk view: rigs read back from every format alike; the blend and its colours against a naive
sum; --screenshot writes a picture (under Xvfb where it is installed, as in CI) whose colours
follow the displacement."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from fwk.errors import FwkError

from .conftest import grid_obj, neutral

pytest.importorskip("pygltflib", reason="the rig extra: pip install 'fwk[rig]'")
pytest.importorskip("pxr", reason="the rig extra: pip install 'fwk[rig]'")


@pytest.fixture(scope="module")
def rig_dir(grid_run, tmp_path_factory):
    from fwk.apply import apply

    tmp = tmp_path_factory.mktemp("view")
    src = tmp / "anna.obj"
    src.write_text(grid_obj(neutral(np.random.default_rng(4))))
    apply(grid_run, src, tmp / "out", formats="obj,gltf,usda", log=lambda *_: None)
    return src, tmp / "out"


def test_every_format_gives_the_same_rig(rig_dir):
    from fwk.view import load_rig

    src, out = rig_dir
    g = load_rig(out / "anna.glb")
    u = load_rig(out / "anna.usda")
    assert g.names == u.names and g.units == u.units == "cm"
    # the glb's vertices are the OBJ's split at the UV seam: map them back
    assert np.abs(g.deltas - u.deltas[:, g.vertex_of]).max() < 1e-5
    assert np.abs(g.neutral - u.neutral[g.vertex_of]).max() < 1e-5
    objs = sorted(p for p in out.glob("*.obj"))
    folder = out.parent / "objs"
    folder.mkdir(exist_ok=True)
    for p in objs:
        shutil.copy(p, folder / p.name)
    o = load_rig(folder, neutral=src)
    assert sorted(o.names) == sorted(u.names)
    for i, n in enumerate(o.names):
        assert np.abs(o.deltas[i] - u.deltas[u.names.index(n)]).max() < 2e-6
    with pytest.raises(FwkError, match="--neutral"):
        load_rig(folder)


def test_blend_and_colours_against_a_naive_sum(rig_dir):
    from fwk.view import load_rig

    src, out = rig_dir
    rig = load_rig(out / "anna.usda", truth=out)  # the OBJs as their own ground truth: zero error
    w = np.linspace(0.2, 1.0, len(rig.names))
    ref = rig.neutral.copy()
    for i in range(len(rig.names)):
        ref = ref + w[i] * rig.deltas[i]
    assert np.allclose(rig.blend(w), ref)
    err, label = rig.scalars(w)
    assert label == "error (cm)" and err.max() < 1e-5
    rig.truth = None
    disp, label = rig.scalars(w)
    assert label == "displacement (cm)" and np.allclose(disp, np.linalg.norm(ref - rig.neutral, axis=1))
    with pytest.raises(FwkError, match="not in the rig"):
        rig.weights({"nope": 1.0})


def _view(args, tmp_path):
    """``python -m fwk.view ARGS`` (``fwk view`` once cli.py lists it), under xvfb-run when it is
    installed (CI), else as is (open3d's EGL needs no display)."""
    cmd = [sys.executable, "-m", "fwk.view", *map(str, args)]
    if shutil.which("xvfb-run"):
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1280x1024x24", *cmd]
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)


def _yellow(img) -> int:
    """Pixels near the top of viridis (yellow) left of the colour bar: where the displacement is largest."""
    img = img[:, :int(0.80 * img.shape[1])]
    return int(((img[..., 0] > 0.8) & (img[..., 1] > 0.75) & (img[..., 2] < 0.35)).sum())


@pytest.mark.slow
def test_screenshot_shows_the_displacement(rig_dir, tmp_path):
    pytest.importorskip("open3d", reason="the rig extra: pip install 'fwk[rig]'")
    import matplotlib.image as mpimg

    _, out = rig_dir
    r = _view([out, "--screenshot", tmp_path / "sheet.png"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    sheet = mpimg.imread(tmp_path / "sheet.png")
    assert sheet.shape[0] > 200 and sheet.shape[1] > 600
    assert (sheet[..., :3].std(axis=(0, 1)) > 0.05).all()  # not blank
    r1 = _view([out / "anna.glb", "--screenshot", tmp_path / "jaw.png", "--expression", "jawOpen"], tmp_path)
    r0 = _view([out / "anna.glb", "--screenshot", tmp_path / "zero.png", "--weights", "jawOpen=0"], tmp_path)
    assert r1.returncode == 0 and r0.returncode == 0, (r1.stderr[-2000:], r0.stderr[-2000:])
    jaw, zero = mpimg.imread(tmp_path / "jaw.png"), mpimg.imread(tmp_path / "zero.png")
    assert _yellow(jaw) > 50 and _yellow(zero) == 0
    # a fifth of jawOpen: a fifth of the shared scale (no top colour), all of its own
    r_sh = _view([out / "anna.glb", "--screenshot", tmp_path / "fifth.png", "--weights", "jawOpen=0.2"], tmp_path)
    r_pt = _view([out / "anna.glb", "--screenshot", tmp_path / "fifth-own.png", "--weights", "jawOpen=0.2",
                  "--scale", "per-tile"], tmp_path)
    assert r_sh.returncode == 0 and r_pt.returncode == 0, (r_sh.stderr[-2000:], r_pt.stderr[-2000:])
    assert _yellow(mpimg.imread(tmp_path / "fifth.png")) == 0
    assert _yellow(mpimg.imread(tmp_path / "fifth-own.png")) > 50
    bad = _view([out / "anna.glb", "--screenshot", tmp_path / "x.png", "--expression", "smile"], tmp_path)
    assert bad.returncode == 2 and "fwk: error: --expression smile: not in the rig" in bad.stderr


@pytest.mark.skipif(os.environ.get("FWK_TEST_WINDOW") != "1",
                    reason="opens open3d's GUI window: set FWK_TEST_WINDOW=1 on a machine with a GPU "
                           "(its Filament renderer on a software Vulkan did not start within 150 s on 2 cores)")
def test_window_sliders_drive_the_blend(rig_dir):
    from fwk.view import load_rig, open_window

    _, out = rig_dir
    rig = load_rig(out / "anna.glb")
    state = open_window(rig, ticks=3, set_weights={"jawOpen": 1.0})
    assert state["weights"][rig.names.index("jawOpen")] == 1.0
    assert np.isclose(state["max_displacement"], np.linalg.norm(rig.deltas[rig.names.index("jawOpen")], axis=1).max())


def test_tiles_select_by_name_and_pattern_in_order():
    from fwk.view import select_tiles

    names = ["jawOpen", "browDown_L", "browDown_R", "eyeBlink_L", "browInnerUp"]
    assert select_tiles(names, None, 3) == (["jawOpen", "browDown_L"], 5)
    assert select_tiles(names, ["eyeBlink_L", "brow*"], 12) == (
        ["eyeBlink_L", "browDown_L", "browDown_R", "browInnerUp"], 4)
    assert select_tiles(names, ["browDown_?", "*_L"], 12)[0] == ["browDown_L", "browDown_R", "eyeBlink_L"]
    assert select_tiles(names, ["brow*"], 3) == (["browDown_L", "browDown_R"], 3)  # capped, the count kept
    with pytest.raises(FwkError, match=r"--tiles cheek\*: matches no expression of the rig \(expressions: jawOpen,"):
        select_tiles(names, ["jawOpen", "cheek*"], 12)


def test_screenshot_sheet_renders_the_selected_tiles(rig_dir, tmp_path, monkeypatch):
    import fwk.view
    from fwk.view import load_rig, screenshot

    _, out = rig_dir
    rig = load_rig(out / "anna.glb")
    seen = {}

    def fake_render(rig, weights, size=(480, 540), tops=None):  # the weights asked for, no renderer needed
        seen["weights"] = [np.asarray(w) for w in weights]
        return [np.zeros((8, 8, 3)) for _ in weights]

    monkeypatch.setattr(fwk.view, "render_tiles", fake_render)
    pick = [n for n in rig.names if n != rig.names[0]][::-1][:2]
    screenshot(rig, tmp_path / "sheet.png", tiles=pick)
    expected = [np.zeros(len(rig.names))] + [np.eye(len(rig.names))[rig.names.index(n)] for n in pick]
    assert len(seen["weights"]) == 3
    for got, want in zip(seen["weights"], expected):
        np.testing.assert_array_equal(got, want)
    assert (tmp_path / "sheet.png").stat().st_size > 0
    with pytest.raises(FwkError, match="use it without --expression"):
        screenshot(rig, tmp_path / "x.png", weights={pick[0]: 1.0}, tiles=pick)
