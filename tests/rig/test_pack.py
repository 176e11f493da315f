"""fwk pack and fwk rig: a rig model folder from a finished blendshapes run (the packed model
predicts as the run's did, its card says what it is), a rig from it with no run directory, and the
rig model that ships with fwk (fwk/shipped/ict-face): under 20 MB, no pickle, 51 ARKit shapes."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from fwk.cli import main
from fwk.errors import FwkError
from fwk.lifecycle import open_run
from fwk.pack import CARD, MAX_PACK_ERROR, find_model, pack, shipped
from fwk.safeio import is_pickle, load_npz, load_state

from .readers import glb_shapes
from .test_apply_rig import _validate, _validator


def _mean_obj(folder, path):
    """The model's mean training neutral (its units) as an OBJ of its topology."""
    V = np.asarray(load_npz(folder / "stats" / "preprocess.npz")["mean_centred"])
    F = np.asarray(load_npz(folder / "stats" / "template.npz")["triangles"])
    path.write_text("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    return V


@pytest.fixture(scope="module")
def packed(shippable_rig_run, tmp_path_factory):
    licence = tmp_path_factory.mktemp("lic") / "LICENSE-data.txt"
    licence.write_text("the data's licence\n")
    out = tmp_path_factory.mktemp("packed") / "face"
    lines = []
    pack(shippable_rig_run, out, include=[licence], log=lines.append)
    return shippable_rig_run, out, lines


def test_pack_writes_a_smaller_model_that_predicts_as_the_run(packed):
    run_dir, out, lines = packed
    assert "predicts within" in lines[0]
    full = (run_dir / "models" / "pbs.safetensors").stat().st_size
    small = (out / "models" / "pbs.safetensors").stat().st_size
    assert small < full
    assert not is_pickle((out / "models" / "pbs.safetensors").read_bytes()[:9])
    a, b = open_run(run_dir), open_run(out)
    m, p = a.model("pbs"), b.model("pbs")
    st = load_state(out / "models" / "pbs.safetensors")
    n = m.shape[0]
    K = max([k for k in m.k.values() if 0 < k < n], default=0)
    assert st["sweep"] == {} and p.k == m.k
    if K:  # the basis cut at the largest chosen k below n
        assert st["assembler"]["U"].shape == (n, K) and st["assembler"]["U"].dtype == np.float32
    assert "neutral" in st["anchor"] and "src" not in st["anchor"]  # the mean neutral stored once
    col = np.load(run_dir / "stats" / "template.npz")["mean_neutral"][None]
    rng = np.random.default_rng(1)
    N = col + 0.01 * rng.standard_normal((3, *col.shape[1:]))  # heads near the mean, registered space
    want, got = m.predict_all(N, m.expressions), p.predict_all(N, m.expressions)
    for e in m.expressions:
        disp = np.abs(want[e] - N).max()
        assert np.abs(got[e] - want[e]).max() <= MAX_PACK_ERROR * disp, e


def test_card_says_what_the_model_is(packed):
    run_dir, out, _ = packed
    card = json.loads((out / CARD).read_text())
    split = json.loads((run_dir / "split.json").read_text())
    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert card["model"] == "pbs" and card["recipe"] == "smoke-rig-shippable"
    assert card["identities"] == split
    assert card["epochs"]["pbs"]["epochs_run"] == 3
    assert card["included"] == ["LICENSE-data.txt"] and (out / "LICENSE-data.txt").read_text() == "the data's licence\n"
    for e in metrics["expressions"]:
        for label in ("pbs", "dt"):
            want = metrics["blendshapes"][e][label]["l1"]
            assert card["test"][e][label]["l1"] == {"mean": pytest.approx(want["mean_input"]), "units": "cm"}
    assert card["pack"]["largest_difference"] <= MAX_PACK_ERROR * card["pack"]["largest_displacement"]


def test_show_rig_prints_the_card_table(packed, capsys):
    _, out, _ = packed
    assert main(["show", "rig", str(out)]) == 0
    text = capsys.readouterr().out
    assert "pbs against dt" in text and "test: lower than dt on L1" in text
    for e in ("face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"):
        assert e in text


def test_rig_from_a_packed_model_equals_apply_on_the_run(packed, tmp_path, capsys):
    run_dir, out, _ = packed
    V = _mean_obj(out, tmp_path / "head.obj")
    assert main(["rig", str(tmp_path / "head.obj"), "--model", str(out), "--out", str(tmp_path / "rig"),
                 "--naming", "source"]) == 0
    assert main(["apply", str(run_dir), str(tmp_path / "head.obj"), "--out", str(tmp_path / "ref")]) == 0
    from fwk.data.io import read_obj

    names = sorted(p.name for p in (tmp_path / "ref").glob("*.obj"))
    assert names and names == sorted(p.name for p in (tmp_path / "rig").glob("*.obj"))
    size = np.ptp(V, axis=0).max()
    for name in names:
        a, _ = read_obj(tmp_path / "rig" / name)
        b, _ = read_obj(tmp_path / "ref" / name)
        assert np.abs(a - b).max() < 1e-4 * size, name
    assert (tmp_path / "rig" / "head.glb").is_file() and (tmp_path / "rig" / "head.usdc").is_file()
    assert "fwk rig:" in capsys.readouterr().out


def test_pack_and_rig_refusals(packed, tmp_path):
    run_dir, out, _ = packed
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(FwkError, match="not an empty folder"):
        pack(run_dir, tmp_path / "full")
    with pytest.raises(FwkError, match="--include"):
        pack(run_dir, tmp_path / "new", include=[tmp_path / "nope.txt"])
    assert not (tmp_path / "new").exists()
    (tmp_path / "card.json").write_text("{}")
    with pytest.raises(FwkError, match="name is taken"):
        pack(run_dir, tmp_path / "new", include=[tmp_path / "card.json"])
    with pytest.raises(FwkError, match="--model nope"):
        find_model("nope")
    with pytest.raises(FwkError, match="not a model of"):
        pack(run_dir, tmp_path / "new2", model="nope")
    assert not (tmp_path / "new2").exists()


def test_a_packed_model_opens_read_only(packed, tmp_path):
    """A shipped model sits in site-packages, perhaps read-only: fwk rig writes nothing into it."""
    _, out, _ = packed
    ro = tmp_path / "ro"
    shutil.copytree(out, ro)
    before = sorted(p.relative_to(ro) for p in ro.rglob("*"))
    for p in [ro, *ro.rglob("*")]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    try:
        _mean_obj(ro, tmp_path / "head.obj")
        assert main(["rig", str(tmp_path / "head.obj"), "--model", str(ro), "--out", str(tmp_path / "rig"),
                     "--naming", "source", "--format", "obj"]) == 0
    finally:
        for p in [ro, *ro.rglob("*")]:
            p.chmod(0o755 if p.is_dir() else 0o644)
    assert sorted(p.relative_to(ro) for p in ro.rglob("*")) == before


# ----------------------------------------------------------------------------- the shipped model

SHIPPED = shipped()


@pytest.mark.skipif("ict-face" not in SHIPPED, reason="this checkout ships no ict-face rig model")
def test_the_shipped_model_is_small_safe_and_licensed():
    folder = SHIPPED["ict-face"]
    for p in folder.rglob("*"):
        if p.is_file():
            assert p.stat().st_size <= 20_000_000, p
    model = folder / "models" / "pbs-dt.safetensors"
    assert not is_pickle(model.read_bytes()[:9])
    assert isinstance(load_state(model), dict)  # safetensors + JSON, verified, never unpickled
    card = json.loads((folder / CARD).read_text())
    assert {"LICENSE-ICT-FaceKit.txt", "ATTRIBUTION.md"} <= set(card["included"])
    assert "MIT" in (folder / "LICENSE-ICT-FaceKit.txt").read_text()
    assert len(card["test"]) == 57 and card["identities"]["test"]


@pytest.mark.skipif("ict-face" not in SHIPPED, reason="this checkout ships no ict-face rig model")
def test_apply_takes_a_shipped_models_name_as_its_run(tmp_path, monkeypatch, capsys):
    """fwk apply ict-face HEAD.obj (and fwk register --template ict-face: the same reopening) uses
    the shipped model; a folder of that name in the working directory wins, for fwk apply and for
    fwk rig --model alike (fwk rig without --model still takes the shipped default)."""
    from fwk.data.io import read_obj

    folder = SHIPPED["ict-face"]
    _mean_obj(folder, tmp_path / "head.obj")
    monkeypatch.chdir(tmp_path)
    assert main(["apply", "ict-face", "head.obj", "--out", "a", "--expressions", "jawOpen", "eyeBlink_L"]) == 0
    assert main(["rig", "head.obj", "--out", "r", "--naming", "source", "--all-shapes", "--format", "obj",
                 "--expressions", "jawOpen", "eyeBlink_L"]) == 0
    for e in ("jawOpen", "eyeBlink_L"):
        assert np.array_equal(read_obj(tmp_path / "a" / f"{e}.obj")[0], read_obj(tmp_path / "r" / f"{e}.obj")[0])
    (tmp_path / "ict-face").mkdir()  # not a run: refused as a path, not taken for the shipped model
    assert main(["apply", "ict-face", "head.obj", "--out", "b"]) == 2
    assert main(["rig", "head.obj", "--out", "b", "--model", "ict-face"]) == 2  # fwk rig alike
    assert "is neither a folder written by fwk pack nor a run" in capsys.readouterr().err
    assert main(["rig", "head.obj", "--out", "c", "--format", "obj", "--expressions", "jawOpen"]) == 0  # the default


@pytest.mark.skipif("ict-face" not in SHIPPED, reason="this checkout ships no ict-face rig model")
def test_fwk_list_shows_the_shipped_model_as_a_row(capsys):
    """fwk list: one row per component, the shipped rig models among them (kind rig) with what they
    were trained on and their test counts against their run's baselines; --kind rig alone."""
    assert main(["list", "--kind", "rig"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert rows[0].split()[:2] == ["name", "kind"] and rows[1].split()[:3] == ["ict-face", "rig", "fwk"]
    for word in ("rig_ict_shipped", "identities train 24 / val 8 / test 8", "epochs", "commit",
                 "test: lower than dt on L1"):
        assert word in rows[1], word
    assert main(["list"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert all(line.split() for line in out)  # no blank line: every line after the header is a row
    assert any(line.split()[:2] == ["ict-face", "rig"] for line in out)


@pytest.mark.skipif("ict-face" not in SHIPPED, reason="this checkout ships no ict-face rig model")
def test_rig_with_the_shipped_model_writes_51_arkit_shapes(tmp_path, capsys):
    from fwk.rig.arkit import ARKIT_NAMES

    folder = SHIPPED["ict-face"]
    _mean_obj(folder, tmp_path / "head.obj")
    assert main(["rig", str(tmp_path / "head.obj"), "--out", str(tmp_path / "rig")]) == 0
    objs = sorted(p.stem for p in (tmp_path / "rig").glob("*.obj"))
    assert len(objs) == 51 and set(objs) <= set(ARKIT_NAMES)
    shapes = glb_shapes(tmp_path / "rig" / "head.glb")[0]
    assert sorted(k for k in shapes if k != "neutral") == objs
    if _validator() is not None:
        report = _validate(tmp_path / "rig" / "head.glb")
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]


@pytest.mark.skipif("ict-face" not in SHIPPED, reason="this checkout ships no ict-face rig model")
def test_shipped_model_rigs_a_held_out_ict_head(tmp_path, capsys):
    """A test identity of the shipped model's own split (never trained on), its full 26,719-vertex
    ICT-FaceKit head through ``fwk rig`` (defaults: OBJ, glb, USD, the 51 ARKit shapes): jawOpen
    moves the lower teeth within 20 % of the identity's true jawOpen displacement there, the upper
    teeth stay still and the skull top moves by less than 2 % of the lower teeth's mean motion
    (what the model's region predicts there); the time is printed (the issue's target, 10 s on 2
    cores, is a benchmark's: ``fwk rig`` prints its own timing)."""
    import time

    from fwk.data.io import read_obj, write_obj
    from fwk.plugins import get_registry
    from fwk.testing import ICT_SKIP_REASON, ict_path

    from .test_follow import N_REGION, TEETH

    ict = ict_path()
    if ict is None:
        pytest.skip(ICT_SKIP_REASON)
    card = json.loads((SHIPPED["ict-face"] / CARD).read_text())
    subject = card["identities"]["test"][0]
    n_subjects = len([s for ids in card["identities"].values() for s in ids])
    full = get_registry().get("dataset", "ict-facekit")(path=str(ict), region="full", n_subjects=n_subjects,
                                                         shapes=["neutral", "jawOpen"]).load()
    P = np.asarray(full.positions[full.subjects.index(subject)])
    write_obj(tmp_path / "head.obj", P[0], full.template)
    t0 = time.perf_counter()
    assert main(["rig", str(tmp_path / "head.obj"), "--out", str(tmp_path / "rig")]) == 0
    seconds = time.perf_counter() - t0
    assert len(list((tmp_path / "rig").glob("*.obj"))) == 51
    got = read_obj(tmp_path / "rig" / "jawOpen.obj")[0]
    generic = read_obj(ict / "jawOpen.obj")[0] - read_obj(ict / "generic_neutral_mesh.obj")[0]
    teeth = np.arange(*TEETH)
    moving = np.linalg.norm(generic[teeth], axis=1) > 0.1
    lower, upper = teeth[moving], teeth[~moving]
    true, pred = P[1] - P[0], got - P[0]
    rel = np.linalg.norm(pred[lower] - true[lower]) / np.linalg.norm(true[lower])
    mean_true = np.linalg.norm(true[lower], axis=1).mean()
    top = np.flatnonzero(P[0, :N_REGION, 1] > P[0, lower, 1].max() + 14.0)
    up_move = np.linalg.norm(pred[upper], axis=1).max()
    top_move = np.linalg.norm(pred[top], axis=1).max()
    print(f"fwk rig {subject}: {seconds:.1f} s in-process; lower teeth rel {rel:.4f} (mean true {mean_true:.3f} cm); "
          f"upper teeth max {up_move:.2e} cm; skull top max {top_move:.2e} cm")
    assert rel < 0.2, f"lower teeth: relative error {rel:.3f} (true mean displacement {mean_true:.3f} cm)"
    assert up_move < 0.01 * mean_true, f"upper teeth move {up_move:.4f} cm"
    assert top_move < 0.02 * mean_true, f"skull top moves {top_move:.4f} cm, lower teeth {mean_true:.3f} cm"
    if _validator() is not None:
        report = _validate(tmp_path / "rig" / "head.glb")
        assert report["issues"]["numErrors"] == 0, report["issues"]["messages"]


def test_narrow_and_widen_follow_the_stated_rule():
    """fwk.safeio.narrow (what fwk pack stores) against a loop over the rule, and widen back."""
    import torch

    from fwk.safeio import MIXED_MIN, narrow, widen

    state = {"big": np.linspace(0, 1, MIXED_MIN), "small": np.linspace(0, 1, 10), "ids": np.arange(5, dtype=np.int64),
             "huge_ids": np.array([2 ** 40], dtype=np.int64), "w": torch.ones(MIXED_MIN), "b": torch.ones(3),
             "nested": [{"x": np.ones((2, 2))}], "flag": True}
    for precision in ("float32", "mixed"):
        n = narrow(state, precision)
        for k in ("big", "small"):
            want = np.float16 if precision == "mixed" and state[k].size >= MIXED_MIN else np.float32
            assert n[k].dtype == want, (precision, k)
        assert n["w"].dtype == (torch.float16 if precision == "mixed" else torch.float32) and n["b"].dtype == torch.float32
        assert n["ids"].dtype == np.int32 and n["huge_ids"].dtype == np.int64 and n["flag"] is True
        w = widen(n)
        assert w["big"].dtype == np.float64 and w["ids"].dtype == np.int64 and w["w"].dtype == torch.float32
        assert np.allclose(w["big"], state["big"], atol=1e-3) and np.array_equal(w["ids"], state["ids"])
        assert w["nested"][0]["x"].dtype == np.float64
    with pytest.raises(ValueError):
        narrow(state, "float8")


def test_mixed_precision_pack(shippable_rig_run, tmp_path):
    out = tmp_path / "mixed"
    lines = []
    pack(shippable_rig_run, out, precision="mixed", log=lines.append)
    card = json.loads((out / CARD).read_text())
    assert card["pack"]["precision"] == "mixed" and "mixed" in lines[0]
    st, meta = load_state(out / "models" / "pbs.safetensors", with_meta=True)
    assert meta["narrowed"] == "mixed" and meta["label"] == "pbs" and meta["name"] == "pbs"
    assert card["pack"]["largest_difference"] <= MAX_PACK_ERROR * card["pack"]["largest_displacement"]
