"""Shared by the benchmarks that reread a finished run's data (``pbs_band_errors.py``,
``dsm_band_errors.py``): its split and preprocessing rebuilt as the run made them."""
from __future__ import annotations

import json

from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
from fwk.data.split import SplitConfig


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
