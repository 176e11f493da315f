"""fwk apply --naming arkit --only-mapped: exactly the shapes with an ARKit name, in Apple's order,
in the OBJs, the glb and the USD rig (read back by code that shares nothing with the writers);
ICT-FaceKit's 57 shapes give 51 of ARKit's 52 (no tongueOut); without a naming that maps, and
when nothing maps, one line and exit 2 with nothing written."""
from __future__ import annotations

import numpy as np
import pytest

from fwk.errors import FwkError

from .conftest import grid_obj, neutral
from .readers import glb_shapes, read_glb, usd_shapes


def test_ict_facekit_gives_51_of_arkits_52_in_apples_order():
    from fwk_ict_facekit import ICT_BLENDSHAPES

    from fwk.rig.arkit import ARKIT_NAMES, only_mapped_note, rename

    N = np.zeros((3, 3))
    shapes = {n: N + i + 1 for i, n in enumerate(ICT_BLENDSHAPES)}
    out = rename(shapes, N, "arkit", only_mapped=True)
    assert list(out) == [n for n in ARKIT_NAMES if n != "tongueOut"] and len(out) == 51
    # the whole of a split shape is the sum of its halves' deltas; the rest are ICT's shapes renamed
    assert np.array_equal(out["browInnerUp"], shapes["browInnerUp_L"] + shapes["browInnerUp_R"] - N)
    assert np.array_equal(out["cheekPuff"], shapes["cheekPuff_L"] + shapes["cheekPuff_R"] - N)
    assert out["eyeBlinkLeft"] is shapes["eyeBlink_L"] and out["mouthSmileRight"] is shapes["mouthSmile_R"]
    note = only_mapped_note(list(shapes), list(out), "arkit")
    assert note == ("--only-mapped: 51 of ARKit's 52 shapes (none for tongueOut); left out, with no ARKit name: "
                    "browInnerUp_L, browInnerUp_R, cheekPuff_L, cheekPuff_R, cheekRaiser_L, cheekRaiser_R, "
                    "PupilDilate_L, PupilDilate_R")
    # without --only-mapped every shape stays: 57 renamed plus the 2 sums
    assert len(rename(shapes, N, "arkit")) == 59
    # what fwk rig predicts: only the shapes the kept ones come from (53), and they give the same rig
    from fwk.rig.arkit import mapped_sources

    need = mapped_sources(list(shapes), "arkit")
    assert len(need) == 53 and not {"cheekRaiser_L", "cheekRaiser_R", "PupilDilate_L", "PupilDilate_R"} & set(need)
    part = rename({n: shapes[n] for n in need}, N, "arkit", only_mapped=True)
    assert list(part) == list(out) and all(np.array_equal(part[k], out[k]) for k in out)
    with pytest.raises(FwkError, match="only-mapped"):
        mapped_sources(list(shapes), "source")


def test_only_mapped_needs_a_naming_that_maps():
    from fwk.rig.arkit import rename

    N = np.zeros((2, 3))
    with pytest.raises(FwkError, match="--only-mapped keeps the shapes a naming maps: use it with --naming arkit"):
        rename({"jawOpen": N}, N, "source", only_mapped=True)
    with pytest.raises(FwkError, match="--only-mapped: no shape has an ARKit name \\(the shapes: face-x, mine\\)"):
        rename({"face-x": N, "mine": N}, N, "arkit", only_mapped=True)
    # one half alone makes no whole: left out with the rest
    assert list(rename({"cheekPuff_L": N + 1, "jawOpen": N + 2}, N, "arkit", only_mapped=True)) == ["jawOpen"]


