"""Claims C5 and C6 (thesis 5.2.3 table 5.1; 5.3.5 table 5.2) from a finished chapter 5 run (issue 13).

    python benchmarks/claims_ch5.py RUN [--split test]

RUN is a run of ``recipes/thesis/ch5/plateau.yaml`` (a blendshapes run). Its models are found by
their labels: ``<x>-two-step`` is a two-step PB whose end-to-end partner is the label ending in
``:<x>`` or equal to ``<x>`` (PBS's parts reported alone are ``pbs:pb-euclidean-std`` and
``pbs:pb-dr-norm``); the cut-selecting models are those with a k sweep (metrics.json ``pbs``);
Deformation Transfer is every label starting with ``dt``. Prints, in markdown:

* every model's L1, DAME and FMPD per expression (mean, ± the seeds' sd with seeds), the page's
  chapter 5 table;
* C5 per pair and expression (thesis 5.2.3, table 5.1, l. 2117-2131): DAME and FMPD (and L1) of
  end-to-end against two-step, and whether end-to-end is lower on both perceptual metrics. C5
  "holds" for a pair when it is on more than half of the expressions. Also how many expressions
  end-to-end has the lower L1 on (table 5.1: two-step Eucl. Std. 1-3 % lower, two-step DR Norm.
  6-15 % higher);
* C6 per PBS model and expression (5.3.5, l. 2241; table 5.2, l. 2162-2177): L1 and DAME of PBS
  against each DT source, DT's excess over PBS in % (the thesis: DT +61.11, +60.15 and +32.47 %
  in L1 on its three expressions), and whether PBS is lower on both. C6 "holds" when PBS is lower
  on both than every source on more than half of the expressions; the same count for L1 alone and
  DAME alone is printed beside it;
* C9 (5.3.4, l. 2225-2235): the k PBS chose per expression (the thesis: 440, 380 and 200); it
  "holds" when the chosen k are not all equal (the Pareto-optimal k vary across expressions); in a
  run with seeds whose seeds chose different k, the k per seed, and the claim counted over the
  seeds by the rule (holds on more than half, partly on some);
* C10 (5.3.5, l. 2243): PBS against its end-to-end Eucl. Std. network (``<pbs>:pb-euclidean-std``)
  on L1 (the thesis: that network's L1 0.14, 0.37 and 0.16 % above PBS's); "holds" when PBS is
  lower on more than half of the expressions;
* C14 (5.4 / 6.1, l. 2288: "both approaches outperform the Deformation Transfer"): each two-step PB
  against every DT source, on L1 and on DAME separately (in the thesis's own tables 5.1 and 5.2
  two-step is lower on L1 than DT on all three expressions and higher on DAME on all three);
* the training of every network: epochs, what ended it, the plateau rule's verdict, minutes
  (the sum of the epochs' own seconds, a resumed run's earlier epochs included).

Comparisons and ties: ``_claims.RULE`` (printed).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import CLOSE, RULE, fmt, lower, margin, pct, qualify, seeded, verdict  # noqa: E402


def by_seed(k, seeds=("0",)) -> dict:
    """{seed: k} of a chosen k as metrics.json gives it: a number (one seed, or every one of the
    run's ``seeds`` chose it) or {"by_seed": {seed: k}} (seeds that chose different k)."""
    if isinstance(k, dict) and "by_seed" in k:
        return {str(sd): v for sd, v in k["by_seed"].items()}
    return {str(sd): k for sd in seeds}


def pairs(labels) -> list[tuple[str, str]]:
    """(end-to-end, two-step) label pairs: ``<x>-two-step`` with ``<x>`` or ``...:<x>``."""
    out = []
    for b in labels:
        if not b.endswith("-two-step"):
            continue
        x = b[: -len("-two-step")]
        a = next((a for a in labels if a == x or a.endswith(":" + x)), None)
        if a is not None:
            out.append((a, b))
    return out


#: the metrics of the overview table and the factor each is printed in
SCALES = {"l1": 1e3, "dame": 1e2, "fmpd": 1e2}


def overview(per: dict, exprs: list, labels: list) -> str:
    """One row per expression and metric, one column per model (docs/methods/claims.md's chapter 5
    table): mean (± the seeds' sd) scaled by SCALES, the lowest mean in bold."""
    lines = [f"| expression | metric | {' | '.join(labels)} |", "| --- | --- |" + " --- |" * len(labels)]
    for e in exprs:
        for k, f in SCALES.items():
            vals = {lb: per[e].get(lb, {}).get(k) for lb in labels}
            means = {lb: v["mean"] for lb, v in vals.items() if v is not None}
            best = min(means.values()) if means else None
            cells = ["" if v is None else (f"**{fmt(v, f)}**" if v["mean"] == best else fmt(v, f))
                     for v in vals.values()]
            lines.append(f"| {e} | {k.upper()} ×1e-{round(math.log10(f))} | {' | '.join(cells)} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--split", default="test", help="(the blendshapes task reports the test split)")
    a = ap.parse_args(argv)
    m = json.loads((a.run / "metrics.json").read_text())
    per = m["blendshapes"]  # {expression: {label: {metric: {mean: ...}}}}
    exprs = list(per)
    labels = list(dict.fromkeys(lb for e in exprs for lb in per[e]))
    mean = lambda e, lb, k: per[e].get(lb, {}).get(k, {}).get("mean")  # noqa: E731
    yes = lambda b: "yes" if b else "no"  # noqa: E731

    get = lambda e, lb, k: per[e].get(lb, {}).get(k)  # noqa: E731
    print(f"Every model ({a.run.name}, {a.split}, mean over subjects, evaluation space; ± the seeds' sd in a run "
          f"with seeds; the lowest mean in bold)\n")
    print(overview(per, exprs, labels))
    print(RULE + "\n")
    print(f"C5: end-to-end against two-step PB ({a.run.name}, {a.split}, mean over subjects, evaluation space)\n")
    print("| end-to-end | two-step | expression | L1 ×1e-3 e2e / 2-step | DAME ×1e-2 e2e / 2-step | "
          "FMPD ×1e-2 e2e / 2-step | e2e lower DAME and FMPD |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    verdicts = []
    for e2e, two in pairs(labels):
        n_yes = n_ties = n_l1 = 0
        close, seeds = [], False
        for e in exprs:
            c = {k: lower(get(e, e2e, k), get(e, two, k)) for k in ("dame", "fmpd")}
            ok = c["dame"] is True and c["fmpd"] is True
            n_yes += ok
            n_ties += ok and all(lower(get(e, e2e, k), get(e, two, k), CLOSE) is True for k in ("dame", "fmpd"))
            n_l1 += lower(get(e, e2e, "l1"), get(e, two, "l1")) is True
            seeds |= seeded(get(e, e2e, "dame"))
            close += [f"{e} {k.upper()} {pct(margin(get(e, e2e, k), get(e, two, k)))}" for k in ("dame", "fmpd")
                      if ok and margin(get(e, e2e, k), get(e, two, k)) < CLOSE]
            word = yes(ok) if (c["dame"] is not None and c["fmpd"] is not None) else "tie"
            cells = " | ".join(f"{fmt(get(e, e2e, k), f)} / {fmt(get(e, two, k), f)}"
                               for k, f in (("l1", 1e3), ("dame", 1e2), ("fmpd", 1e2)))
            print(f"| {e2e} | {two} | {e} | {cells} | {word} |")
        n = len(exprs)
        verdicts.append(f"C5, {e2e} against {two}: end-to-end lower on both perceptual metrics for {n_yes} of "
                        f"{n} expressions: {qualify(verdict(n_yes, n), close, f'{n_ties} of {n}, {verdict(n_ties, n)}', seeds)}. "
                        f"End-to-end lower L1 on {n_l1} of {n}.")
    print("\n" + "\n".join(verdicts))

    pbs = [lb for lb in m.get("pbs", {}) if lb in labels]
    dts = [lb for lb in labels if lb.startswith("dt")]
    print(f"\nC6: PBS against Deformation Transfer ({a.split})\n")
    print("| PBS | DT | expression | k | L1 ×1e-3 PBS / DT | DT's L1 excess | DAME ×1e-2 PBS / DT | DT's DAME excess "
          "| PBS lower on both |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    verdicts = []
    for p in pbs:
        got, got_t = {"both": [], "l1": [], "dame": []}, []
        close, seeds = [], False
        for e in exprs:
            k = by_seed(m["pbs"][p].get("k", {}).get(e, ""))
            k = " / ".join(str(v) for v in k.values())  # one k, or one per seed
            lo = {"l1": True, "dame": True}
            for d in dts:
                l1 = (mean(e, p, "l1"), mean(e, d, "l1"))
                dame = (mean(e, p, "dame"), mean(e, d, "dame"))
                c = {x: lower(get(e, p, x), get(e, d, x)) for x in ("l1", "dame")}
                for x in lo:
                    lo[x] &= c[x] is True
                seeds |= seeded(get(e, p, "l1"))
                print(f"| {p} | {d} | {e} | {k} | {fmt(get(e, p, 'l1'), 1e3)} / {fmt(get(e, d, 'l1'), 1e3)} | "
                      f"{(l1[1] / l1[0] - 1) * 100:+.1f} % | {fmt(get(e, p, 'dame'), 1e2)} / {fmt(get(e, d, 'dame'), 1e2)} | "
                      f"{(dame[1] / dame[0] - 1) * 100:+.1f} % | "
                      f"{yes(c['l1'] is True and c['dame'] is True)} |")
            got["both"].append(lo["l1"] and lo["dame"])
            got_t.append(lo["l1"] and lo["dame"] and all(lower(get(e, p, x), get(e, d, x), CLOSE) is True
                                                         for x in ("l1", "dame") for d in dts))
            got["l1"].append(lo["l1"])
            got["dame"].append(lo["dame"])
            close += [f"{e} {x.upper()} against {d} {pct(margin(get(e, p, x), get(e, d, x)))}" for x in ("l1", "dame")
                      for d in dts if lo[x] and margin(get(e, p, x), get(e, d, x)) < CLOSE]
        n = len(exprs)
        part = {x: f"{sum(got[x])} of {n}: {verdict(sum(got[x]), n)}" for x in got}
        verdicts.append(f"C6, {p}: lower L1 and DAME than every DT source for {sum(got['both'])} of {n} expressions: "
                        f"{qualify(verdict(sum(got['both']), n), close, f'{sum(got_t)} of {n}, {verdict(sum(got_t), n)}', seeds)}. "
                        f"L1 alone {part['l1']}; DAME alone {part['dame']}.")
        run_seeds = [str(sd) for sd in m.get("seeds") or [0]]
        ks = {e: by_seed(k, run_seeds) for e, k in m["pbs"][p].get("k", {}).items() if e in exprs}
        if ks:
            seeds_k = sorted({sd for v in ks.values() for sd in v}, key=int)
            differ = [len({ks[e].get(sd) for e in ks}) > 1 for sd in seeds_k]
            shown = ", ".join(f"{e} {' / '.join(str(ks[e].get(sd)) for sd in seeds_k)}" for e in exprs if e in ks)
            if len(seeds_k) == 1:
                verdicts.append(f"C9, {p}: chosen k {shown}: {verdict(sum(differ), 1)} (the k differ across "
                                f"expressions: {yes(differ[0])}).")
            else:
                verdicts.append(f"C9, {p}: chosen k {shown} (seeds {', '.join(seeds_k)}): the k differ across "
                                f"expressions on {sum(differ)} of {len(differ)} seeds: "
                                f"{verdict(sum(differ), len(differ))}.")
        sp = next((lb for lb in labels if lb.startswith(p + ":") and "euclidean" in lb), None)
        if sp is not None:
            c = [lower(get(e, p, "l1"), get(e, sp, "l1")) for e in exprs]
            mg = [margin(get(e, p, "l1"), get(e, sp, "l1")) for e in exprs]
            n_yes = sum(x is True for x in c)
            cl = [f"{e} {pct(x)}" for e, x, y in zip(exprs, mg, c) if y is not None and x < CLOSE]
            excess = ", ".join(f"{e} {(mean(e, sp, 'l1') / mean(e, p, 'l1') - 1) * 100:+.1f} %" for e in exprs)
            n_t = sum(lower(get(e, p, "l1"), get(e, sp, "l1"), CLOSE) is True for e in exprs)
            word = qualify(verdict(n_yes, n), cl, f"{n_t} of {n}, {verdict(n_t, n)}", seeded(get(exprs[0], p, "l1")))
            verdicts.append(f"C10, {p} against {sp} on L1: PBS lower for {n_yes} of {n} expressions "
                            f"(its L1 against PBS's: {excess}): {word}.")
    for _, two in pairs(labels):
        got = {"l1": 0, "dame": 0}
        for e in exprs:
            for x in got:
                got[x] += all(lower(get(e, two, x), get(e, d, x)) is True for d in dts)
        n = len(exprs)
        if dts:
            verdicts.append(f"C14, {two} against every DT source: lower L1 for {got['l1']} of {n} expressions: "
                            f"{verdict(got['l1'], n)}; lower DAME for {got['dame']} of {n}: {verdict(got['dame'], n)} "
                            f"({'over seeds' if seeded(get(exprs[0], two, 'l1')) else 'one seed'}).")
    print("\n" + "\n".join(verdicts))

    nets = m.get("training", {}).get("networks", {})
    if nets:
        print("\n| network | epochs | ended by | verdict | train min |\n| --- | --- | --- | --- | --- |")
        for name, t in nets.items():
            mins = "" if t.get("train_s") is None else f"{t['train_s'] / 60:.1f}"
            print(f"| {name} | {t['epochs_run']}/{t['max_epochs']} | {t['stopped_by']} | {t['plateau']} | {mins} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
