"""Claim C4 (thesis 4.7.1, tables 4.2-4.4) from a finished chapter 4 run (issue 13).

    python benchmarks/claims_ch4.py RUN [--k KRUN] [--edit EDITRUN] [--splits train,test]
    python benchmarks/claims_ch4.py --k KRUN | --edit EDITRUN     # a k study or an edit run alone

RUN is a run of ``recipes/thesis/ch4/plateau.yaml`` (one reconstruct run: ``dsm`` and ``dsm-g04``,
the single-representation VAEs, SpiralNet++, Neural 3DMM and the mean shape); KRUN, optional, a
run of ``recipes/thesis/ch4/k-plateau.yaml`` or ``k-plateau-seeds.yaml`` (grid members
``k<k>``). Prints, in markdown:

* per split, one row per model: L1, DAME and FMPD (mean over meshes, evaluation space), whether
  the model is on the L1/DAME Pareto front of the learned models (the thesis's comparison: the
  mean shape is not in it), and its training: epochs, what ended it, the plateau rule's verdict
  and minutes (the sum of the epochs' own seconds, a resumed run's earlier epochs included);
* per dsm model and split, C4 (thesis 4.7.1, table 4.2, l. 1866-1881): dsm against table 4.2's
  methods in the run: SpiralNet++ and Neural 3DMM (Euclidean Std.), the Mesh Autoencoder, whose
  table 4.2 row is raw Euclidean coordinates (``vae-euclidean`` or ``mesh-autoencoder``: table 4.2's
  Mesh Autoencoder numbers are table 4.3's Euclidean row, l. 1872/1895), and FeaStNet when present.
  The thesis: dsm has the lowest DAME on both data sets' training and test splits and is behind
  SpiralNet++ and Neural 3DMM on L1 on 3 of the 4. C4 "holds" on a split when dsm's DAME is lower
  than every one of them, "partly" than some, "does not hold" than none; its L1 rank is printed;
* C7 (table 4.3, l. 1887-1905): dsm against the single-representation VAEs (``vae-euclidean``,
  ``vae-euclidean-std``, ``vae-dr-norm``, ``vae-dr``). The thesis: on the training set dsm has the
  lowest L1 and DAME on most data sets (Facsimile and FaceWarehouse); on the test set it
  "favourably compromises", i.e. lies on their L1/DAME front (the DR VAE has the lower test DAME
  there too, 3.00 and 1.22 against 3.17 and 1.29). Train: "holds" when dsm is the lowest on both,
  "partly" on one, "does not hold" on neither; test: "holds" when no VAE dominates dsm (lower on one
  metric and not higher on the other, a tie within the seeds' sd counting as neither), else "does
  not hold";
* C16 (table 4.4, l. 1922-1935): whether the Euclidean Std. VAE has a lower L1 and a lower DAME than
  the raw Euclidean VAE, per split;
* with KRUN, the k study: L1, DAME, FMPD of dsm per k on each split, the front over k, and C8 (l. 2282:
  "As the parameter k increases, the perceptual error increases and geometric error decreases"): a
  metric follows the claim when it moves the claimed way on more than half of the steps between
  consecutive k; C8 "holds" when both L1 and DAME follow, "partly" when one does, else "does not hold";
* with EDITRUN, a run of ``recipes/thesis/ch4/edit.yaml``: C17 (4.7.2-4.7.3, fig. 4.19) from the
  decoders' cross-responses rho_{c<-j} (``fwk_dsm_tasks``: 0 = an edit of band j leaves decoder
  c's band alone, 1 = c responds to it as much as to its own code), per dsm model and pair of
  bands. "Lower gamma provides more control" (l. 2010): the lowest-gamma dsm model's rho is
  compared with the gamma = 1 model's pair by pair, "holds" when lower on more than half of the
  pairs. "High- and low-frequency parameters barely influence each other" at gamma = 0.4
  (l. 2002) has no number in the thesis; fwk reads it as "holds" when every rho of the
  lowest-gamma model is at most BARELY (0.1: a tenth of the band's own response), "partly" when
  every one is below HALF (0.5), else "does not hold".

Comparisons and ties: ``_claims.RULE`` (printed).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from fwk.evaluation.core import pareto_front

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _claims import CLOSE, RULE, fmt, lower, margin, pct, qualify, seeded, training, verdict  # noqa: E402

BASELINE = "mean-shape"
#: C17's reading of "barely influence each other" (no number in the thesis): every cross-response
#: rho at most BARELY holds, every one below HALF partly
BARELY, HALF = 0.1, 0.5


def load(run: Path) -> dict:
    """{label: {split: {metric: mean}, "training": {...}}} of the run's models."""
    m = json.loads((run / "metrics.json").read_text())
    return {label: {**{split: {k: v["mean"] for k, v in res.items()} for split, res in r.items()},
                    "_sd": {split: {k: v.get("seed_sd") for k, v in res.items()} for split, res in r.items()},
                    "training": training(m, label, run)}
            for label, r in m["models"].items()}


