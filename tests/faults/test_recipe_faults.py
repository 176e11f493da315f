"""Hostile recipes (issue 25, item 2): every value checked before any work, the YAML and the
files bounded. Each case: exit 2, at most 3 lines on stderr, no traceback, within 20 s, nothing
written outside the runs folder (``tests/faults/hostile.py``)."""
from __future__ import annotations

import os
import sys

import pytest

from fwk.engine.config import TrainConfig
from fwk.errors import RecipeError
from tests.faults.common import PCA_RECIPE, recipe, run_dirs
from tests.faults.hostile import refused


def _runs(tmp_path):
    return tmp_path / "w" / "runs"


def _refused(tmp_path, text, *expect, extra=(), subprocess=False, env=None):
    r = recipe(tmp_path, text)
    runs = _runs(tmp_path)
    err = refused(["--quiet", "run", str(r), *extra, "--runs-dir", str(runs)], tmp_path, *expect, runs=runs,
                  subprocess=subprocess, env=env)
    assert run_dirs(runs) == []
    return err


def _with_train(train: str) -> str:
    return PCA_RECIPE + f"train: {train}\n"


@pytest.mark.parametrize("train,expect", [
    ("{lr: .inf}", "train.lr: expected a finite number, got inf"),
    ("{lr: -1.0e-3}", "train.lr: -0.001 is out of range"),
    ("{weight_decay: .nan}", "train.weight_decay: expected a finite number, got nan"),
    ("{kl_weight: -1}", "train.kl_weight: -1 is out of range"),
    ("{lr_decay: 1.5}", "train.lr_decay: 1.5 is out of range"),
    ("{epochs: 0}", "train.epochs: 0 is out of range"),
    ("{epochs: 1.0e+30}", "train.epochs:"),
    ("{batch_size: 100000000000000000000000}", "train.batch_size:"),
    ("{precision: 17}", "train.precision:"),
    ("{precision: 'half'}", "train.precision: 'half' is not one of 32-true"),
    ("{accelerator: xpu}", "train.accelerator: 'xpu' is not one of auto, cpu"),
    ("{strategy: fsdp_turbo}", "train.strategy: 'fsdp_turbo' is not one of auto, ddp"),
    ("{devices: 0}", "train.devices: 0 is out of range"),
    ("{devices: 'all the gpus'}", "train.devices:"),
    ("{early_stopping: {min_delta: .inf}}", "train.early_stopping.min_delta: expected a finite number"),
    ("{early_stopping: {patience: 0}}", "train.early_stopping.patience: 0 is out of range"),
])
def test_training_values_out_of_range(tmp_path, env, train, expect):
    _refused(tmp_path, _with_train(train), expect)


def test_non_finite_values_anywhere_and_overrides(tmp_path, env):
    _refused(tmp_path, PCA_RECIPE, "train.lr: expected a finite number, got inf", extra=["train.lr=.inf"])
    _refused(tmp_path, PCA_RECIPE, "split.ratios[0]: expected a finite number, got nan",
             extra=["split.ratios=[.nan, 0.5, 0.5]"])


def test_a_model_overriding_train_settings_is_checked_the_same_way():
    with pytest.raises(RecipeError, match="train.lr: expected a finite number"):
        TrainConfig().replace(lr=float("inf"))
    with pytest.raises(RecipeError, match="train.weight_decay: expected a finite number"):
        TrainConfig().replace(weight_decay=float("nan"))


@pytest.mark.parametrize("seed,expect", [
    ("18446744073709551616", "seed: 18446744073709551616 is out of range"),  # 2**64
    ("4294967296", "seed: 4294967296 is out of range (0 to 4294967295"),    # 2**32: Lightning would seed 0
    ("-1", "seed: -1 is out of range"),
    ("1.0e+300", "seed:"),
])
def test_seed_out_of_range(tmp_path, env, seed, expect):
    _refused(tmp_path, PCA_RECIPE.replace("seed: 0", f"seed: {seed}"), expect)


@pytest.mark.parametrize("name,expect", [
    ("../escaped", "contains a path separator /"),
    ("'..'", "contains `..`"),
    ("a/b", "contains a path separator /"),
    ("'a\\b'", "contains a path separator \\"),
    ('"a\\0b"', "contains a NUL character"),
    ('"a\\nb"', "contains a control character"),
    ("''", "name: empty"),
    ("x" * 300, "300 characters, at most 100"),
])
def test_run_names_stay_inside_the_runs_folder(tmp_path, env, name, expect):
    err = _refused(tmp_path, PCA_RECIPE + f"name: {name}\n", expect)
    assert err.startswith("fwk: error: name:"), err
    assert not (tmp_path / "w" / "escaped").exists()


def test_run_name_from_an_override(tmp_path, env):
    _refused(tmp_path, PCA_RECIPE, "name: '../../x' contains a path separator", extra=["name=../../x"])


