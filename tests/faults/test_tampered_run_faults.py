"""Tampered or inconsistent run directories (issue 25, item 4): a truncated or swapped model file,
a garbage or foreign ``stats/*.npz``, a malformed ``metrics.json`` or ``split.json``, an edited
or unreadable ``recipe.yaml``, a missing file. Through ``fwk sample``, ``fwk report``,
``fwk run --resume``, a recipe's ``run:`` (task ``edit``) and ``fwk apply``, each is refused in
one line naming the file (exit 2, at most 3 lines on stderr, no traceback), or, where the
command does not need the file or rebuilds it (``--resume`` recomputes the split, the
preprocessing and the metrics), the command works and gives the run's own numbers."""
from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from fwk.cli import main
from tests.faults.common import models
from tests.faults.run_fixtures import (blendshapes_run, copy_run, edit_recipe, refused, sample,  # noqa: F401
                                       trained_run)


def _truncate(p):
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])


def _edit_recipe(d):
    p = d / "recipe.yaml"
    text = p.read_text()
    assert "n_components: 3" in text
    p.write_text(text.replace("n_components: 3", "n_components: 2"))  # still a valid recipe


#: tamper -> (what to do to the run, the file the refusal names, the commands that must refuse it;
#: every other command must work, and a resume must give the run's own metrics)
TAMPERS = {
    "truncated-model": (lambda d: _truncate(d / "models" / "pca.safetensors"), "models/pca.safetensors",
                        {"sample", "edit", "resume"}),
    # (sample opens the first generative model only: pca)
    "flipped-byte-model": (lambda d: _flip(d / "models" / "mlp.safetensors"), "models/mlp.safetensors",
                           {"edit", "resume"}),
    "swapped-model": (lambda d: shutil.copy(d / "models" / "mlp.safetensors", d / "models" / "pca.safetensors"),
                      "models/pca.safetensors", {"sample", "edit", "resume"}),
    "garbage-npz": (lambda d: (d / "stats" / "preprocess.npz").write_bytes(os.urandom(3000)),
                    "stats/preprocess.npz", {"sample", "edit"}),
    "foreign-npz": (lambda d: np.savez(d / "stats" / "preprocess.npz", x=np.zeros(3)), "stats/preprocess.npz",
                    {"sample", "edit"}),
    "metrics-not-json": (lambda d: (d / "metrics.json").write_text('{"models": {'), "metrics.json",
                         {"sample", "edit", "report"}),
    "metrics-a-list": (lambda d: (d / "metrics.json").write_text("[1, 2]"), "metrics.json",
                       {"sample", "edit", "report"}),
    "metrics-wrong-inside": (lambda d: (d / "metrics.json").write_text('{"models": {"pca": 3}}'), "metrics.json",
                             {"report"}),
    "recipe-edited": (_edit_recipe, "recipe.yaml", {"sample", "edit", "resume"}),
    "recipe-not-utf8": (lambda d: (d / "recipe.yaml").write_bytes(b"\xff\xfe task: [\n"), "recipe.yaml",
                        {"sample", "edit", "resume"}),
    "split-not-json": (lambda d: (d / "split.json").write_text("{{"), "split.json", {"edit"}),
    "split-foreign": (lambda d: (d / "split.json").write_text('{"train": ["nobody"]}'), "split.json", {"edit"}),
    "missing-model": (lambda d: (d / "models" / "pca.safetensors").unlink(), "models/pca.safetensors",
                      {"sample", "edit"}),
    "missing-npz": (lambda d: (d / "stats" / "preprocess.npz").unlink(), "preprocess.npz", {"sample", "edit"}),
    "missing-metrics": (lambda d: (d / "metrics.json").unlink(), "metrics.json", {"report"}),
    "missing-recipe": (lambda d: (d / "recipe.yaml").unlink(), "recipe.yaml", {"sample", "edit", "resume"}),
}


def _flip(p):
    raw = bytearray(p.read_bytes())
    raw[-5] ^= 0x01  # one bit of a weight: still a well-formed file
    p.write_bytes(bytes(raw))