#: table 4.2's methods (l. 1866-1881) by their labels in the chapter 4 recipes: the Mesh Autoencoder's
#: row is raw Euclidean coordinates (vae-euclidean in reconstruction.yaml, mesh-autoencoder in autoencoders-full.yaml)
TABLE_4_2 = ("spiralnet++", "neural-3dmm", "vae-euclidean", "mesh-autoencoder", "feastnet")
#: table 4.2's four methods beside Deep Spectral Meshes (l. 1872-1875), each with the model names it runs under
TABLE_4_2_METHODS = {"SpiralNet++": ("spiralnet++",), "Neural 3DMM": ("neural-3dmm",),
                     "Mesh Autoencoder": ("vae-euclidean", "mesh-autoencoder"), "FeaStNet": ("feastnet",)}
#: table 4.3's single-representation VAEs (l. 1887-1905)
TABLE_4_3 = ("vae-euclidean", "vae-euclidean-std", "vae-dr-norm", "vae-dr")


def every(n_yes: int, n: int) -> str:
    """A "lowest" claim: 'holds' when the comparison goes its way against all n, 'partly' some, else 'does not hold'."""
    return "holds" if n_yes == n else ("does not hold" if n_yes == 0 else "partly")


def _m(r: dict, split: str, metric: str):
    """(mean, seeds' sd or None) of one model's ``metric`` on ``split`` (a ``load`` entry)."""
    return r[split][metric], r.get("_sd", {}).get(split, {}).get(metric)


def _v(models: dict, label: str, split: str, metric: str):
    return _m(models[label], split, metric)


def _versus(models, dsm, split, others, metric):
    """[(other, dsm lower?, margin)] of ``metric`` against each other model present on the split."""
    out = []
    for o in others:
        if o in models and split in models[o]:
            a, b = _v(models, dsm, split, metric), _v(models, o, split, metric)
            out.append((o, lower(a, b), lower(a, b, CLOSE), margin(a, b)))
    return out


