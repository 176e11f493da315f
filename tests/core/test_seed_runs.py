"""A run with ``seeds:`` reopened (``fwk.lifecycle.open_run`` / ``seed_sub_run``): ``fwk apply
RUN``, ``fwk sample RUN`` and a recipe's ``run: RUN`` use the first seed's sub-run and say so in
one line; ``--seed-run S`` picks seed S and gives exactly what ``RUN/seed-S`` gives; a seed's
sub-run that is missing, unfinished, failed or holds another recipe is refused in one line
naming it."""
import filecmp
import shutil

import pytest
import yaml

from fwk.apply import apply
from fwk.cli import main
from fwk.generate import sample_meshes
from fwk.runs import execute
from tests.core.test_seeds import _grid, _json, tmp  # noqa: F401  (tmp: the module's folder, one thread, own cache)

NET = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
#: two seeds of a trained blendshape model: its predictions differ by seed
BS = {"name": "bs2", "task": "blendshapes", "seeds": [0, 1], "train": {"epochs": 1, "batch_size": 4},
      "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 8, "shapes": ["neutral", "mouth-wide"]},
      "split": {"ratios": [0.5, 0.25, 0.25]}, "metrics": ["l1"], "renders": 0,
      "models": {"pb": {"name": "pb", "network": NET}}}
#: two seeds of a band model (fwk sample's first choice, what edit edits)
REC = {"name": "rec2", "task": "reconstruct", "seeds": 2, "train": {"epochs": 1, "batch_size": 8},
       "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12},
       "split": {"ratios": [0.6, 0.2, 0.2]}, "metrics": ["l1"], "renders": 0,
       "models": {"dsm": {"name": "dsm", "k": 20, "network": NET}}}


def _run(tmp, recipe):
    (tmp / f"{recipe['name']}.yaml").write_text(yaml.safe_dump(recipe))
    return execute(str(tmp / f"{recipe['name']}.yaml"), runs_dir=str(tmp / recipe["name"]), quiet=True)


@pytest.fixture(scope="module")
def bs2(tmp):
    return _run(tmp, BS)


@pytest.fixture(scope="module")
def rec2(tmp):
    return _run(tmp, REC)


def _line(run, choose="--seed-run S or {run}/seed-S"):
    return f"{run} has seeds 0, 1: using seed-0 (choose with {choose.format(run=run)})"


def _same(a, b) -> bool:
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert files and files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    return all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)


def test_apply_uses_the_first_seed_or_the_one_chosen(bs2, tmp_path, capsys):
    neutral = bs2 / "seed-0" / "template.obj"
    said = []
    apply(bs2, neutral, tmp_path / "top", log=lambda *_: None, say=said.append)
    assert said == [_line(bs2)]
    apply(bs2 / "seed-0", neutral, tmp_path / "s0", log=lambda *_: None, say=said.append)
    apply(bs2 / "seed-1", neutral, tmp_path / "s1", log=lambda *_: None, say=said.append)
    assert said == [_line(bs2)]  # RUN/seed-S: nothing to say
    assert _same(tmp_path / "top", tmp_path / "s0")
    assert not _same(tmp_path / "s0", tmp_path / "s1")  # the seeds' models differ
    # the command line: the line on stderr, once; --seed-run 1 is RUN/seed-1
    capsys.readouterr()
    assert main(["apply", str(bs2), str(neutral), "--out", str(tmp_path / "cli0")]) == 0
    assert capsys.readouterr().err.strip() == _line(bs2)
    assert main(["apply", str(bs2), str(neutral), "--out", str(tmp_path / "cli1"), "--seed-run", "1"]) == 0
    assert capsys.readouterr().err == ""
    assert _same(tmp_path / "cli0", tmp_path / "s0") and _same(tmp_path / "cli1", tmp_path / "s1")
    assert main(["--quiet", "apply", str(bs2), str(neutral), "--out", str(tmp_path / "q")]) == 0
    assert capsys.readouterr().err == ""  # --quiet: no line


def test_sample_uses_the_first_seed_or_the_one_chosen(rec2, tmp_path, capsys):
    said = []
    label, top, _ = sample_meshes(rec2, 2, say=said.append)
    assert label == "dsm" and said == [_line(rec2)]
    s0 = sample_meshes(rec2 / "seed-0", 2, say=said.append)[1]
    s1 = sample_meshes(rec2 / "seed-1", 2, say=said.append)[1]
    assert len(said) == 1 and (top == s0).all() and not (s0 == s1).all()
    assert (sample_meshes(rec2, 2, seed_run=1, say=said.append)[1] == s1).all()
    capsys.readouterr()
    assert main(["sample", str(rec2), "--n", "2", "--out", str(tmp_path / "a"), "--seed-run", "1"]) == 0
    assert main(["sample", str(rec2 / "seed-1"), "--n", "2", "--out", str(tmp_path / "b")]) == 0
    assert capsys.readouterr().err == ""
    assert _same(tmp_path / "a", tmp_path / "b")
    assert main(["sample", str(rec2), "--n", "2", "--out", str(tmp_path / "c")]) == 0
    assert capsys.readouterr().err.strip() == _line(rec2)


