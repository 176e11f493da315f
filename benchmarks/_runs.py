"""Shared by the benchmarks that reread a finished run's data (``pbs_band_errors.py``,
``dsm_band_errors.py``): its split and preprocessing rebuilt as the run made them, and one table
row of L1, DAME and FMPD means in the units the claims docs print."""
from __future__ import annotations

import json

from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
from fwk.data.split import SplitConfig
from fwk.evaluation import evaluate

#: the metrics of the band tables and the factor each is printed in (x1e-3, x1e-2, x1e-2)
METRICS = {"l1": 1e3, "dame": 1e2, "fmpd": 1e2}


class _Quiet:
    """A stand-in run context for split_and_preprocess: writes and logs nothing."""

    def __getattr__(self, name):
        return lambda *a, **k: None


def run_data(run):
    """(collection, Preprocessor, {split: preprocessed collection}) of an opened run (``fwk.lifecycle.
    open_run``), rebuilt from its recipe's dataset, split, preprocessing and seed. The subjects are
    checked against the run's ``split.json``: a dataset that changed since is refused."""
    p = run.params
    col = p["dataset"].build().load(run.ctx.cache)
    split, pre, cols, _ = split_and_preprocess(col, p.get("split") or SplitConfig(),
                                               p.get("preprocess") or PreprocessConfig(), run.ctx.seed, _Quiet())
    saved = run.run_dir / "split.json"
    if saved.exists() and json.loads(saved.read_text()) != {k: list(v) for k, v in split.items()}:
        raise SystemExit(f"{saved}: the dataset's subjects differ from the run's split; is it the same data?")
    return col, pre, cols


def metric_cells(P, G, template, metrics) -> str:
    """``| L1 | DAME | FMPD |`` cells (means over the meshes, scaled by ``METRICS``) of meshes P
    against G; ``metrics`` are the instances of ``METRICS``' metrics, in that order."""
    res = evaluate(P, G, template, metrics)
    return " | ".join(f"{res[n]['scores'].mean() * f:.3f}" for n, f in METRICS.items()) + " |"
