"""What the example's recipe tests share: a tiny recipe around their own model lines, running it into
tmp_path, and the checks that every model was tested and trained.

A sibling module, not a test file: pytest's default (prepend) import mode puts this folder, which has
no ``__init__.py``, on ``sys.path`` before it imports the test files here, so they ``import recipe_runs``
whether they run alone or beside fwk's own ``tests`` package."""
import json
import textwrap
from pathlib import Path

import numpy as np
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from fwk.cache import Cache
from fwk.runs import execute


def tiny_recipe(models: str, *, task: str = "reconstruct", shapes: list[str] | None = None,
                epochs: int | None = 2, kl_weight: float | None = 1.0e-6) -> str:
    """A recipe of ``task`` on 16 synthetic heads of 300 vertices (seed 0, split 0.7/0.1/0.2), trained
    ``epochs`` epochs in batches of 8 at lr 1e-3 (no ``train:`` section where ``epochs`` is None;
    ``kl_weight`` None leaves it out), tested with l1 and no renders. ``models``: the ``models:``
    mapping's YAML (label: model lines, indented as one block), as the test writes it."""
    shapes = f", shapes: [{', '.join(shapes)}]" if shapes else ""
    kl = "" if kl_weight is None else f", kl_weight: {kl_weight:.1e}"
    train = "" if epochs is None else f"train: {{epochs: {epochs}, batch_size: 8, lr: 1.0e-3{kl}}}\n"
    models = textwrap.indent(textwrap.dedent(models).strip("\n"), "  ")
    return (f"task: {task}\nseed: 0\n"
            f"dataset: {{name: synthetic-heads, n_vertices: 300, n_subjects: 16{shapes}}}\n"
            f"split: {{ratios: [0.7, 0.1, 0.2]}}\n"
            f"{train}"
            f"models:\n{models}\n"
            "metrics: [l1]\nrenders: 0\n")


def run_recipe(tmp_path: Path, name: str, text: str, monkeypatch=None) -> Path:
    """Writes ``text`` to ``tmp_path / name`` and runs it quietly into ``tmp_path / "runs"`` with its
    cache in ``tmp_path / "cache"`` (``FWK_CACHE`` pointed there too where ``monkeypatch`` is given);
    returns the run directory."""
    if monkeypatch is not None:
        monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    recipe = tmp_path / name
    recipe.write_text(text)
    return execute(str(recipe), runs_dir=str(tmp_path / "runs"), quiet=True, cache=Cache(tmp_path / "cache"))


def assert_tested(run_dir: Path, labels, *, only: bool = False) -> dict:
    """Each of ``labels`` has a finite, positive test l1 in the run's metrics.json (``only``: and the
    run has no other model); returns metrics.json's ``models``."""
    metrics = json.loads((run_dir / "metrics.json").read_text())["models"]
    if only:
        assert set(metrics) == set(labels)
    for label in labels:
        l1 = metrics[label]["test"]["l1"]["mean"]
        assert np.isfinite(l1) and l1 > 0, label
    return metrics


def assert_trained(run_dir: Path, labels, epochs: int) -> None:
    """Each of ``labels`` logged one TensorBoard events folder whose every ``val_loss`` scalar (there
    is at least one) has ``epochs`` finite values: ``epochs`` epochs trained."""
    for label in labels:
        (events,) = {p.parent for p in (run_dir / "tb" / label).rglob("events.*")}
        ea = EventAccumulator(str(events))
        ea.Reload()
        val = [t for t in ea.Tags()["scalars"] if t.startswith("val_loss")]
        assert val and all(len(ea.Scalars(t)) == epochs and np.isfinite([e.value for e in ea.Scalars(t)]).all()
                           for t in val), label
