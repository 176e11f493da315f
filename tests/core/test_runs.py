"""End to end: the smoke recipe's run directory, resume after a kill, errors that write nothing."""
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fwk.cli import main

REPO = Path(__file__).resolve().parents[2]
SMOKE = REPO / "recipes/smoke/reconstruct.yaml"


def _run(tmp_path, *extra):
    runs = tmp_path / "runs"
    rc = main(["--quiet", "run", str(SMOKE), *extra, "--runs-dir", str(runs)])
    assert rc == 0
    (d,) = [p for p in runs.iterdir() if p.is_dir()]
    return d


@pytest.mark.slow
def test_smoke_run_directory(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    d = _run(tmp_path)
    for f in ("recipe.yaml", "versions.json", "split.json", "metrics.json", "report.md", "log.txt"):
        assert (d / f).exists(), f
    assert any((d / "stats").glob("*.npz"))
    assert any((d / "checkpoints").rglob("*.ckpt"))
    assert any((d / "tb").rglob("events.*"))
    m = json.loads((d / "metrics.json").read_text())
    for model in ("pca", "mlp-vae"):
        for split in ("train", "val", "test"):
            for metric in ("l1", "l2", "euclidean"):
                v = m["models"][model][split][metric]["mean"]
                assert math.isfinite(v), (model, split, metric)
    versions = json.loads((d / "versions.json").read_text())
    assert "torch" in versions and "plugins" in versions
    # the trained network's curves, summarised in metrics.json and the report
    curves = json.loads((d / "curves" / "mlp-vae" / "mlp-vae.json").read_text())
    assert curves["finished"] and curves["stopped_by"] == "max_epochs" and curves["epochs_run"] == 5
    assert m["training"]["networks"]["mlp-vae"]["epochs_run"] == 5 and "pca" not in m["training"]["networks"]
    assert "## Training" in (d / "report.md").read_text()
    split = json.loads((d / "split.json").read_text())
    assert not set(split["train"]) & set(split["test"])


@pytest.mark.slow
def test_resume_after_kill_gives_same_metrics(tmp_path):
    env = {**os.environ, "FWK_CACHE": str(tmp_path / "cache"), "PYTHONUNBUFFERED": "1"}
    over = ["train.epochs=40", "models={vae: {name: mlp-vae, latent: 8}}", "metrics=[l1, l2]", "renders=0"]
    full_runs, kill_runs = tmp_path / "full", tmp_path / "kill"
    subprocess.run([sys.executable, "-m", "fwk", "--quiet", "run", str(SMOKE), *over, "--runs-dir", str(full_runs)],
                   check=True, env=env, capture_output=True)
    p = subprocess.Popen([sys.executable, "-m", "fwk", "--quiet", "run", str(SMOKE), *over, "--runs-dir", str(kill_runs)],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.time() + 300
    killed = False
    while time.time() < deadline and p.poll() is None:
        ck = list(kill_runs.rglob("*.ckpt")) if kill_runs.exists() else []
        if any("epoch" in c.name for c in ck):
            p.send_signal(signal.SIGKILL)
            killed = True
            break
        time.sleep(0.05)
    p.wait()
    assert killed, "the run finished before it could be killed; raise train.epochs"
    (d,) = list(kill_runs.iterdir())
    assert not (d / "metrics.json").exists()
    subprocess.run([sys.executable, "-m", "fwk", "--quiet", "run", "--resume", str(d)], check=True, env=env,
                   capture_output=True)
    (f,) = list(full_runs.iterdir())
    a = json.loads((f / "metrics.json").read_text())["models"]
    b = json.loads((d / "metrics.json").read_text())["models"]
    assert a == b


def test_mesh_folder_bad_file_named_and_no_run_dir(tmp_path, capsys):
    import numpy as np

    from fwk.data import Template
    from fwk.data.io import write_obj

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    F = np.array([[0, 1, 2], [1, 3, 2]])
    t = Template(V, F)
    root = tmp_path / "data"
    for s in ("a", "b", "c", "d"):
        write_obj(root / s / "neutral.obj", V + np.random.default_rng(len(s)).normal(0, 0.01, V.shape), t)
    bad = Template(np.vstack([V, [[2, 2, 0]]]), np.vstack([F, [[3, 4, 2]]]))
    write_obj(root / "c" / "neutral.obj", bad.vertices, bad)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(f"task: reconstruct\ndataset: {{name: mesh-folder, root: {root}, pattern: '{{subject}}/{{shape}}.obj'}}\n"
                      "models: {pca: {name: pca, n_components: 2}}\nmetrics: [l1]\nrenders: 0\n")
    runs = tmp_path / "runs"
    assert main(["--quiet", "run", str(recipe), "--runs-dir", str(runs)]) == 2
    err = capsys.readouterr().err
    assert str(Path("c") / "neutral.obj") in err
    assert not runs.exists() or not any(runs.iterdir())


def test_ict_recipe_trains_pca(tmp_path, monkeypatch):
    from fwk.testing import ICT_SKIP_REASON, ict_path

    folder = ict_path()
    if folder is None:
        pytest.skip(ICT_SKIP_REASON)
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    runs = tmp_path / "runs"
    rc = main(["--quiet", "run", str(REPO / "recipes/smoke/reconstruct_ict.yaml"), f"dataset.path={folder}",
               "--runs-dir", str(runs)])
    assert rc == 0
    (d,) = list(runs.iterdir())
    m = json.loads((d / "metrics.json").read_text())
    assert m["dataset"]["n_vertices"] == 11248 and m["dataset"]["units"] == "cm"
    for split in ("train", "val", "test"):
        assert math.isfinite(m["models"]["pca"][split]["l1"]["mean"])
    assert m["models"]["pca"]["test"]["l1"]["mean"] > m["models"]["pca"]["train"]["l1"]["mean"]


def test_predictions_written_back_with_original_polygons_and_uvs(tmp_path):
    """A user's quad mesh with UVs and materials: predicted OBJs keep f, vt and usemtl lines."""
    import numpy as np

    from fwk.data.io import read_obj

    src = (REPO / "tests" / "core" / "quad_head.obj")
    V0, t = read_obj(src)
    root = tmp_path / "data"
    rng = np.random.default_rng(0)
    from fwk.data.io import write_obj

    for s in range(8):
        write_obj(root / f"s{s}" / "neutral.obj", V0 * (1 + 0.05 * rng.normal()) + rng.normal(0, 0.01, V0.shape), t)
    recipe = tmp_path / "r.yaml"
    recipe.write_text(f"task: reconstruct\ndataset: {{name: mesh-folder, root: {root}, pattern: '{{subject}}/{{shape}}.obj', units: mm}}\n"
                      "split: {ratios: [0.6, 0.2, 0.2]}\nmodels: {pca: {name: pca, n_components: 3}}\nmetrics: [l1]\n"
                      "renders: 0\nwrite_obj: 2\n")
    runs = tmp_path / "runs"
    assert main(["--quiet", "run", str(recipe), "--runs-dir", str(runs)]) == 0
    (d,) = list(runs.iterdir())
    outs = sorted((d / "predictions" / "pca").glob("*.obj"))
    assert len(outs) == 2
    src_lines = src.read_text().splitlines()
    for o in outs:
        lines = o.read_text().splitlines()
        for tag in ("f ", "vt ", "usemtl", "mtllib"):
            assert [l for l in lines if l.startswith(tag)] == [l for l in src_lines if l.startswith(tag)], tag
        V, _ = read_obj(o)
        assert V.shape == V0.shape and np.abs(V - V0).max() < 1.0  # back in input units, near the data
