"""The bf16 decision of issue 28 (item 2) from two finished seeds runs of one recipe, one per precision.

    python benchmarks/precision_decision.py FP32_RUN BF16_RUN [--split test]

Each RUN is a run with ``seeds:`` (``fwk run R --seeds 3`` and ``fwk run R --seeds 3
train.precision=bf16-mixed``); their recipes must be equal but for ``train.precision`` and ``name``
(any other difference is printed and refused). Prints, in markdown, one row per model (its networks
too: PBS's ``pbs:pb-...``) and metric on the split, and per expression of a blendshapes run: the
mean ± sd over seeds of each run, the relative difference, and whether it is within the seeds'
spread by the claims scripts' rule (``_claims.lower``: a difference within the larger of the two
sds is a tie). Then the decision per model: bf16 is adoptable for a model when every one of its
metrics (overall and per expression) is within the spread, and the training time of its networks
(the mean over seeds of the sum of their epochs' seconds, ``train_s``) in each precision.
No threshold is tuned: the rule is the seeds' sd.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import lower, networks  # noqa: E402

#: recipe keys that may differ between the two runs
FREE = ("name",)


def summaries(m: dict, split: str) -> dict:
    """{(model, where, metric): summary} of a seeds run's metrics.json: ``models/<model>/<split>/<metric>``
    (where ``all``) and, for a blendshapes run, ``blendshapes/<expression>/<model>/<metric>``."""
    out = {}
    for model, res in m.get("models", {}).items():
        for metric, s in (res.get(split) or {}).items():
            if isinstance(s, dict) and "mean" in s:
                out[model, "all", metric] = s
    if split == "test":  # the per-expression tables are the test split's
        for expr, models in (m.get("blendshapes") or {}).items():
            if not isinstance(models, dict):
                continue
            for model, res in models.items():
                for metric, s in (res if isinstance(res, dict) else {}).items():
                    if isinstance(s, dict) and "mean" in s:
                        out[model, expr, metric] = s
    return out


def train_seconds(m: dict, models) -> dict:
    """{model: mean over seeds of its networks' summed train_s} for the models that train networks
    (``_claims.networks``: keyed seed-<s>/<model>[/...])."""
    out = {}
    for model in models:
        per = {}
        for key, net in networks(m, model).items():
            if net.get("train_s") is not None:
                seed = key.split("/", 1)[0]
                per[seed] = per.get(seed, 0.0) + net["train_s"]
        if per:
            out[model] = sum(per.values()) / len(per)
    return out


def recipe_differences(a: dict, b: dict) -> list[str]:
    """Keys where the two recipes differ, other than train.precision and FREE."""
    a, b = dict(a), dict(b)
    for r in (a, b):
        for k in FREE:
            r.pop(k, None)
        r["train"] = {k: v for k, v in (r.get("train") or {}).items() if k != "precision"}
    return sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))


def _fmt(s: dict) -> str:
    return f"{s['mean']:.5g} ± {s['seed_sd']:.2g}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", type=Path, help="the fp32 seeds run")
    ap.add_argument("b", type=Path, help="the bf16 seeds run")
    ap.add_argument("--split", default="test")
    args = ap.parse_args(argv)
    runs = []
    for run in (args.a, args.b):
        f = run / "metrics.json"
        if not f.exists():
            raise SystemExit(f"{run}: no metrics.json (not a finished run)")
        m = json.loads(f.read_text())
        if len(m.get("seeds") or []) < 2:
            raise SystemExit(f"{run}: not a run of 2 or more seeds (fwk run R --seeds 3): one seed has no spread")
        recipe = yaml.safe_load((run / "recipe.yaml").read_text()) or {}
        runs.append((run, m, recipe, (recipe.get("train") or {}).get("precision", "32-true")))
    (ra, ma, rec_a, pa), (rb, mb, rec_b, pb) = runs
    diff = recipe_differences(rec_a, rec_b)
    if diff:
        raise SystemExit(f"the runs' recipes differ beyond train.precision: {', '.join(diff)}")
    if ma.get("seeds") != mb.get("seeds") or ma.get("split_seed") != mb.get("split_seed"):
        raise SystemExit(f"the runs have other seeds or splits: {ma.get('seeds')} / {ma.get('split_seed')} "
                         f"against {mb.get('seeds')} / {mb.get('split_seed')}")
    sa, sb = summaries(ma, args.split), summaries(mb, args.split)
    keys = [k for k in sa if k in sb]
    print(f"{args.split}: {ra.name} ({pa}) against {rb.name} ({pb}), seeds {ma['seeds']}\n")
    print(f"| model | expression | metric | {pa} | {pb} | difference | within the spread |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    beyond = {}
    for k in keys:
        a, b = sa[k], sb[k]
        tie = lower((a["mean"], a["seed_sd"]), (b["mean"], b["seed_sd"])) is None
        rel = (b["mean"] - a["mean"]) / abs(a["mean"]) if a["mean"] else 0.0
        if not tie:
            beyond.setdefault(k[0], []).append(f"{k[1]} {k[2]} {rel * 100:+.1f} %")
        print(f"| {k[0]} | {k[1]} | {k[2]} | {_fmt(a)} | {_fmt(b)} | {rel * 100:+.2f} % | {'yes' if tie else 'no'} |")
    models = list(dict.fromkeys(k[0] for k in keys))
    ta, tb = train_seconds(ma, models), train_seconds(mb, models)
    print(f"\nRule: a difference within the larger of the two runs' seed sd is within the spread (a tie). "
          f"{pb} is adoptable for a model when all of its metrics are.\n")
    for model in models:
        n = sum(1 for k in keys if k[0] == model)
        t = "" if model not in ta or model not in tb else \
            f"; training {ta[model]:.0f} s against {tb[model]:.0f} s a seed ({ta[model] / tb[model]:.2f}x)"
        if model not in ta and ":" not in model:  # no network of its own (DT): nothing to decide
            print(f"- {model}: trains no network, the precision does not apply (its {n} values: "
                  f"{'all within the spread' if model not in beyond else 'some beyond the spread'}).")
        elif model in beyond:
            print(f"- {model}: {pb} **not adoptable**: {len(beyond[model])} of {n} beyond the spread "
                  f"({', '.join(beyond[model])}){t}.")
        else:
            print(f"- {model}: {pb} **adoptable**: all {n} within the spread{t}.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