def reading(models: dict, split: str) -> tuple[list[str], dict]:
    """(the learned models on the L1/DAME front, {dsm label: its C4, C7 and C16 readings}) on ``split``."""
    learned = [k for k in models if k != BASELINE and split in models[k]]
    pts = [(models[k][split]["l1"], models[k][split]["dame"]) for k in learned]
    front = [learned[i] for i in pareto_front(pts)]
    by_dame = sorted(learned, key=lambda k: models[k][split]["dame"])
    by_l1 = sorted(learned, key=lambda k: models[k][split]["l1"])
    base = models.get(BASELINE, {}).get(split)
    out = {}
    for k in learned:
        if not k.startswith("dsm"):
            continue
        r = models[k][split]
        seeds = seeded(_v(models, k, split, "dame"))
        # C4: DAME against table 4.2's methods
        c4 = _versus(models, k, split, TABLE_4_2, "dame")
        n4, n4t = sum(x is True for _, x, _, _ in c4), sum(t is True for _, _, t, _ in c4)
        close4 = [f"{o} {pct(m)}" for o, x, _, m in c4 if x is True and m < CLOSE]
        l1_42 = sorted([k, *[o for o, *_ in c4]], key=lambda x: models[x][split]["l1"])
        c4_word = every(n4, len(c4)) if c4 else "not measured"
        # C7: against table 4.3's VAEs
        l1v, dv = _versus(models, k, split, TABLE_4_3, "l1"), _versus(models, k, split, TABLE_4_3, "dame")
        if not dv:
            c7 = "not measured"
        elif split == "train":
            both = [all(x is True for _, x, _, _ in l1v), all(x is True for _, x, _, _ in dv)]
            both_t = [all(t is True for _, _, t, _ in l1v), all(t is True for _, _, t, _ in dv)]
            close7 = [f"{m_} against {o} {pct(mm)}" for m_, vs in (("L1", l1v), ("DAME", dv))
                      for o, x, _, mm in vs if x is True and mm < CLOSE]
            c7 = (f"lowest L1 of dsm and the VAEs: {'yes' if both[0] else 'no'}, lowest DAME: "
                  f"{'yes' if both[1] else 'no'}: " + qualify(every(sum(both), 2), close7,
                                                               every(sum(both_t), 2), seeds))
        else:
            # a VAE dominates dsm when dsm is lower on neither metric and higher on one (a tie, within the
            # seeds' sd, is neither); one seed: dsm's winning margins under 10 % are listed, and the verdict
            # they would give as ties
            def dominated(i):
                return [o for (o, *xl), (_, *xd) in zip(l1v, dv)
                        if xl[i] is not True and xd[i] is not True and False in (xl[i], xd[i])]

            dom, dom_t = dominated(0), dominated(1)
            close7 = []  # a VAE dsm keeps off only by margins under 10 %: those margins
            for (o, xl, _, ml), (_, xd, _, md) in zip(l1v, dv):
                wins = [(m_, mm) for m_, x, mm in (("L1", xl, ml), ("DAME", xd, md)) if x is True]
                if wins and max(mm for _, mm in wins) < CLOSE:
                    close7 += [f"{m_} against {o} {pct(mm)}" for m_, mm in wins]
            c7 = (f"on the front of dsm and the VAEs: {'no, dominated by ' + ', '.join(dom) if dom else 'yes'}: "
                  + qualify("does not hold" if dom else "holds", close7,
                            "does not hold" if dom_t else "holds", seeds))
        out[k] = {"front": k in front, "dame_rank": by_dame.index(k) + 1, "l1_rank": by_l1.index(k) + 1,
                  "n": len(learned),
                  "beats_mean": None if base is None else bool(r["l1"] < base["l1"] and r["dame"] < base["dame"]),
                  "c4_vs": [o for o, *_ in c4], "c4_lower": n4, "c4_l1_rank": l1_42.index(k) + 1,
                  "verdict": c4_word,
                  "c4": (f"{qualify(c4_word, close4, every(n4t, len(c4)), seeds)}" if c4 else c4_word),
                  "c7": c7}
    return front, out


def c16(models: dict, split: str) -> str | None:
    """C16: the Euclidean Std. VAE against the raw Euclidean VAE on ``split`` (table 4.4)."""
    if not all(x in models and split in models[x] for x in ("vae-euclidean", "vae-euclidean-std")):
        return None
    got = {m: (lower(_v(models, "vae-euclidean-std", split, m), _v(models, "vae-euclidean", split, m)),
               margin(_v(models, "vae-euclidean-std", split, m), _v(models, "vae-euclidean", split, m)))
           for m in ("l1", "dame")}
    ok = all(x is True for x, _ in got.values())
    close = [f"{m.upper()} {pct(mm)}" for m, (x, mm) in got.items() if x is True and mm < CLOSE]
    word = qualify("holds" if ok else "does not hold", close, "holds" if ok and not close else "does not hold",
                   seeded(_v(models, "vae-euclidean", split, "l1")))
    return (f"C16, {split}: Euclidean Std. VAE lower L1 ({'yes' if got['l1'][0] else 'no'}) and DAME "
            f"({'yes' if got['dame'][0] else 'no'}) than the raw Euclidean VAE: {word}.")