def test_apply_only_mapped_writes_exactly_the_arkit_shapes_in_every_format(grid_run, tmp_path):
    pytest.importorskip("pygltflib", reason="the rig extra: pip install 'fwk[rig]'")
    pytest.importorskip("pxr", reason="the rig extra: pip install 'fwk[rig]'")
    from fwk.apply import apply
    from fwk.data.io import read_obj

    V = neutral(np.random.default_rng(21))
    src = tmp_path / "cleo.obj"
    src.write_text(grid_obj(V))
    said = []
    files = apply(grid_run, src, tmp_path / "only", formats="obj,gltf,usd", naming="arkit", only_mapped=True,
                  log=lambda *_: None, say=said.append)
    want = ["jawOpen", "browInnerUp"]  # Apple's order; the run's browInnerUp_L/_R and face-x left out
    assert sorted(f.name for f in files) == sorted([f"{n}.obj" for n in want] + ["cleo.glb", "cleo.usdc"])
    assert said == ["fwk apply --only-mapped: 2 of ARKit's 52 shapes (none for 50 of them); left out, with no "
                    "ARKit name: browInnerUp_L, browInnerUp_R, face-x"]
    doc, _ = read_glb(tmp_path / "only" / "cleo.glb")
    assert doc["meshes"][0]["extras"]["targetNames"] == want and len(doc["meshes"][0]["primitives"][0]["targets"]) == 2
    g, *_ = glb_shapes(tmp_path / "only" / "cleo.glb")
    u, mesh, _ = usd_shapes(tmp_path / "only" / "cleo.usdc")
    assert list(g) == list(u) == ["neutral", *want]
    from pxr import UsdSkel

    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    assert list(binding.GetBlendShapesAttr().Get()) == want and len(binding.GetBlendShapeTargetsRel().GetTargets()) == 2
    # the same shapes as without --only-mapped, in every format
    apply(grid_run, src, tmp_path / "all", formats="obj", naming="arkit", log=lambda *_: None, say=None)
    for n in want:
        X = read_obj(tmp_path / "only" / f"{n}.obj")[0]
        assert np.array_equal(X, read_obj(tmp_path / "all" / f"{n}.obj")[0])
        assert np.abs(g[n] - X).max() < 1e-6 and np.abs(u[n] - X).max() < 1e-6
    assert {p.stem for p in (tmp_path / "all").glob("*.obj")} == {*want, "browInnerUp_L", "browInnerUp_R", "face-x"}


@pytest.mark.parametrize("args, message", [
    (["--only-mapped"], "fwk: error: --only-mapped keeps the shapes a naming maps: use it with --naming arkit "
                        "(--naming source maps no names)"),
    (["--naming", "arkit", "--only-mapped", "--expressions", "face-x"],
     "fwk: error: --only-mapped: no shape has an ARKit name (the shapes: face-x); leave --only-mapped out to keep "
     "them under their own names"),
])
def test_only_mapped_errors_are_one_line_exit_2_with_nothing_written(grid_run, tmp_path, capsys, args, message):
    from fwk.cli import main

    src = tmp_path / "me.obj"
    src.write_text(grid_obj(neutral(np.random.default_rng(2))))
    out = tmp_path / "out"
    assert main(["apply", str(grid_run), str(src), "--out", str(out), "--format", "obj,gltf", *args]) == 2
    err = capsys.readouterr().err.strip()
    assert err == message
    assert not out.exists() and not list(tmp_path.glob(".out.*"))


def test_ict_left_is_the_faces_own_left_as_arkits():
    """ARKit's Left and Right are the face's own (Apple: eyeBlinkRight is the face's right eye).
    ICT-FaceKit's head looks along +z with y up, so the face's own left is +x: each _L shape
    moves the +x side and its _R twin the -x side, and the renaming (_L -> Left, no mirroring)
    keeps the side."""
    from fwk.data.io import read_obj
    from fwk.rig.arkit import ICT_TO_ARKIT
    from fwk.testing import ICT_SKIP_REASON, ict_path

    ict = ict_path()
    if ict is None:
        pytest.skip(ICT_SKIP_REASON)
    N = read_obj(ict / "generic_neutral_mesh.obj")[0]
    assert N[np.argmax(N[:, 2]), 0] == 0.0 and N[:, 2].max() > 10  # the nose tip: on the midline, at +z
    for left in ("eyeBlink_L", "mouthSmile_L", "browDown_L"):
        assert ICT_TO_ARKIT[left].endswith("Left") and ICT_TO_ARKIT[left[:-1] + "R"].endswith("Right")
        for name, sign in ((left, 1), (left[:-1] + "R", -1)):
            d = np.linalg.norm(read_obj(ict / f"{name}.obj")[0] - N, axis=1)
            assert sign * (d @ N[:, 0]) / d.sum() > 2.0, name  # the displacement's centre: 2+ cm to that side
