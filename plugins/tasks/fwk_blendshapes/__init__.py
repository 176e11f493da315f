"""Task ``blendshapes``: personalised blendshapes from a neutral head (thesis chapter 5).

Data flow: dataset (neutral + named expressions per subject) -> split by subject (saved as
``split.json``) -> preprocessing fitted on the training neutrals (centring, rigid registration
to the mean neutral, one scale into [-1, 1]; a subject's expressions move with its neutral;
thesis 5.2.1; saved as ``stats/preprocess.npz`` with the topology in ``stats/template.npz``)
-> each model (``pb``, ``pbs``, ``dt``, any ``task_family = "blendshapes"`` model) fits on the
training subjects (``pbs`` also chooses its k per expression on the validation subjects) and
is saved as ``models/<label>.pt`` -> every model predicts every expression of the test
subjects from their neutrals -> l1, l2, euclidean, DAME, FMPD against the ground truth.

Report: the per-expression table in the layout of thesis table 5.2 (rows expression x metric,
a column per method), the end-to-end vs two-step table of table 5.1 where both modes ran,
PBS's k sweep on validation with the Pareto fronts and the chosen k (figure 5.8: L1 against
FMPD and against DAME, k labelled, front drawn), the method comparison on test (figure 5.9),
and renders of ground truth and every method with L1 and DAME maps (figures 5.4-5.6).
A ``pbs`` model also reports its two networks alone (``<label>:pb-euclidean-std``, the k = n
end, and ``<label>:pb-dr-norm``, its dr network registered onto the ground truth as the thesis
evaluates dr outputs): they are the two end-to-end PBs trained jointly with separate
parameters and losses, so a recipe need not train them twice (``pbs_ends: false`` turns the
rows off). ``fwk apply RUN_DIR NEUTRAL.obj`` reuses the saved model (``apply_model``).
"""
from __future__ import annotations

import time
from typing import Annotated

import numpy as np

from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
from fwk.data.split import SplitConfig
from fwk.errors import DataError, RecipeError
from fwk.evaluation import evaluate_summary
from fwk.hookspecs import hookimpl
from fwk.protocols import FitData
from fwk.recipes import Kind, Spec

DEFAULT_METRICS = ["l1", "l2", "euclidean", "dame", "fmpd"]
DISPLAY = {"l1": 1e-3, "l2": 1e-5, "euclidean": 1e-3, "dame": 1e-2, "fmpd": 1e-2}
LABEL = {"l1": "L1 norm", "l2": "L2 norm", "euclidean": "Euclidean", "dame": "DAME", "fmpd": "FMPD"}


def _f(x, m):
    return "n/a" if x is None or not np.isfinite(x) else f"{x / DISPLAY.get(m, 1.0):.4g}"


