"""How long a study takes on a quiet machine: a finished study's epochs x a short quiet run's epoch
times (issue 13: "each study in about 2 hours on 2 cores").

    python benchmarks/study_time.py STUDY TIMING [--wall SECONDS]

STUDY is a finished run of a study recipe (a ``reconstruct``, ``blendshapes`` or ``grid`` run,
however it ran: interrupted, resumed, beside other work); TIMING a run of the *same recipe* for a
few epochs on an otherwise idle machine, e.g.

    fwk run recipes/thesis/ch4/plateau.yaml train.epochs=3

Every network fwk trained writes ``curves/<label>/<network>.json`` (a grid member's under
``<member>/``): the epochs it ran and each epoch's seconds and threads; both runs' are read by
``fwk.evaluation.curves.find_curves``, as the reports read them. For each network of STUDY
this prints the epochs it ran, its median epoch seconds there, the median seconds of TIMING's
epochs after the first (the first carries one-off warm-up; a one-epoch TIMING uses it) and the
predicted minutes, epochs x TIMING's median. Everything that does not scale with epochs (loading
and preprocessing the data, eigenvectors, evaluation, figures, reports) is taken once from TIMING
as its wall time minus its epochs' seconds. TIMING's wall time is ``--wall`` when given (e.g. from
``/usr/bin/time``), else the span from its ``recipe.yaml`` being written to its ``report.md``
(accurate for an uninterrupted run; a resumed TIMING is refused). The prediction assumes the
stopping rule ends each network at the same epoch as in STUDY, which holds when TIMING uses the
same thread count as STUDY's epochs did (the rule's decisions are otherwise equal to the last
digits of the losses).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from fwk.evaluation.curves import find_curves


def epoch_seconds(curve: dict) -> float:
    """The median seconds of a curve's epochs after the first (the first alone if it is the only one)."""
    secs = [e["seconds"] for e in curve["epochs"] if "seconds" in e]
    if not secs:
        raise ValueError(f"{curve.get('network')}: no epoch times in its curve")
    return statistics.median(secs[1:] or secs)


def wall_seconds(run: Path) -> float:
    """From writing recipe.yaml to writing report.md (an uninterrupted run's wall time)."""
    v = run / "versions.json"
    if v.exists() and json.loads(v.read_text()).get("resumed"):
        raise SystemExit(f"{run}: resumed; its file times do not give its wall time (give --wall)")
    report = run / "report.md"
    if not report.exists():
        raise SystemExit(f"{run}: no report.md (not finished); give --wall")
    return report.stat().st_mtime - (run / "recipe.yaml").stat().st_mtime


def predict(study: dict[str, dict], timing: dict[str, dict], wall: float) -> tuple[list[dict], float, float]:
    """(rows per network, the fixed seconds, the predicted total seconds)."""
    missing = sorted(set(study) - set(timing))
    if missing:
        raise SystemExit(f"TIMING has no curve for {', '.join(missing)}: run the same recipe as STUDY")
    fixed = wall - sum(e.get("seconds", 0.0) for c in timing.values() for e in c["epochs"])
    rows = []
    for key, c in study.items():
        t = epoch_seconds(timing[key])
        rows.append({"network": key, "epochs": c["epochs_run"], "study_s": epoch_seconds(c), "quiet_s": t,
                     "threads": sorted({e.get("threads") for e in timing[key]["epochs"]} - {None}),
                     "minutes": c["epochs_run"] * t / 60})
    return rows, fixed, fixed + sum(r["minutes"] * 60 for r in rows)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("study", type=Path)
    ap.add_argument("timing", type=Path)
    ap.add_argument("--wall", type=float, default=None, help="TIMING's wall time in seconds")
    a = ap.parse_args()
    study, timing = find_curves(a.study), find_curves(a.timing)
    if not study:
        sys.exit(f"{a.study}: no training curves")
    unfinished = [k for k, c in study.items() if not c.get("finished")]
    if unfinished:
        sys.exit(f"{a.study}: still training or killed: {', '.join(unfinished)}")
    wall = a.wall if a.wall is not None else wall_seconds(a.timing)
    rows, fixed, total = predict(study, timing, wall)
    print(f"{a.study.name} (epochs) x {a.timing.name} (quiet epoch times, wall {wall / 60:.1f} min)\n")
    print("| network | epochs | epoch s in the study | quiet epoch s | threads | predicted min |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['network']} | {r['epochs']} | {r['study_s']:.1f} | {r['quiet_s']:.1f} | "
              f"{', '.join(map(str, r['threads']))} | {r['minutes']:.1f} |")
    print(f"| everything else (data, evaluation, reports; from TIMING) | | | | | {fixed / 60:.1f} |")
    print(f"\npredicted wall time on a quiet machine: {total / 60:.0f} min ({total / 3600:.2f} h)")


if __name__ == "__main__":
    main()
