"""Finished runs the fault modules on run files share (a PCA run, a PCA + MLP run with checkpoints,
a blendshapes run on OBJ heads big enough for the on-disk topology cache), built once per module,
and the checks of a clean refusal."""
from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch
import yaml

from fwk.cache import forget
from fwk.cli import main
from tests.faults.common import PCA_RECIPE, TRAIN_RECIPE, assert_complete, fwk_run, models, recipe


def _pickled(obj) -> bytes:
    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def _finished(tmp_path_factory, text: str, name: str):
    """A finished run of ``text`` with its own cache: (run directory, metrics by model)."""
    base = tmp_path_factory.mktemp(name)
    old = os.environ.get("FWK_CACHE")
    os.environ["FWK_CACHE"] = str(base / "cache")
    try:
        rc, d = fwk_run(recipe(base, text), base / "runs")
    finally:
        os.environ.pop("FWK_CACHE") if old is None else os.environ.__setitem__("FWK_CACHE", old)
    assert rc == 0
    assert_complete(d)
    return d, models(d)


@pytest.fixture(scope="module")
def pca_run(tmp_path_factory):
    return _finished(tmp_path_factory, PCA_RECIPE, "pca")


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    return _finished(tmp_path_factory, TRAIN_RECIPE, "trained")


W = 46  # a (W+1) x (W+1) grid head of W x W quads: over 2,000 faces, so its topology is cached on disk


def _grid_obj(V) -> str:
    lines = [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    for j in range(W):
        for i in range(W):
            a = j * (W + 1) + i
            lines.append("f " + " ".join(str(v + 1) for v in (a, a + 1, a + W + 2, a + W + 1)))
    return "\n".join(lines) + "\n"


def _neutral(rng):
    x, y = np.meshgrid(np.linspace(-1, 1, W + 1), np.linspace(-1, 1, W + 1))
    z = 0.3 * np.exp(-(x ** 2 + y ** 2)) + 0.01 * rng.standard_normal(x.shape)
    return np.stack([x.ravel() * (1 + 0.1 * rng.standard_normal()), y.ravel(), z.ravel()], 1)


def _smile(V):
    out = V.copy()
    out[:, 2] += 0.2 * np.exp(-4 * (V[:, 0] ** 2 + (V[:, 1] + 0.5) ** 2))
    return out


@pytest.fixture(scope="module")
def blendshapes_run(tmp_path_factory):
    """A finished blendshapes run (dt, closed form) on a folder of OBJ heads, and one neutral."""
    base = tmp_path_factory.mktemp("heads")
    root = base / "heads"
    rng = np.random.default_rng(0)
    for s in range(6):
        V = _neutral(rng)
        (root / f"s{s}").mkdir(parents=True)
        (root / f"s{s}" / "neutral.obj").write_text(_grid_obj(V))
        (root / f"s{s}" / "smile.obj").write_text(_grid_obj(_smile(V)))
    (base / "me.obj").write_text(_grid_obj(_neutral(rng)))
    text = yaml.safe_dump({"name": "bs", "task": "blendshapes", "seed": 0,
                           "dataset": {"name": "mesh-folder", "root": str(root)},
                           "split": {"ratios": [0.5, 0.17, 0.33]}, "models": {"dt": {"name": "dt", "sources": 0}},
                           "renders": 0, "metrics": ["l1", "l2"]})
    forget("obj-topology")  # parsed in this process before (another module's fixture): read it from disk again
    d, _ = _finished(tmp_path_factory, text, "bs")
    assert list((d.parents[1] / "cache").rglob("*.bin")), "no pickled cache entry to plant in"
    return d, base / "me.obj"


def fwk_sub(env, *args):
    """``fwk ARGS`` in a new process (nothing memoised in this one): (exit status, stderr)."""
    p = subprocess.run([sys.executable, "-m", "fwk", "--quiet", *map(str, args)], env=env, capture_output=True,
                       text=True, timeout=300)
    return p.returncode, p.stderr


@pytest.fixture
def marker(tmp_path):
    m = tmp_path / "payload-ran"
    yield m
    assert not m.exists(), "the planted payload ran"


def copy_run(src, tmp_path):
    return shutil.copytree(src, tmp_path / "run" / src.name)


def refused(capsys, rc, *words):
    """A clean refusal: exit 2, at most 3 lines on stderr, no traceback, naming ``words``."""
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.strip() and len(err.strip().splitlines()) <= 3 and "Traceback" not in err, err
    for w in words:
        assert w in err, (w, err)
    return err


def sample(run, tmp_path):
    return main(["--quiet", "sample", str(run), "--n", "2", "--out", str(tmp_path / "samples")])


def edit_recipe(run, tmp_path):
    p = tmp_path / "edit.yaml"
    p.write_text(f"task: edit\nrun: {run}\nrenders: 0\n")
    return main(["--quiet", "run", str(p), "--runs-dir", str(tmp_path / "edits")])