def c8(rows: list, split: str) -> str:
    """C8 over the k study's members (sorted by k): the steps between consecutive k on which L1 falls
    and DAME rises, by ``_claims.lower`` (with seeds a step within the larger sd is a tie and counts
    for neither; on one seed the steps under 10 % are listed, with the verdict they would give as
    ties)."""
    steps = list(zip(rows, rows[1:]))
    n = len(steps)
    if n == 0:
        return f"C8, {split}: not measured (fewer than two finished k)."
    seeds = any(v is not None for _, r in rows for v in r.get("_sd", {}).get(split, {}).values())

    def moves(close=None):
        fall = [lower(_m(b, split, "l1"), _m(a, split, "l1"), close) for (_, a), (_, b) in steps]
        rise = [lower(_m(a, split, "dame"), _m(b, split, "dame"), close) for (_, a), (_, b) in steps]
        return fall, rise

    (fall, rise), (fall_t, rise_t) = moves(), moves(CLOSE)
    word = verdict(sum([2 * sum(x is True for x in fall) > n, 2 * sum(x is True for x in rise) > n]), 2)
    word_t = verdict(sum([2 * sum(x is True for x in fall_t) > n, 2 * sum(x is True for x in rise_t) > n]), 2)
    close = [f"{m} {ka} -> {kb} {pct(margin(_m(a, split, key), _m(b, split, key)))}"
             for m, key in (("L1", "l1"), ("DAME", "dame")) for (ka, a), (kb, b) in steps
             if margin(_m(a, split, key), _m(b, split, key)) < CLOSE]
    ties = "" if not seeds else (f"; ties: L1 on {sum(x is None for x in fall)}, DAME on "
                                 f"{sum(x is None for x in rise)}")
    counts = (f"L1 falls on {sum(x is True for x in fall)} of {n} steps of k, DAME rises on "
              f"{sum(x is True for x in rise)} of {n}{ties}")
    if seeds:
        return f"C8, {split}: {counts}: {word} (over seeds; differences within the seeds' sd are ties)."
    if not close:
        return f"C8, {split}: {counts}: {word} (one seed per k; every step 10 % or more)."
    return (f"C8, {split}: {counts}: {word} (one seed per k; steps under 10 %: {', '.join(close)}; counting those "
            f"as ties: {word_t}).")


def c17(edit_run: Path) -> list[str]:
    """C17's two readings from an edit run's ``metrics.json`` (``disentanglement.dsm``: per model its
    ``gamma`` and ``cross_response`` {"c<-j": rho}), as lines; one seed (an edit run has no seeds)."""
    d = json.loads((edit_run / "metrics.json").read_text()).get("disentanglement", {}).get("dsm", {})
    models = {k: v for k, v in d.items() if v.get("gamma") is not None and v.get("cross_response")}
    if len(models) < 2:
        return ["C17: not measured (the edit run has fewer than two dsm models with a gamma and cross-responses)."]
    lo = min(models, key=lambda k: models[k]["gamma"])
    hi = next((k for k in models if models[k]["gamma"] == 1.0), max(models, key=lambda k: models[k]["gamma"]))
    rl, rh = models[lo]["cross_response"], models[hi]["cross_response"]
    pairs = [p for p in rl if p in rh]
    rows = [(p, lower(rl[p], rh[p]), lower(rl[p], rh[p], CLOSE), margin(rl[p], rh[p])) for p in pairs]
    n_yes, n_t = sum(x is True for _, x, _, _ in rows), sum(t is True for _, _, t, _ in rows)
    close = [f"{p} {pct(m)}" for p, x, _, m in rows if x is True and m < CLOSE]
    gl, gh = models[lo]["gamma"], models[hi]["gamma"]
    each = ", ".join(f"rho {p} {rl[p]:.3f} against {rh[p]:.3f}" for p in pairs)
    more = (f"C17, lower gamma more control: {lo} (gamma {gl:g}) against {hi} (gamma {gh:g}): {each}; lower for "
            f"{n_yes} of {len(pairs)} pairs: {qualify(verdict(n_yes, len(pairs)), close, verdict(n_t, len(pairs)), False)}.")
    top = max(rl.values())
    word = "holds" if top <= BARELY else ("partly" if top < HALF else "does not hold")
    barely = (f"C17, bands barely influence each other at gamma {gl:g} ({lo}): rho "
              f"{', '.join(f'{p} {rl[p]:.3f}' for p in rl)}; largest {top:.3f} against {BARELY:g} (holds) and {HALF:g} "
              f"(partly): {word} (one seed).")
    return [more, barely]


def k_rows(krun: Path) -> list[tuple[int, dict]]:
    """(k, {split: {metric: mean}}) of the k study's finished members, by k."""
    rows = []
    for d in krun.iterdir():
        mk = re.fullmatch(r"k(\d+)", d.name)
        if mk and (d / "metrics.json").exists():
            models = load(d)
            dsm = next((v for k, v in models.items() if k.startswith("dsm")), None)
            if dsm is not None:
                rows.append((int(mk.group(1)), dsm))
    return sorted(rows, key=lambda r: r[0])