def _command(cmd, d, tmp_path):
    if cmd == "sample":
        return sample(d, tmp_path)
    if cmd == "report":
        return main(["--quiet", "report", str(d)])
    if cmd == "resume":
        return main(["--quiet", "run", "--resume", str(d)])
    return edit_recipe(d, tmp_path)


@pytest.mark.parametrize("tamper", list(TAMPERS))
@pytest.mark.parametrize("cmd", ["sample", "report", "resume", "edit"])
def test_tampered_run(trained_run, tmp_path, env, capsys, tamper, cmd):
    do, name, refusing = TAMPERS[tamper]
    d = copy_run(trained_run[0], tmp_path)
    do(d)
    capsys.readouterr()
    rc = _command(cmd, d, tmp_path)
    if cmd in refusing:
        err = refused(capsys, rc, name)
        assert "Traceback" not in err
        return
    err = capsys.readouterr().err
    if cmd == "edit":  # the run opened whole: edit then asks for what a PCA + MLP run lacks, a band model
        assert rc == 2 and "no dsm model to edit" in err and len(err.splitlines()) == 1, err
        return
    assert rc == 0, err
    if cmd == "resume":
        assert models(d) == trained_run[1]  # recomputed: the run's own numbers
    if cmd == "sample":
        assert len(list((tmp_path / "samples").glob("*.obj"))) == 2


def test_resume_refuses_an_edited_recipe_and_keeps_the_run(trained_run, tmp_path, env, capsys):
    """``--resume`` checks recipe.yaml against the SHA-256 recorded when the run started, before
    it writes anything: the run stays complete, its models and numbers untouched."""
    d = copy_run(trained_run[0], tmp_path)
    versions = json.loads((d / "versions.json").read_text())
    assert len(versions["recipe_sha256"]) == 64
    _edit_recipe(d)
    before = {p: p.read_bytes() for p in (d / "models").iterdir()}
    capsys.readouterr()
    refused(capsys, main(["--quiet", "run", "--resume", str(d)]), "recipe.yaml", "edited")
    assert not (d / "FAILED").exists() and not (d / "RUNNING").exists()
    assert {p: p.read_bytes() for p in (d / "models").iterdir()} == before
    assert json.loads((d / "versions.json").read_text()) == versions


@pytest.mark.parametrize("tamper", ["truncated-model", "garbage-template", "foreign-template", "garbage-npz",
                                    "metrics-not-json", "recipe-edited", "missing-template"])
def test_apply_on_a_tampered_run(blendshapes_run, tmp_path, env, capsys, tamper):
    d = copy_run(blendshapes_run[0], tmp_path)
    stats = d / "stats"
    do, name = {
        "truncated-model": (lambda: _truncate(d / "models" / "dt.safetensors"), "dt.safetensors"),
        "garbage-template": (lambda: (stats / "template.npz").write_bytes(b"PK\x03\x04" + os.urandom(500)),
                             "template.npz"),
        "foreign-template": (lambda: np.savez(stats / "template.npz", x=np.zeros(2)), "template.npz"),
        "garbage-npz": (lambda: (stats / "preprocess.npz").write_bytes(os.urandom(500)), "preprocess.npz"),
        "metrics-not-json": (lambda: (d / "metrics.json").write_text("{"), "metrics.json"),
        "recipe-edited": (lambda: (d / "recipe.yaml").write_text((d / "recipe.yaml").read_text()
                                                                 .replace("renders: 0", "renders: 1")),
                          "recipe.yaml"),
        "missing-template": (lambda: (stats / "template.npz").unlink(), "template.npz"),
    }[tamper]
    do()
    capsys.readouterr()
    rc = main(["--quiet", "apply", str(d), str(blendshapes_run[1]), "--out", str(tmp_path / "out")])
    refused(capsys, rc, name)


def test_apply_on_the_untampered_run_works(blendshapes_run, tmp_path, env):
    """(The baseline of the cases above: the same command on the run as it was works.)"""
    d = copy_run(blendshapes_run[0], tmp_path)
    assert main(["--quiet", "apply", str(d), str(blendshapes_run[1]), "--out", str(tmp_path / "out")]) == 0
    assert list((tmp_path / "out").rglob("*.obj"))
