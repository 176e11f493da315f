"""Claims C1, C2, C12, C13 and C15 (thesis 3.5) from a finished chapter 3 grid run (issues 13, 26).

    python benchmarks/claims_ch3.py RUN [MORE_RUN ...] [--split test]

RUN is a run of ``recipes/thesis/ch3/plateau.yaml`` (members ``<conv>-<representation>``, each with
``metrics.json``; unfinished members are listed as missing). Each MORE_RUN's members replace the
members of the same name before it (a seeds run of some members read after the one-seed run of
all: ``recipes/thesis/ch3/feast-variance-seeds.yaml`` after ``feast-variance.yaml``); the output
names the members taken from later runs. Prints, in markdown:

* one row per conv: L1 and DAME (and L2, FMPD) of each representation on the split, mean over
  meshes in the evaluation space, with each member's epochs, what ended its training, the
  plateau rule's verdict (the report's Training section) and its training minutes (the sum of its
  epochs' seconds, resumed runs included);
* C1 per conv (thesis 3.5.1, tables 3.3-3.5): whether a Euclidean-based representation
  (Euclidean or Euclidean Std., the better of the two) has the lower L1 (and L2) than DR Norm., and
  DR Norm. the lower DAME (and FMPD) than both; the verdict counts L1 and DAME. The thesis takes
  the better of DR and DR Norm.; these runs have DR Norm. only;
* C2 per conv (thesis 3.5.2, tables 3.3-3.5): whether Euclidean Std. has a lower L1 and a lower
  DAME than Euclidean;
* C13 (thesis 3.5.3, l. 1483): the L1/DAME Pareto front over every (conv, representation) member,
  and whether the pair the thesis names as the fair balance on Facsimile's test set (LSA-3DMM and
  the Mesh Autoencoder (vcconv), each with Euclidean Std.) is on it;
* C15 (a run of ``recipes/thesis/ch3/feast-variance.yaml``, whose ``mean-shape`` member is the
  baseline): how many FeaStNet members have both L1 and DAME below the mean shape's (ties and
  one-seed margins as for the others);
* C12 (a run with raw-DR members ``<conv>-dr`` beside ``<conv>-dr-norm``,
  ``recipes/thesis/ch3/plateau-dr.yaml``): per conv, whether normalising DR lowers (positive) or
  raises (negative) the majority of L1, L2, DAME and FMPD, against the thesis's sign (``c12``).

Verdicts: ``_claims.RULE`` (printed): a verdict "holds" when its comparison goes the claim's way
for more than half of the complete convs, "partly" for some, "does not hold" for none; on one
seed the deciding margins under 10 % are listed with the verdict they would give as ties.
No threshold is tuned: a comparison is the sign of a difference of means.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import (CLOSE, RULE, fmt, lower, margin, pct, qualify_cases, seeded, training,  # noqa: E402
                     verdict, yes)
from fwk.evaluation.core import pareto_front  # noqa: E402

REPS = ("euclidean", "euclidean-std", "dr-norm")
#: raw DR (``<conv>-dr``): C12's run (``recipes/thesis/ch3/plateau-dr.yaml``) has it beside DR Norm.
OPTIONAL_REPS = ("dr",)
CONVS = ("spiral", "spiralpp", "feast", "lsa", "vcconv")
METRICS = ("l1", "l2", "dame", "fmpd")
#: thesis 3.5.2 (l. 1441), Facsimile's test set: the overall impact of normalising DR per model
C12_THESIS = {"spiral": "negative", "spiralpp": "negative", "feast": "negative", "lsa": "positive",
              "vcconv": "positive"}


def load(run: Path, split: str) -> dict:
    """{(conv, rep): {metric: mean, "epochs": ..., "ended": ..., "verdict": ...}} of finished members."""
    out = {}
    for conv in CONVS:
        for rep in REPS + OPTIONAL_REPS:
            f = run / f"{conv}-{rep}" / "metrics.json"
            if not f.exists():
                continue
            m = json.loads(f.read_text())
            (label, res), = m["models"].items()
            row = {k: v["mean"] for k, v in res[split].items()}
            row["_sd"] = {k: v.get("seed_sd") for k, v in res[split].items()}
            t = training(m, label, run / f"{conv}-{rep}")
            row.update(epochs=t["epochs"], ended=t["ended"], verdict=t["verdict"], fit_min=t["minutes"])
            out[conv, rep] = row
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("more", type=Path, nargs="*", help="runs whose members replace those of the same name")
    ap.add_argument("--split", default="test")
    a = ap.parse_args(argv)
    runs = [a.run, *a.more]
    rows, base = {}, None
    for run in runs:
        got = load(run, a.split)
        for r in got.values():
            r["run"] = run.name
        rows.update(got)
        base = mean_shape(run, a.split) or base
    print(f"{a.split}, evaluation space, mean over meshes ({', '.join(r.name for r in runs)})\n")
    print("| conv | representation | L1 ×1e-3 | L2 ×1e-5 | DAME ×1e-2 | FMPD ×1e-2 | epochs | ended by | verdict | fit min |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    shown = REPS + tuple(rep for rep in OPTIONAL_REPS if any(k[1] == rep for k in rows))
    for conv in CONVS:
        for rep in shown:
            r = rows.get((conv, rep))
            if r is None:
                print(f"| {conv} | {rep} | missing | | | | | | | |")
                continue
            cells = " | ".join(fmt(_pair(r, k), f) for k, f in (("l1", 1e3), ("l2", 1e5), ("dame", 1e2), ("fmpd", 1e2)))
            print(f"| {conv} | {rep} | {cells} | {r['epochs']} | {r['ended']} | {r['verdict']} | "
                  f"{'' if r['fit_min'] is None else format(r['fit_min'], '.1f')} |")
    print("\n| conv | C1: Euclidean-based lower L1 | lower L2 | C1: DR Norm. lower DAME | lower FMPD | "
          "C2: Std. lower L1 | C2: Std. lower DAME |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    res = c1_c2(rows)
    for conv in CONVS:
        r = res["convs"].get(conv)
        print(f"| {conv} | incomplete | | | | | |" if r is None else
              f"| {conv} | {yes(r['l1'])} | {yes(r['l2'])} | {yes(r['dame'])} | {yes(r['fmpd'])} | "
              f"{yes(r['std_l1'])} | {yes(r['std_dame'])} |")
    print(f"\n{RULE}\n")
    for c in ("C1", "C2"):
        print(res[c])
    print(c12(rows))
    front, line = c13(rows)
    print(f"\nL1/DAME front over the {len(rows)} finished members: {', '.join(f'{c}-{r}' for c, r in front)}.")
    print(line)
    if a.more:
        later = [f"{c}-{r} ({v['run']})" for (c, r), v in rows.items() if v["run"] != a.run.name]
        print(f"\nMembers from later runs: {', '.join(later) or 'none'}.")
    print(c15(rows, base))
    return 0


def c12(rows: dict) -> str:
    """C12 (thesis 3.5.2, l. 1441: normalising DR helps the Mesh Autoencoder and LSA-3DMM and hurts
    FeaStNet, Neural 3DMM and SpiralNet++ on Facsimile's test set). Per conv with both a ``dr`` and a
    ``dr-norm`` member, normalisation's impact over the four metrics (L1, L2, DAME, FMPD): positive
    when DR Norm. is lower on at least 3 of them, negative when raw DR is, else mixed (ties count for
    neither). The thesis's own words follow this count: the Mesh Autoencoder lower on L1, L2 and DAME
    (FMPD +36 %), LSA-3DMM on L1, L2 and FMPD (DAME +36 %), the other three higher on all four. The
    claim holds for a conv when the impact has the thesis's sign."""
    convs = [c for c in CONVS if (c, "dr") in rows and (c, "dr-norm") in rows]
    if not convs:
        return "C12 (normalising DR helps vcconv and lsa, hurts spiral, spiral++ and feast): not measured (no conv has both a dr and a dr-norm member)."
    parts, close, on_seeds, n_match, n_match_t = [], [], [], 0, 0

    def impact(c):
        down, up = sum(x is True for x in c), sum(x is False for x in c)
        return "positive" if down >= 3 else "negative" if up >= 3 else "mixed"

    for conv in convs:
        raw, norm = rows[conv, "dr"], rows[conv, "dr-norm"]
        pair = {k: (_pair(norm, k), _pair(raw, k)) for k in METRICS}
        c = [lower(*pair[k]) for k in METRICS]
        both = seeded(pair["l1"][0]) and seeded(pair["l1"][1])  # ties by the seeds' sd only when both have seeds
        if both:
            on_seeds.append(conv)
        got = impact(c)
        ok = got == C12_THESIS[conv]
        n_match += ok
        n_match_t += ok and (both or impact([lower(*pair[k], CLOSE) for k in METRICS]) == got)
        if ok and not both:
            close += [f"{conv} {k.upper()} {pct(margin(*pair[k]))}" for k, x in zip(METRICS, c)
                      if x is not None and margin(*pair[k]) < CLOSE]
        ratios = ", ".join(f"{k.upper()} {norm[k] / raw[k]:.2f}x{'' if x is not None else ' (tie)'}"
                           for k, x in zip(METRICS, c))
        parts.append(f"{conv} {got} (DR Norm. over DR: {ratios}; thesis: {C12_THESIS[conv]})")
    k = len(convs)
    word = qualify_cases(verdict(n_match, k), close, f"{n_match_t} of {k}, {verdict(n_match_t, k)}", on_seeds, k)
    return (f"C12 (normalising DR: the impact over L1, L2, DAME and FMPD has the thesis's sign): {n_match} of {k} "
            f"convs ({'; '.join(parts)}): {word}.")


def mean_shape(run: Path, split: str) -> dict | None:
    """The ``mean-shape`` member's means on ``split`` (feast-variance.yaml's baseline: pca with no
    component, the training mean), or None where the run has none."""
    f = run / "mean-shape" / "metrics.json"
    if not f.exists():
        return None
    (res,) = json.loads(f.read_text())["models"].values()
    out = {k: v["mean"] for k, v in res[split].items()}
    out["_sd"] = {k: v.get("seed_sd") for k, v in res[split].items()}
    return out


def c15(rows: dict, base: dict | None) -> str:
    """C15 (FeaStNet moves off the mean shape; fwk's reading of tables 3.3-3.5, not the thesis's
    words): for each finished feast member, whether its L1 and its DAME are both below the mean
    shape's (a network that stays at the mean shape has neither), ties and one-seed margins as for
    the other claims (``_claims.lower``, ``qualify``)."""
    feast = [(rep, rows[("feast", rep)]) for rep in REPS if ("feast", rep) in rows]
    if base is None or not feast:
        return "C15 (FeaStNet moves off the mean shape): not measured (no mean-shape member, or no finished feast member)."
    n = n_ties = 0
    close, on_seeds, parts = [], [], []
    for rep, r in feast:
        seeds = seeded(_pair(r, "l1"), _pair(r, "dame"))
        if seeds:  # its ties are decided by the seeds' sd; a one-seed member's close margins are listed
            on_seeds.append(rep)
        comps = [(name, _pair(r, m), _pair(base, m)) for name, m in (("L1", "l1"), ("DAME", "dame"))]
        below = [lower(a, b) for _, a, b in comps]
        ok = all(x is True for x in below)
        n += ok
        n_ties += ok and (seeds or all(lower(a, b, CLOSE) is True for _, a, b in comps))
        close += [f"{rep} {name} {pct(margin(a, b))}" for name, a, b in comps
                  if ok and margin(a, b) < CLOSE and not seeds]
        sd = {m: "" if r.get("_sd", {}).get(m) is None else f" ± {r['_sd'][m] * k:.3f}"
              for m, k in (("l1", 1e3), ("dame", 1e2))}
        parts.append(f"{rep} L1 {r['l1'] * 1e3:.3f}{sd['l1']} / DAME {r['dame'] * 1e2:.3f}{sd['dame']}")
    k = len(feast)
    word = qualify_cases(verdict(n, k), close, f"{n_ties} of {k}, {verdict(n_ties, k)}", on_seeds, k)
    return (f"C15 (FeaStNet moves off the mean shape: L1 and DAME below the mean shape's, {base['l1'] * 1e3:.3f}e-3 / "
            f"{base['dame'] * 1e2:.3f}e-2): {n} of {k} feast members ({', '.join(parts)}): {word}.")


def _pair(r: dict, k: str):
    return r[k], r.get("_sd", {}).get(k)


def c1_c2(rows: dict) -> dict:
    """Per complete conv the C1 and C2 comparisons (True / False / None = tie) and the two verdict lines."""
    convs, close, seeded_convs = {}, {"C1": [], "C2": []}, []
    n = {"C1": [0, 0], "C2": [0, 0]}  # [by the sign, counting margins under 10 % as ties]
    for conv in CONVS:
        r = {rep: rows.get((conv, rep)) for rep in REPS}
        if any(v is None for v in r.values()):
            continue
        e, s, d = r["euclidean"], r["euclidean-std"], r["dr-norm"]
        be = {m: min((e, s), key=lambda x: x[m]) for m in ("l1", "l2", "dame", "fmpd")}  # the better Euclidean-based
        c = {"l1": lower(_pair(be["l1"], "l1"), _pair(d, "l1")), "l2": lower(_pair(be["l2"], "l2"), _pair(d, "l2")),
             "dame": lower(_pair(d, "dame"), _pair(be["dame"], "dame")),
             "fmpd": lower(_pair(d, "fmpd"), _pair(be["fmpd"], "fmpd")),
             "std_l1": lower(_pair(s, "l1"), _pair(e, "l1")), "std_dame": lower(_pair(s, "dame"), _pair(e, "dame"))}
        convs[conv] = c
        on_seeds = seeded(_pair(d, "l1"), _pair(s, "l1"), _pair(e, "l1"))
        if on_seeds:  # its ties are decided by the seeds' sd; a one-seed conv's close margins are listed
            seeded_convs.append(conv)
        deciding = {"C1": [("L1", _pair(be["l1"], "l1"), _pair(d, "l1"), c["l1"]),
                           ("DAME", _pair(d, "dame"), _pair(be["dame"], "dame"), c["dame"])],
                    "C2": [("L1", _pair(s, "l1"), _pair(e, "l1"), c["std_l1"]),
                           ("DAME", _pair(s, "dame"), _pair(e, "dame"), c["std_dame"])]}
        for claim, comps in deciding.items():
            ok = all(x is True for *_, x in comps)
            n[claim][0] += ok
            n[claim][1] += ok and (on_seeds or all(lower(a, b, CLOSE) is True for _, a, b, _x in comps))
            close[claim] += [f"{conv} {name} {pct(margin(a, b))}" for name, a, b, x in comps
                             if x is True and ok and margin(a, b) < CLOSE and not on_seeds]
    k = len(convs)
    what = {"C1": "a Euclidean-based representation lower L1 and DR Norm. lower DAME",
            "C2": "Euclidean Std. lower L1 and DAME than Euclidean"}
    out = {"convs": convs}
    for claim in ("C1", "C2"):
        if not k:
            out[claim] = (f"{claim} ({what[claim]}): not measured (no conv with all of "
                          f"{', '.join(REPS)} finished).")
            continue
        word = verdict(n[claim][0], k)
        as_ties = f"{n[claim][1]} of {k}, {verdict(n[claim][1], k)}"
        words = qualify_cases(word, close[claim], as_ties, seeded_convs, k)
        out[claim] = f"{claim} ({what[claim]}): {n[claim][0]} of {k} complete convs: {words}."
    return out


#: the fair balance the thesis names on Facsimile's test set (3.5.3, l. 1483): LSA-3DMM and the Mesh
#: Autoencoder (fwk's vcconv), each with Euclidean Std.
BALANCED = (("lsa", "euclidean-std"), ("vcconv", "euclidean-std"))


def _c13_state(rows: dict, b: tuple, close: float | None):
    """(state, words, deciding margin or None, deciding member or None) of balanced member b: *off*
    when another member is lower on both L1 and DAME, *on* when it is lower than every other member
    on L1 or DAME, *tied* otherwise; each comparison by the rule (``lower``; with ``close``, a
    one-seed margin under it is a tie too, as the verdicts' "counting those as ties")."""
    me, others = rows[b], [k for k in rows if k != b]

    def cmp(k, m):  # is k lower than b on m? (None: a tie)
        a, c = _pair(rows[k], m), _pair(me, m)
        return lower(a, c, None if seeded(a) and seeded(c) else close)

    def mg(k, m):
        return margin(_pair(rows[k], m), _pair(me, m))

    doms = [k for k in others if cmp(k, "l1") is True and cmp(k, "dame") is True]
    beats = {k: [m for m in ("l1", "dame") if cmp(k, m) is False] for k in others}  # where b is the lower
    if doms:  # the nearest dominator: the smallest of its two margins
        k = min(doms, key=lambda k: min(mg(k, m) for m in ("l1", "dame")))
        m = min(("l1", "dame"), key=lambda m: mg(k, m))
        return "off", f"{k[0]}-{k[1]} below it on both, {m.upper()} by", mg(k, m), k
    if all(beats[k] for k in others):  # the nearest contender: the smallest of its best escapes
        k = min(others, key=lambda k: max(mg(k, m) for m in beats[k]))
        m = max(beats[k], key=lambda m: mg(k, m))
        return "on", f"below {k[0]}-{k[1]} on {m.upper()} by", mg(k, m), k
    tied = ", ".join(f"{k[0]}-{k[1]}" for k in others if not beats[k])
    return "tied", f"below {tied} on neither beyond the seeds' sd", None, None


def c13(rows: dict) -> tuple[list, str]:
    """The L1/DAME front over the finished members (by means) and the C13 line: how many of BALANCED
    are on it, each on, off or tied (``_c13_state``) with its deciding margin (an off member's
    nearest dominator's smaller margin; an on member's smallest escape from another); a deciding
    comparison without seeds on both sides and a margin under 10 % is listed, and the count is
    given again with those margins as ties."""
    keys = list(rows)
    front = [keys[i] for i in pareto_front([(rows[k]["l1"], rows[k]["dame"]) for k in keys])]
    present = [b for b in BALANCED if b in rows]
    if not present:
        return front, "C13 (the thesis's balanced pair on the L1/DAME front): not measured (none finished)."
    names, close, on_seeds, n_on, n_on_t = [], [], [], 0, 0
    for b in present:
        state, text, mg, vs = _c13_state(rows, b, None)
        name = f"{b[0]}-{b[1]}"
        names.append(f"{name}: {state} ({text}{'' if mg is None else ' ' + pct(mg)})")
        n_on += state == "on"
        n_on_t += _c13_state(rows, b, CLOSE)[0] == "on"
        if seeded(_pair(rows[b], "l1")) and (vs is None or seeded(_pair(rows[vs], "l1"))):
            on_seeds.append(name)  # decided over seeds
        elif mg is not None and mg < CLOSE:
            close.append(f"{name} {pct(mg)}")
    k = len(present)
    word = qualify_cases(verdict(n_on, k), close, f"{n_on_t} of {k}, {verdict(n_on_t, k)}", on_seeds, k)
    return front, (f"C13 (the thesis's balanced pair on the L1/DAME front over the {len(rows)} finished members: "
                   f"{'; '.join(names)}): {n_on} of {k}: {word}.")


if __name__ == "__main__":
    raise SystemExit(main())