class Blendshapes:
    """Train personalised-blendshape models and compare them with Deformation Transfer on test subjects."""

    name = "blendshapes"

    def __init__(
        self,
        dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads",
        models: Annotated[dict[str, Spec], Kind("model")] | None = None,
        expressions: list[str] | None = None,
        split: SplitConfig | None = None,
        preprocess: PreprocessConfig | None = None,
        metrics: Annotated[list[Spec], Kind("metric")] | None = None,
        renders: int = 2,
        pbs_ends: bool = True,
        apply_model: str | None = None,
        write_obj: int = 0,
    ):
        if not models:
            raise RecipeError("models: a blendshapes recipe needs at least one model")
        if apply_model is not None and apply_model not in models:
            raise RecipeError(f"apply_model: {apply_model!r} is not one of the models ({', '.join(models)})")
        self.dataset, self.models, self.expressions = dataset, models, expressions
        self.split = split or SplitConfig()
        self.preprocess = preprocess or PreprocessConfig()
        self.metrics, self.renders, self.pbs_ends = metrics, renders, pbs_ends
        self.apply_model, self.write_obj = apply_model, write_obj

    # ------------------------------------------------------------------ data
    def _prepare(self, col, ctx):
        out = split_and_preprocess(col, self.split, self.preprocess, ctx.seed, ctx)
        t = col.template  # what `fwk apply` needs to check and undo a user's neutral
        ctx.save_npz("stats/template.npz", triangles=t.triangles, n_vertices=np.int64(t.n_vertices),
                     mean_neutral=out[1].mean_neutral)
        return out

    # ------------------------------------------------------------------ run
    def run(self, ctx):
        import torch

        ctx.log(f"loading dataset {getattr(self.dataset, 'name', self.dataset)}")
        col = ctx.build("dataset", self.dataset).load(ctx.cache)
        col.shape_index("neutral")
        expressions = list(self.expressions) if self.expressions else [s for s in col.shape_names if s != "neutral"]
        if not expressions:
            raise DataError(f"dataset {col.name} has no expression shapes (shapes: {', '.join(col.shape_names)})")
        for e in expressions:
            col.shape_index(e)
        split, pre, cols, transforms = self._prepare(col, ctx)
        template = col.template.with_vertices(pre.mean_neutral)
        data = FitData(template, cols["train"], cols["val"], ["neutral", *expressions])
        metrics = [ctx.build("metric", m) for m in (self.metrics or DEFAULT_METRICS)]
        ctx.log(f"{len(col.subjects)} subjects ({', '.join(f'{k} {len(v)}' for k, v in split.items())}), "
                f"{template.n_vertices} vertices, expressions {', '.join(expressions)}")

        test = cols["test"]
        j0 = test.shape_index("neutral")
        gt = {}
        for e in expressions:
            je = test.shape_index(e)
            ok = test.present[:, j0] & test.present[:, je]
            gt[e] = (np.flatnonzero(ok), np.asarray(test.positions[ok, j0]), np.asarray(test.positions[ok, je]))

        results = {"dataset": {"name": getattr(self.dataset, "name", self.dataset), "n_vertices": template.n_vertices,
                               "units": col.units, "scale": float(pre.scale),
                               "subjects": {k: len(v) for k, v in split.items()}},
                   "expressions": expressions, "models": {}, "blendshapes": {e: {} for e in expressions},
                   "timing": {}, "pbs": {}}
        preds = {e: {} for e in expressions}
        fitted = {}
        for label, spec in self.models.items():
            model = ctx.build("model", spec)
            family = getattr(model, "task_family", "reconstruct")
            if family != "blendshapes":
                raise RecipeError(f"models.{label}: {model.name} is a {family} model, not a blendshapes model")
            if getattr(model, "expressions", None) is None and hasattr(model, "expressions"):
                model.expressions = list(expressions)
            state = ctx.run_dir / "models" / f"{label}.pt"
            t0 = time.perf_counter()
            if ctx.resume and state.exists():
                ctx.log(f"[{label}] loading the finished model from {state}")
                model.load_state_dict(torch.load(state, weights_only=False))
            else:
                ctx.log(f"[{label}] fitting {model.name}")
                model.fit(data, ctx.scoped(label))
                ctx.save_torch(f"models/{label}.pt", model.state_dict())
            fit_s = time.perf_counter() - t0
            fitted[label] = model
            t0 = time.perf_counter()
            rows = self._predict(model, label, expressions, gt)
            pred_s = time.perf_counter() - t0
            n_pred = sum(len(gt[e][1]) for e in expressions)
            results["timing"][label] = {"fit_s": fit_s, "predict_s_per_mesh": pred_s / max(n_pred, 1)}
            for row_label, per_e in rows.items():
                for e, P in per_e.items():
                    preds[e][row_label] = P
            if hasattr(model, "sweep") and isinstance(getattr(model, "k", None), dict):
                results["pbs"][label] = {"k": dict(model.k), "sweep": model.sweep}
        # metrics
        row_labels = list(dict.fromkeys(r for e in expressions for r in preds[e]))
        for e in expressions:
            _, N, G = gt[e]
            for r, P in preds[e].items():
                if not np.all(np.isfinite(P)):
                    ctx.log(f"[{r}] warning: non-finite prediction for {e}")
                results["blendshapes"][e][r] = evaluate_summary(P, G, template, metrics, scale=pre.scale)
        for r in row_labels:
            have = [e for e in expressions if r in preds[e]]
            P = np.concatenate([preds[e][r] for e in have])
            G = np.concatenate([gt[e][2] for e in have])
            results["models"][r] = {"test": evaluate_summary(P, G, template, metrics, scale=pre.scale)}
        for e in expressions:
            ctx.log(f"test {e}: " + "; ".join(
                f"{r} l1={results['blendshapes'][e][r]['l1']['mean']:.4g}"
                + (f" dame={results['blendshapes'][e][r]['dame']['mean']:.4g}" if "dame" in results['blendshapes'][e][r] else "")
                for r in preds[e]))
        apply_label = self.apply_model or next((l for l, m in fitted.items() if m.name == "pbs"), next(iter(fitted)))
        results["apply_model"] = apply_label
        figures = self._figures(ctx, template, expressions, gt, preds, results, metrics)
        if self.write_obj:
            from fwk.data.io import write_obj

            for e in expressions:
                idx, _, _ = gt[e]
                n = min(self.write_obj, len(idx))
                T = transforms["test"].select(idx[:n])
                for r, P in preds[e].items():
                    Pin = pre.inverse(P[:n], T)
                    for i in range(n):
                        write_obj(ctx.path("predictions", r.replace(":", "_"), f"{test.subjects[idx[i]]}_{e}.obj"),
                                  Pin[i], col.template)
        from fwk.evaluation import write_report

        sections = self._tables(results, expressions, row_labels, [m.name for m in metrics])
        notes = [f"train epochs: {ctx.train.epochs} (recipe `train.epochs`; the thesis trained 500)",
                 f"evaluation space: registered and scaled into [-1, 1] (scale {pre.scale:.6g} per {col.units}); "
                 "numbers are means over test subjects",
                 "dr outputs of single PB models are rigidly registered onto the ground truth before scoring "
                 "(the thesis's protocol, 3.3.10); PBS and DT use no ground truth",
                 f"`fwk apply {ctx.run_dir} NEUTRAL.obj --out DIR` uses model `{apply_label}`"]
        write_report(ctx, f"Personalised blendshapes: {ctx.recipe.get('name', 'run')}", results, figures, notes,
                     sections)

    def _predict(self, model, label, expressions, gt) -> dict:
        """{row label: {expression: (b, n, 3)}}: the model, and a pbs model's two networks alone."""
        rows = {label: {}}
        if getattr(model, "name", "") == "dt" and hasattr(model, "predict_all"):
            # one factorisation per target neutral for every expression
            for e in expressions:
                if len(gt[e][1]):
                    rows[label][e] = model.predict_all(gt[e][1], [e])[e]
            return rows
        for e in expressions:
            _, N, G = gt[e]
            if not len(N):
                continue
            try:
                rows[label][e] = np.asarray(model.predict(N, e, target=G), dtype=np.float64)
            except TypeError:
                rows[label][e] = np.asarray(model.predict(N, e), dtype=np.float64)
            if self.pbs_ends and hasattr(model, "ends"):
                for name, P in model.ends(N, e, target=G).items():
                    rows.setdefault(f"{label}:{name}", {})[e] = P
        return rows

    # ------------------------------------------------------------------ tables
    def _summary(self, results, expressions, rows) -> str:
        """Plain sentences: does each PBS beat DT and its single PBs on L1 and on DAME?"""
        lines = []
        pbs = [r for r in rows if r in results["pbs"]]
        dts = [r for r in rows if r.startswith("dt")]
        for e in expressions:
            r = results["blendshapes"][e]
            for p in pbs:
                if p not in r:
                    continue
                others = [x for x in dts if x in r] + [x for x in rows if x.startswith(p + ":") and x in r]
                for m in ("l1", "dame"):
                    if m not in r[p]:
                        continue
                    v = r[p][m]["mean"]
                    better = [x for x in others if v < r[x][m]["mean"]]
                    worse = [x for x in others if v >= r[x][m]["mean"]]
                    parts = []
                    if better:
                        parts.append("beats " + ", ".join(f"{x} ({(1 - v / r[x][m]['mean']) * 100:.0f}% lower)" for x in better))
                    if worse:
                        parts.append("does not beat " + ", ".join(f"{x} ({(v / r[x][m]['mean'] - 1) * 100:.0f}% higher)" for x in worse))
                    lines.append(f"- {e}, {LABEL[m]}: `{p}` (k = {results['pbs'][p]['k'].get(e, 'n')}) " + "; ".join(parts) + ".")
        return "\n".join(lines)

    def _tables(self, results, expressions, rows, metric_names) -> list:
        sections = []
        summary = self._summary(results, expressions, rows)
        if summary:
            sections.append(("Summary: PBS against DT and the single PBs (test)", summary))
        cols = ["expression", "metric", *rows]
        body = []
        for e in expressions:
            for m in metric_names:
                r = results["blendshapes"][e]
                body.append([e, f"{LABEL.get(m, m)} ×{DISPLAY.get(m, 1.0):g}",
                             *(_f(r.get(x, {}).get(m, {}).get("mean"), m) for x in rows)])
        from fwk.evaluation import markdown_table

        sections.append(("Per expression (layout of thesis table 5.2)",
                         "Mean over test subjects in the evaluation space; lower is better; "
                         "the best value of each row is in bold.\n\n" + markdown_table(self._bold(body), cols)))
        # table 5.1: end-to-end vs two-step, where a recipe has both modes for one representation
        pairs = []
        for a in rows:
            for b in rows:
                ma, mb = self._mode(a), self._mode(b)
                if ma and mb and ma[0] == "end-to-end" and mb[0] == "two-step" and ma[1] == mb[1]:
                    pairs.append((a, b))
        if pairs:
            cols = ["expression", "metric"]
            for a, b in pairs:
                cols += [a, b, "change"]
            body = []
            for e in expressions:
                for m in metric_names:
                    r = results["blendshapes"][e]
                    row = [e, f"{LABEL.get(m, m)} ×{DISPLAY.get(m, 1.0):g}"]
                    for a, b in pairs:
                        va = r.get(a, {}).get(m, {}).get("mean")
                        vb = r.get(b, {}).get(m, {}).get("mean")
                        ch = f"{'↑' if vb > va else '↓'}{abs(vb / va - 1) * 100:.0f}%" if va and vb else "n/a"
                        row += [_f(va, m), _f(vb, m), ch]
                    body.append(row)
            sections.append(("End-to-end against two-step (layout of thesis table 5.1)",
                             "Change: the two-step model's error relative to the end-to-end one.\n\n"
                             + markdown_table(body, cols)))
        if results["pbs"]:
            lines = []
            for label, d in results["pbs"].items():
                for e, s in d["sweep"].items():
                    fronts = "; ".join(f"L1/{k[6:].upper()} front k = {s[k]}" for k in s if k.startswith("front_"))
                    lines.append(f"- `{label}` {e}: chosen k = **{s['chosen']}** of {len(s['ks'])} values "
                                 f"(knee of the L1/{s['knee_metric'].upper()} front on {s['n_subjects']} validation "
                                 f"subjects); {fronts}")
            sections.append(("PBS: Pareto-optimal k (thesis 5.3.4)",
                             "k = 0 is the dr network alone, k = n the euclidean network alone. The knee: both "
                             "objectives normalised to [0, 1] over the front, the front point farthest below the "
                             "chord joining its two ends.\n\n" + "\n".join(lines)))
        return sections

    @staticmethod
    def _mode(label):
        m = None
        for key in ("two-step", "end-to-end"):
            if key in label:
                m = key
        if m is None:
            return None
        rep = "dr" if "dr" in label else "euclidean"
        return m, rep

    @staticmethod
    def _bold(body):
        out = []
        for row in body:
            vals = []
            for x in row[2:]:
                try:
                    vals.append(float(x))
                except ValueError:
                    vals.append(np.inf)
            best = int(np.argmin(vals)) if vals and np.isfinite(min(vals)) else -1
            out.append(row[:2] + [f"**{x}**" if i == best else x for i, x in enumerate(row[2:])])
        return out

    # ------------------------------------------------------------------ figures
    def _figures(self, ctx, template, expressions, gt, preds, results, metrics) -> dict:
        from fwk.evaluation.plots import scatter_pareto

        figures = {}
        names = [m.name for m in metrics]
        for label, d in results["pbs"].items():
            for e, s in d["sweep"].items():
                for pm in ("fmpd", "dame"):
                    if pm not in s:
                        continue
                    pts = {str(k): (s["l1"][i], s[pm][i]) for i, k in enumerate(s["ks"])}
                    p = scatter_pareto(pts, ctx.path("figures", f"pbs_k_{label}_{e}_{pm}.png"), "L1 norm",
                                       pm.upper(), f"{e}: k sweep on validation (chosen k = {s['chosen']})")
                    figures[f"{label} {e}: L1 against {pm.upper()} for every k (figure 5.8)"] = p
        for e in expressions:
            r = results["blendshapes"][e]
            for pm in ("dame", "fmpd"):
                if pm not in names:
                    continue
                pts = {x: (r[x]["l1"]["mean"], r[x][pm]["mean"]) for x in r if "l1" in r[x]}
                p = scatter_pareto(pts, ctx.path("figures", f"methods_{e}_{pm}.png"), "L1 norm", pm.upper(),
                                   f"{e}: methods on test")
                figures[f"{e}: methods, L1 against {pm.upper()} on test (figure 5.9)"] = p
        if self.renders:
            figures.update(self._renders(ctx, template, expressions, gt, preds, metrics))
        return figures

    def _renders(self, ctx, template, expressions, gt, preds, metrics) -> dict:
        from fwk.evaluation import evaluate
        from fwk.evaluation.render import colour_limits

        by = {m.name: m for m in metrics}
        figures = {}
        for e in expressions:
            _, N, G = gt[e]
            n = min(self.renders, len(G))
            if not n:
                continue
            labels = list(preds[e])
            maps = {r: evaluate(preds[e][r][:n], G[:n], template, [by[k] for k in ("l1", "dame") if k in by])
                    for r in labels}
            for key in ("l1", "dame"):
                if key not in by:
                    continue
                # shared limits: one poor method saturates instead of washing out everyone else's map
                clim = colour_limits([maps[r][key]["maps"] for r in labels])
                rows = []
                for i in range(n):
                    row = [{"V": N[i], "label": f"neutral {i}"}, {"V": G[i], "label": "ground truth"}]
                    for r in labels:
                        row.append({"V": preds[e][r][i], "scalars": maps[r][key]["maps"][i], "clim": clim,
                                    "label": r, "bar": key.upper(), "cmap": "inferno" if key == "dame" else "viridis"})
                    rows.append(row)
                try:
                    from fwk.evaluation.render import render_grid

                    figures[f"{e}: test subjects with {key.upper()} error maps (figures 5.4-5.6)"] = render_grid(
                        rows, template, ctx.path("figures", f"render_{e}_{key}.png"), view="front")
                except Exception as exc:  # no OpenGL: keep the numbers
                    ctx.log(f"warning: renders skipped ({type(exc).__name__}: {exc})")
                    return figures
        return figures


@hookimpl
def fwk_register_tasks():
    return [Blendshapes]
