"""Every reader of a run's ``recipe.yaml`` applies the checks of a recipe file
(``fwk.recipes.read_recipe_file``: a key given twice, aliases expanding past
``MAX_RECIPE_NODES``), not a bare ``yaml.safe_load``: ``fwk run --resume``, ``fwk sample`` and
``fwk apply`` (``fwk.lifecycle.open_run``), a recipe's ``run:`` (task ``edit``), ``fwk report``
comparing runs (``cli_report.identity``) and a DDP rank (``fwk.rank``). The planted recipe also
gets its SHA-256 recorded in ``versions.json`` (whoever sends a run can forge both), so the
refusal comes from the reader, not from the hash check. Each is refused in one line naming the
file (exit 2, no traceback)."""
from __future__ import annotations

import hashlib
import json

import pytest

from fwk.cli import main
from tests.faults.run_fixtures import (blendshapes_run, copy_run, edit_recipe, pca_run, refused,  # noqa: F401
                                       sample)


def _plant(d, text: str) -> None:
    """``recipe.yaml`` replaced by ``text``, its SHA-256 recorded as if the run started with it."""
    (d / "recipe.yaml").write_text(text)
    versions = json.loads((d / "versions.json").read_text())
    versions["recipe_sha256"] = hashlib.sha256((d / "recipe.yaml").read_bytes()).hexdigest()
    (d / "versions.json").write_text(json.dumps(versions))


def _duplicate(d) -> None:
    text = (d / "recipe.yaml").read_text()
    assert "\nrenders: 0\n" in text
    _plant(d, text + "renders: 0\n")  # `renders` twice: plain safe_load keeps the last one silently


def _bomb(d) -> None:
    levels = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    levels += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 7)]  # 10^7 values
    _plant(d, (d / "recipe.yaml").read_text() + "description:\n" + "".join(f"  {ln}\n" for ln in levels))


PLANTS = {"duplicate": (_duplicate, "given twice"), "alias-bomb": (_bomb, "100,000")}


@pytest.mark.parametrize("plant", list(PLANTS))
@pytest.mark.parametrize("cmd", ["resume", "sample", "edit", "report"])
def test_a_planted_recipe_is_refused_in_one_line(pca_run, tmp_path, env, capsys, plant, cmd):
    do, words = PLANTS[plant]
    d = copy_run(pca_run[0], tmp_path)
    do(d)
    capsys.readouterr()
    if cmd == "resume":
        rc = main(["--quiet", "run", "--resume", str(d)])
    elif cmd == "sample":
        rc = sample(d, tmp_path)
    elif cmd == "edit":
        rc = edit_recipe(d, tmp_path)
    else:  # comparing runs reads each one's recipe (task, dataset, split)
        other = copy_run(pca_run[0], tmp_path / "other")
        rc = main(["--quiet", "report", str(other), str(d), "--out", str(tmp_path / "combined")])
    err = refused(capsys, rc, "recipe.yaml", words)
    assert str(d) in err
    assert not (d / "FAILED").exists() and not (d / "RUNNING").exists()  # nothing was run


def test_apply_refuses_a_duplicate_key(blendshapes_run, tmp_path, env, capsys):
    d = copy_run(blendshapes_run[0], tmp_path)
    _duplicate(d)
    capsys.readouterr()
    rc = main(["--quiet", "apply", str(d), str(blendshapes_run[1]), "--out", str(tmp_path / "out")])
    refused(capsys, rc, "recipe.yaml", "given twice")
    assert not (tmp_path / "out").exists()


def test_a_ddp_rank_refuses_a_duplicate_key_in_one_line(pca_run, tmp_path, env, capsys):
    from fwk import rank

    d = copy_run(pca_run[0], tmp_path)
    _duplicate(d)
    job = {"run_dir": str(d), "source": None, "ckdir": str(d / "checkpoints" / "x"), "ckpt": None,
           "cache": str(tmp_path / "cache"), "cache_enabled": True, "device": None}
    capsys.readouterr()
    assert rank.main([json.dumps(job)]) == 1
    err = capsys.readouterr().err
    assert "given twice" in err and "recipe.yaml" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1, err
