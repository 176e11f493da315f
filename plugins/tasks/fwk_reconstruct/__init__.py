"""Task ``reconstruct``: fit or train models on the train split and evaluate reconstructions.

The data flow of DESIGN.md: dataset -> split by subject (saved as ``split.json``) ->
preprocessing fitted on the training neutrals (centring, rigid registration to the mean
neutral, one uniform scale into [-1, 1]; thesis 3.3.8; saved under ``stats/``) -> each model
(a ``fwk.protocols.ReconstructionModel``) learns from the training shapes, or with ``--resume``
is reloaded (``fwk.lifecycle.build_models``, ``fit_models``: ``models/<label>.safetensors``) ->
``model.reconstruct`` on every split -> metrics (default ``fwk.evaluation.default_metrics``)
against the ground truth in the evaluation space (the thesis's space) and in the dataset's own
units -> ``metrics.json`` (and ``scores.json``: every test mesh's scores, which a run of several
seeds tests pairwise: ``fwk.evaluation.seeds``), ``report.md`` with tables, renders with error
maps and the standard scatters (L1 against DAME and FMPD) with their Pareto fronts.
"""
from __future__ import annotations

import time
from typing import Annotated

import numpy as np

from fwk import evaluation as ev
from fwk.data.io import write_obj
from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
from fwk.data.split import SplitConfig
from fwk.errors import RecipeError
from fwk.evaluation import default_metrics
from fwk.evaluation.legend import model_legend
from fwk.evaluation.report import standard_scatters
from fwk.hookspecs import hookimpl
from fwk.lifecycle import build_models, fit_models
from fwk.protocols import RECONSTRUCT, FitData, ReconstructionModel
from fwk.recipes import Kind, Spec

SPLITS = ("train", "val", "test")


class Reconstruct:
    """Train/fit models on the train split and evaluate reconstructions on train/val/test."""

    name = "reconstruct"

    def __init__(
        self,
        dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads",
        models: Annotated[dict[str, Spec], Kind("model", ReconstructionModel)] | None = None,
        split: SplitConfig | None = None,
        preprocess: PreprocessConfig | None = None,
        shapes: list[str] | None = None,
        metrics: Annotated[list[Spec], Kind("metric")] | None = None,
        renders: int = 2,
        save_predictions: bool = False,
        write_obj: int = 0,
    ):
        if not models:
            raise RecipeError("models: a reconstruct recipe needs at least one model")
        self.dataset = dataset
        self.models = models
        self.split = split or SplitConfig()
        self.preprocess = preprocess or PreprocessConfig()
        self.shapes = shapes or ["neutral"]
        self.metrics = metrics
        self.renders = renders
        self.save_predictions = save_predictions
        self.write_obj = write_obj

    def run(self, ctx):
        ctx.log(f"loading dataset {getattr(self.dataset, 'name', self.dataset)}")
        col = ctx.build("dataset", self.dataset).load(ctx.cache)
        for s in self.shapes:
            col.shape_index(s)
        split, pre, cols, transforms = split_and_preprocess(col, self.split, self.preprocess, ctx.seed, ctx)
        template = col.template.with_vertices(pre.mean_neutral)
        data = FitData(template, cols["train"], cols["val"], list(self.shapes))
        metrics = [ctx.build("metric", m) for m in (self.metrics or default_metrics(ctx.registry))]
        ctx.log(f"{len(col.subjects)} subjects ({', '.join(f'{k} {len(v)}' for k, v in split.items())}), "
                f"{template.n_vertices} vertices, shapes {', '.join(self.shapes)}")

        stacks = {name: FitData(template, cols[name], cols[name], list(self.shapes)).stack("train") for name in SPLITS}
        results: dict = {"models": {}, "timing": {}, "dataset": {"name": getattr(self.dataset, "name", self.dataset), "n_vertices": template.n_vertices,
                         "units": col.units, "scale": float(pre.scale), "subjects": {k: len(v) for k, v in split.items()}}}
        predictions = {}
        scores: dict = {"models": {}}  # per-subject test scores (fwk.evaluation.seeds' paired tests)
        built = build_models(self.models, RECONSTRUCT, ctx, data)  # all checked first
        # the report's legend: what each label is, as the model describes itself (fwk.evaluation.legend)
        results["legend"] = model_legend(self.models, built)
        fit_seconds = fit_models(built, data, ctx)  # side by side where one model cannot use the threads
        for label, model in built.items():
            fit_s = fit_seconds[label]
            results["models"][label] = {}
            predictions[label] = {}
            t0 = time.perf_counter()
            for name in SPLITS:
                P = stacks[name]
                if len(P) == 0:
                    continue
                pred = np.asarray(model.reconstruct(P), dtype=np.float64)
                if not np.all(np.isfinite(pred)):
                    ctx.log(f"[{label}] warning: non-finite reconstruction on {name}")
                predictions[label][name] = pred
                out = scores["models"].setdefault(label, {}).setdefault(name, {}) if name == "test" else None
                results["models"][label][name] = ev.evaluate_summary(pred, P, template, metrics, scale=pre.scale,
                                                                     scores_out=out)
            results["timing"][label] = {"fit_s": fit_s, "reconstruct_and_metrics_s": time.perf_counter() - t0}
            ctx.log(f"[{label}] test " + ", ".join(
                f"{m}={v['mean']:.4g}" for m, v in results["models"][label].get("test", {}).items()))
        ctx.write_json("scores.json", scores)
        if self.save_predictions:
            for label, d in predictions.items():
                ctx.save_npz(f"predictions/{label}.npz", **d)
        figures = ev.reconstruction_figures(ctx, template, stacks, predictions, metrics, n_rows=self.renders,
                                             scale=pre.scale)
        figures.update(standard_scatters(ctx, results, "test", registry=ctx.registry))
        if self.write_obj:
            self._write_objs(ctx, col.template, pre, transforms, predictions, stacks)
        ev.write_report(ctx, f"Reconstruction: {ctx.recipe.get('name', 'run')}", results, figures,
                        notes=[f"train epochs: {ctx.train.epochs} (recipe `train.epochs`)",
                               f"evaluation space: registered and scaled into [-1, 1] (scale {pre.scale:.6g} per {col.units})"])

    def _write_objs(self, ctx, template, pre, transforms, predictions, stacks):
        n = min(self.write_obj, len(stacks["test"]))
        for label, d in predictions.items():
            if "test" not in d:
                continue
            # neutral-only stacks map one-to-one onto test subjects
            if len(d["test"]) != len(transforms["test"].rotation):
                continue
            P = pre.inverse(d["test"][:n], transforms["test"].select(np.arange(n)))
            for i in range(n):
                write_obj(ctx.path("predictions", label, f"test_{i:03d}.obj"), P[i], template)


@hookimpl
def fwk_register_tasks():
    return [Reconstruct]
