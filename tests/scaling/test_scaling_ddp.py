"""DDP on 2 CPU processes (gloo) through ``fwk run``, against 1 device; resume under DDP.

Each test runs ``fwk run`` as a subprocess (the real entry point: fwk's launcher starts rank 1
as ``python -m fwk.rank``, which must not happen inside pytest's process). Marked
slow: about 15 s per run on 2 cores.

Tolerances. The autoencoder of ``grid_base.yaml`` draws no noise: 2 ranks x 8 samples average
the gradients of exactly the 16 samples one device takes as its batch (the training set, 16
subjects, divides evenly), so only the order of the sums differs; measured 3e-7 relative on
every metric, asserted at 1e-5. The VAE of ``reconstruct.yaml`` samples its code: each rank
draws its own noise (seeded by (seed, epoch, rank)), so the runs are two draws of one training;
after 5 epochs of 2 steps the metrics on the train (34 subjects) and test (4) splits differed by
at most 8 % (L2, a squared error; L1 2 %), asserted at 10 %; the validation split (2 subjects)
differed by up to 20 % and is left out.
"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DDP = ["train.devices=2", "train.strategy=ddp", "train.accelerator=cpu"]
AE = [str(REPO / "recipes" / "smoke" / "grid_base.yaml"), "dataset.n_subjects=23"]  # 16 training subjects

pytestmark = pytest.mark.slow


def _fwk(tmp_path, *args, timeout=300) -> subprocess.CompletedProcess:
    env = {**os.environ, "FWK_CACHE": str(tmp_path / "cache"), "FWK_THREADS": "1", "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, "-m", "fwk", *args], env=env, capture_output=True, text=True,
                       timeout=timeout, cwd=tmp_path)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def _run(tmp_path, label: str, *args) -> tuple[Path, str]:
    runs = tmp_path / label
    out = _fwk(tmp_path, "run", *args, "--runs-dir", str(runs)).stdout
    (d,) = list(runs.iterdir())
    return d, out


def _means(run: Path, model: str, splits=("train", "val", "test")) -> dict:
    m = json.loads((run / "metrics.json").read_text())["models"][model]
    return {(s, k): v["mean"] for s, per in m.items() if s in splits and isinstance(per, dict)
            for k, v in per.items() if isinstance(v, dict) and "mean" in v}


def _close(a: dict, b: dict, rtol: float) -> float:
    assert a.keys() == b.keys() and a
    worst = max(abs(a[k] - b[k]) / max(abs(a[k]), 1e-30) for k in a)
    assert worst <= rtol, (worst, a, b)
    return worst


def test_ddp_resumed_equals_one_device(tmp_path):
    """DDP 2 x 8 trained 2 epochs, cut there and resumed to 3 under DDP, ends with the metrics
    of one device x 16 trained 3 epochs straight; rank 0 alone writes (one run directory, one
    epoch checkpoint beside last.ckpt)."""
    one, _ = _run(tmp_path, "one", *AE, "train.epochs=3", "train.batch_size=16")
    ddp, out = _run(tmp_path, "ddp", *AE, "train.epochs=2", "train.batch_size=8", *DDP)
    assert "DDP on 2 CPU processes, 8 samples each per step (effective batch 16)" in out
    # the run was cut after 2 of 3 epochs: the recipe asks for 3, the model and report are gone
    recipe = (ddp / "recipe.yaml").read_text()
    assert "epochs: 2" in recipe
    (ddp / "recipe.yaml").write_text(recipe.replace("epochs: 2", "epochs: 3"))
    # (as if it had started so: --resume refuses a recipe edited since the start, by its recorded hash)
    versions = json.loads((ddp / "versions.json").read_text())
    versions["recipe_sha256"] = hashlib.sha256((ddp / "recipe.yaml").read_bytes()).hexdigest()
    (ddp / "versions.json").write_text(json.dumps(versions))
    for p in ("models/ae.safetensors", "metrics.json", "report.md"):
        (ddp / p).unlink()
    out = _fwk(tmp_path, "run", "--resume", str(ddp)).stdout
    assert "ae: resuming from last.ckpt: 2 of 3 epochs done, continuing with epoch 3" in out
    _close(_means(ddp, "ae"), _means(one, "ae"), 1e-5)
    curves = [json.loads((d / "curves" / "ae" / "ae.json").read_text())["epochs"] for d in (one, ddp)]
    for a, b in zip(*curves):  # the recorded losses: the ranks' means averaged
        assert abs(a["train_loss"] - b["train_loss"]) <= 1e-5 * a["train_loss"]
        assert abs(a["val_loss"] - b["val_loss"]) <= 1e-5 * a["val_loss"]
    assert len(curves[1]) == 3
    assert {p.name for p in (ddp / "checkpoints" / "ae" / "ae").iterdir()} == {"last.ckpt", "epoch002.ckpt"}
    assert len(list((tmp_path / "ddp").iterdir())) == 1  # rank 1 wrote no run of its own


def test_reconstruct_smoke_recipe_on_two_processes(tmp_path):
    """The issue's command (renders off to save time): pca identical, the VAE within 10 % of one
    device with the same effective batch (2 x 16 against 1 x 32) on the train and test splits."""
    recipe = str(REPO / "recipes" / "smoke" / "reconstruct.yaml")
    one, _ = _run(tmp_path, "one", recipe, "renders=0", "train.batch_size=32")
    ddp, out = _run(tmp_path, "ddp", recipe, "renders=0", *DDP)
    assert "effective batch 32" in out
    assert _means(ddp, "pca") == _means(one, "pca")
    worst = _close(_means(ddp, "mlp-vae", ("train", "test")), _means(one, "mlp-vae", ("train", "test")), 0.10)
    assert worst > 0  # different noise, not the same run: the tolerance is not vacuous