def test_duplicate_keys_name_both_lines(tmp_path, env):
    text = PCA_RECIPE + "train: {epochs: 2}\nmetrics: [l1]\n"  # metrics: on line 6 and line 9
    lines = text.splitlines()
    first = next(i for i, line in enumerate(lines, 1) if line.startswith("metrics:"))
    _refused(tmp_path, text, f"line {len(lines)}: key 'metrics' given twice (first on line {first})")
    nested = PCA_RECIPE.replace("n_vertices: 200,", "n_vertices: 200, n_vertices: 300,")
    _refused(tmp_path, nested, "line 3: key 'n_vertices' given twice (first on line 3)")


def test_merge_keys_may_be_overridden(tmp_path, env):
    """``<<: *base`` then a key of the base: YAML's own override rule, not a duplicate."""
    from fwk.recipes import yaml_load

    assert yaml_load("a: &b {x: 1, y: 2}\nc:\n  <<: *b\n  x: 3\n") == {"a": {"x": 1, "y": 2}, "c": {"x": 3, "y": 2}}


def test_alias_expansion_is_bounded(tmp_path, env):
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    for i in range(1, 9):  # 10**9 values once expanded
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]")
    text = PCA_RECIPE + "\n".join(lines).replace("a8: &a8", "description: &a8") + "\n"
    _refused(tmp_path, text, "more than 100,000 values once its aliases (*name) are expanded")


def test_recursive_alias(tmp_path, env):
    _refused(tmp_path, PCA_RECIPE + "description: &d [1, *d]\n", "r.yaml: an alias (*name) refers to a node that contains it")


def test_nesting_is_bounded(tmp_path, env):
    _refused(tmp_path, PCA_RECIPE + "description: " + "[" * 5000 + "]" * 5000 + "\n", "r.yaml: nested too deeply")


def test_a_run_directorys_recipe_is_read_with_the_same_checks(tmp_path):
    from fwk.recipes import read_recipe_file

    p = tmp_path / "recipe.yaml"
    p.write_text("task: reconstruct\nseed: 1\nseed: 2\n")
    with pytest.raises(RecipeError, match="line 3: key 'seed' given twice"):
        read_recipe_file(p)


def test_file_size_is_bounded(tmp_path, env):
    _refused(tmp_path, PCA_RECIPE + "# " + "x" * (2 << 20) + "\n", "more than a recipe may have (1,048,576)")


def test_non_utf8_recipe(tmp_path, env):
    r = tmp_path / "latin1.yaml"
    r.write_bytes(PCA_RECIPE.encode() + "description: café\n".encode("latin-1"))
    runs = _runs(tmp_path)
    line = len(PCA_RECIPE.splitlines()) + 1
    refused(["run", str(r), "--runs-dir", str(runs)], tmp_path, f"line {line}: not UTF-8 text (byte 0xe9)", runs=runs)


def test_long_values_are_quoted_short(tmp_path, env):
    err = _refused(tmp_path, _with_train("{lr: '" + "9" * 100_000 + "x'}"), "train.lr: expected a number")
    assert len(err) < 400, len(err)
    err = _refused(tmp_path, PCA_RECIPE, "unknown parameter", extra=["k" * 100_000 + "=1"])
    assert len(err) < 1000, len(err)


def test_extends_a_folder(tmp_path, env):
    _refused(tmp_path, f"extends: {tmp_path}\n" + PCA_RECIPE, f"extends: {tmp_path} is a folder, not a file")


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="no /dev/zero")
def test_extends_a_device(tmp_path, env):
    """/dev/zero would be read forever: refused before it is opened for reading (in a subprocess,
    so that a hang fails the test instead of stopping the suite)."""
    _refused(tmp_path, "extends: /dev/zero\n" + PCA_RECIPE, "extends: /dev/zero is not a regular file",
             subprocess=True, env=env)


@pytest.mark.skipif(sys.platform == "win32", reason="no FIFOs")
def test_extends_a_fifo_and_a_fifo_recipe(tmp_path, env):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    _refused(tmp_path, "extends: pipe.yaml\n" + PCA_RECIPE, "is not a regular file", subprocess=True, env=env)
    runs = _runs(tmp_path)
    refused(["run", str(fifo), "--runs-dir", str(runs)], tmp_path, f"recipe file {fifo} is not a regular file",
            runs=runs, subprocess=True, env=env)


@pytest.mark.parametrize("args,expect", [
    (["--seed", "-1"], "--seed -1: out of range (0 to 4294967295)"),
    (["--seed", str(2**70)], f"--seed {2**70}: out of range"),
    (["--n", "0"], "--n 0: from 1 to 10,000"),
    (["--n", "100000000"], "--n 100000000: from 1 to 10,000"),
])
def test_sample_values_checked_before_the_run_is_opened(tmp_path, env, args, expect):
    refused(["sample", str(tmp_path / "no-run"), "--out", str(tmp_path / "out"), *args], tmp_path, expect)