def test_a_grid_members_seeds(tmp):
    """A grid member with seeds (``<grid>/<member>/seed-<s>/``) opens like a run with seeds."""
    grid = execute(str(_grid(tmp)), runs_dir=str(tmp / "grid"), quiet=True)
    said = []
    top = sample_meshes(grid / "a", 2, say=said.append)[1]
    assert said == [_line(grid / "a")]
    assert (top == sample_meshes(grid / "a" / "seed-0", 2, say=said.append)[1]).all()
    assert (sample_meshes(grid / "a", 2, seed_run=1, say=said.append)[1] ==
            sample_meshes(grid / "a" / "seed-1", 2, say=said.append)[1]).all()
    assert len(said) == 1


def test_edit_run_key_uses_the_first_seed(rec2, tmp_path):
    (tmp_path / "edit.yaml").write_text(f"task: edit\nrun: {rec2}\nrenders: 0\n")
    run = execute(str(tmp_path / "edit.yaml"), runs_dir=str(tmp_path / "edits"), quiet=True)
    assert _line(rec2, "run: {run}/seed-S") in (run / "log.txt").read_text()
    assert f"models: {rec2 / 'seed-0'}" in (run / "report.md").read_text()
    (tmp_path / "edit0.yaml").write_text(f"task: edit\nrun: {rec2 / 'seed-0'}\nrenders: 0\n")
    run0 = execute(str(tmp_path / "edit0.yaml"), runs_dir=str(tmp_path / "edits0"), quiet=True)
    for key in ("disentanglement", "models"):  # the same models: the same measures
        assert _json(run / "metrics.json")[key] == _json(run0 / "metrics.json")[key]


def _refused(capsys, rc, *words):
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)


def test_seed_choices_and_unfinished_seeds_are_refused_in_one_line(bs2, tmp_path, capsys):
    run = shutil.copytree(bs2, tmp_path / "run" / bs2.name)
    neutral = bs2 / "seed-0" / "template.obj"

    def go(target, *extra):
        capsys.readouterr()
        return main(["--quiet", "apply", str(target), str(neutral), "--out", str(tmp_path / "out"), *extra])

    _refused(capsys, go(run, "--seed-run", "5"), "--seed-run 5: not a seed of", "its seeds: 0, 1")
    _refused(capsys, go(run / "seed-0", "--seed-run", "1"), "is the sub-run of seed 0", str(run / "seed-1"))
    assert go(run / "seed-0", "--seed-run", "0") == 0
    plain = shutil.copytree(run / "seed-0", tmp_path / "plain")  # a run of one seed
    _refused(capsys, go(plain, "--seed-run", "0"), "--seed-run 0:", "a run of one seed")
    # seed 1 unfinished (no metrics.json): refused whichever way it is named; seed 0 still opens
    (run / "seed-1" / "metrics.json").rename(run / "seed-1" / "m.json")
    _refused(capsys, go(run, "--seed-run", "1"), f"{run / 'seed-1'}: seed 1 did not finish (no metrics.json)")
    _refused(capsys, go(run / "seed-1"), f"{run / 'seed-1'}: seed 1 did not finish", f"--resume {run}")
    (run / "FAILED").write_text("RuntimeError: seed 1 broke\n")  # the run failed on seed 1
    assert go(run) == 0 and go(run, "--seed-run", "0") == 0
    (run / "seed-1" / "m.json").rename(run / "seed-1" / "metrics.json")
    (run / "seed-1" / "FAILED").write_text("RuntimeError: seed 1 broke\n")
    _refused(capsys, go(run, "--seed-run", "1"), f"{run / 'seed-1'}: seed 1 failed (RuntimeError: seed 1 broke)")
    (run / "seed-1" / "FAILED").unlink()
    # a seed's recipe.yaml edited: not the member recipe of the run's (hash-checked) recipe.yaml
    r = run / "seed-1" / "recipe.yaml"
    r.write_text(r.read_text().replace("epochs: 1", "epochs: 2"))
    _refused(capsys, go(run / "seed-1"), f"{r}: not the recipe of seed 1")
    _refused(capsys, go(run, "--seed-run", "1"), f"{r}: not the recipe of seed 1")
    shutil.rmtree(run / "seed-0")
    _refused(capsys, go(run), f"{run / 'seed-0'}: missing")