def k_unfinished(krun: Path) -> list[int]:
    """The k of the k study's members without ``metrics.json`` (still running, or not started)."""
    return sorted(int(m.group(1)) for d in krun.iterdir()
                  if (m := re.fullmatch(r"k(\d+)", d.name)) and not (d / "metrics.json").exists())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, nargs="?", default=None,
                    help="a run of recipes/thesis/ch4/plateau.yaml (C4, C7, C16); optional with --k or --edit")
    ap.add_argument("--k", type=Path, default=None, help="a run of recipes/thesis/ch4/k-plateau.yaml or k-plateau-seeds.yaml")
    ap.add_argument("--edit", type=Path, default=None, help="a run of recipes/thesis/ch4/edit.yaml (C17)")
    ap.add_argument("--splits", default="train,test")
    a = ap.parse_args(argv)
    if a.run is None and a.k is None and a.edit is None:
        ap.error("give RUN (a chapter 4 run), --k KRUN or --edit EDITRUN")
    models = {} if a.run is None else load(a.run)
    for split in a.splits.split(",") if a.run is not None else ():
        front, read = reading(models, split)
        print(f"\n{split} ({a.run.name}), evaluation space, mean over meshes\n")
        print("| model | L1 ×1e-3 | DAME ×1e-2 | FMPD ×1e-2 | on the L1/DAME front | epochs | ended by | verdict "
              "| train min |")
        print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
        for k, v in models.items():
            if split not in v:
                continue
            r, t = v[split], v["training"]
            mins = "" if t["minutes"] is None else f"{t['minutes']:.1f}"
            on = "(baseline)" if k == BASELINE else ("yes" if k in front else "no")
            print(f"| {k} | {r['l1'] * 1e3:.3f} | {r['dame'] * 1e2:.3f} | {r.get('fmpd', float('nan')) * 1e2:.3f} | "
                  f"{on} | {t['epochs']} | {t['ended']} | {t['verdict']} | {mins} |")
        for k, c in read.items():
            mean = {None: "no mean shape in the run", True: "beats the mean shape on L1 and DAME",
                    False: "does not beat the mean shape on both"}[c["beats_mean"]]
            print(f"\n{k}, {split}: {'on' if c['front'] else 'off'} the front of all learned models; DAME rank "
                  f"{c['dame_rank']} and L1 rank {c['l1_rank']} of {c['n']}; {mean}.")
            absent = [m for m, names in TABLE_4_2_METHODS.items() if not set(names) & set(c["c4_vs"])]
            print(f"C4, {k}, {split}: lower DAME than {c['c4_lower']} of the {len(c['c4_vs'])} of table 4.2's "
                  f"{len(TABLE_4_2_METHODS)} methods in the run ({', '.join(c['c4_vs']) or 'none'}"
                  f"{'; not run: ' + ', '.join(absent) if absent else ''}); L1 rank {c['c4_l1_rank']} of "
                  f"{len(c['c4_vs']) + 1}: {c['c4']}.")
            print(f"C7, {k}, {split}: {c['c7']}.")
        line = c16(models, split)
        if line:
            print(line)
    if a.run is not None or a.k is not None:
        print(f"\n{RULE}")
    if a.edit is not None:
        print(f"\nedit run ({a.edit.name})\n")
        for line in c17(a.edit):
            print(line)
    if a.k is not None:
        every_row = k_rows(a.k)
        for split in a.splits.split(","):
            rows = [(k, r) for k, r in every_row if split in r]  # a member without the split is left out
            pts = [(r[split]["l1"], r[split]["dame"]) for _, r in rows]
            front = {rows[i][0] for i in pareto_front(pts)}
            print(f"\nk study ({a.k.name}), {split}\n")
            print("| k | L1 ×1e-3 | DAME ×1e-2 | FMPD ×1e-2 | on the front | verdict | train min |")
            print("| --- | --- | --- | --- | --- | --- | --- |")
            for k, r in rows:
                t = r["training"]
                mins = "" if t["minutes"] is None else f"{t['minutes']:.1f}"
                cell = lambda m, f: fmt(_m(r, split, m), f) if m in r[split] else "nan"  # noqa: E731
                print(f"| {k} | {cell('l1', 1e3)} | {cell('dame', 1e2)} | {cell('fmpd', 1e2)} | "
                      f"{'yes' if k in front else 'no'} | {t['verdict']} | {mins} |")
            print(f"\n{c8(rows, split)}")
            pending = k_unfinished(a.k)
            if pending and len(rows) >= 2:
                print(f"(Over the finished k only: {', '.join(str(k) for k, _ in rows)}; not finished: "
                      f"{', '.join(str(k) for k in pending)}. Its steps join k that are not consecutive in the study.)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
