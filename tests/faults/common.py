"""Helpers of the fault-injection suite (its fixtures are in conftest.py): the smallest recipes,
runs in this process and in a subprocess that dies at a chosen point (``harness.py``), and the
checks every test makes."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from fwk.cli import main

HERE = Path(__file__).resolve().parent
HARNESS = HERE / "harness.py"

#: closed-form model only: no Lightning, a run takes about a second
PCA_RECIPE = """\
task: reconstruct
seed: 0
dataset: {name: synthetic-heads, n_vertices: 200, n_subjects: 12}
split: {ratios: [0.7, 0.15, 0.15]}
models: {pca: {name: pca, n_components: 3}}
metrics: [l1, l2]
renders: 0
"""

#: pca and a tiny trained network (three epochs, a checkpoint each)
TRAIN_RECIPE = PCA_RECIPE.replace(
    "models: {pca: {name: pca, n_components: 3}}",
    "train: {epochs: 3, batch_size: 4}\nmodels: {pca: {name: pca, n_components: 3}, "
    "mlp: {name: mlp-vae, latent: 4, hidden: [16]}}")


def recipe(tmp_path, text: str = PCA_RECIPE, name: str = "r") -> Path:
    p = tmp_path / f"{name}.yaml"
    p.write_text(text)
    return p


def run_dirs(runs: Path) -> list[Path]:
    return sorted(p for p in runs.iterdir() if p.is_dir()) if runs.exists() else []


def fwk_run(recipe_path: Path, runs: Path, *extra: str) -> tuple[int, Path | None]:
    """``fwk --quiet run`` in this process: (exit status, the one run directory or None)."""
    before = set(run_dirs(runs))
    rc = main(["--quiet", "run", str(recipe_path), *extra, "--runs-dir", str(runs)])
    new = [d for d in run_dirs(runs) if d not in before]
    assert len(new) <= 1
    return rc, (new[0] if new else None)


def resume(run_dir: Path) -> int:
    return main(["--quiet", "run", "--resume", str(run_dir)])


def killed_at(point: str, n: int, recipe_path: Path, runs: Path, env: dict, status: int = -9) -> Path:
    """Run the recipe in a subprocess that signals itself at ``point`` (the n-th time); asserts it
    ended with ``status`` (-9: SIGKILL), and returns its run directory."""
    p = subprocess.run([sys.executable, str(HARNESS), point, str(n), "--quiet", "run", str(recipe_path),
                        "--runs-dir", str(runs)], env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == status, f"the run did not end at {point} (exit {p.returncode}): {p.stderr[-2000:]}"
    (d,) = run_dirs(runs)
    return d


def models(run_dir: Path) -> dict:
    """Every metric value of every model and split (what must be identical after a fault)."""
    return json.loads((run_dir / "metrics.json").read_text())["models"]


def assert_complete(run_dir: Path) -> None:
    """A complete run: its files, no marker, no temporary file left behind."""
    for f in ("recipe.yaml", "versions.json", "split.json", "metrics.json", "report.md", "stats/preprocess.npz"):
        assert (run_dir / f).is_file(), f
    assert not (run_dir / "RUNNING").exists() and not (run_dir / "FAILED").exists()
    assert_no_temporary_files(run_dir)


def assert_no_temporary_files(folder: Path) -> None:
    left = [p for p in folder.rglob("*") if p.name.endswith(".tmp")]
    assert not left, left
