"""Which band of Deep Spectral Meshes makes its error: claim C4's DAME gap (issue 13).

    python benchmarks/dsm_band_errors.py RUN [--k KRUN] [--split test] [--models dsm,dsm-g04]
                                         [--others vae-dr-norm,vae-euclidean-std]

RUN is a finished run of ``recipes/thesis/ch4/plateau.yaml`` (``dsm`` models beside
single-representation VAEs); KRUN, optional, a run of ``recipes/thesis/ch4/k-plateau.yaml``
whose finished members ``k<k>`` are added to the dsm models. The split is rebuilt as the run made
it (its recipe, seed and preprocessing), in the evaluation space of its report.

dsm assembles its output from two band predictions (eq. 4.15), P' = X (P'_low - P-bar) +
(I - X)(P'_high - P-bar) + P-bar, with X = U_k U_k^T M the projection onto the first k
eigenvectors. With G the ground truth and G_low, G_high its bands (eq. 4.11, so that assembling
them returns G exactly), each dsm's error is attributed by swapping one band for the truth:

* ``both bands predicted``: dsm's own output (its report's numbers);
* ``low predicted, high true``: assemble(P'_low, G_high): the error the low band's network makes;
* ``low true, high predicted``: assemble(G_low, P'_high): the error the high band's network makes.

And each ``--others`` model R (a whole-mesh network of the same run) is split by the same dsm's
X and crossed with dsm's bands:

* ``R``: R's own output;
* ``R's low band + dsm's high``: assemble(X-part of R, P'_high);
* ``dsm's low + R's high band``: assemble(P'_low, (I - X)-part of R).

If dsm's DAME comes from its low band (a Euclidean network, whose output on these heads is
noisy, thesis 3.5.1) the ``low predicted`` row carries most of it and taking the low band from
a DR network lowers it. Metrics: L1, DAME, FMPD (means over the split's meshes, evaluation
space, as the run's report). Nothing is tuned: every number is a swap of predicted for true (or
for another network's) band, assembled by the model's own assembler.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fwk.lifecycle import open_run
from fwk.plugins import get_registry
from fwk.protocols import FitData

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _runs import METRICS, metric_cells, run_data  # noqa: E402



def attribute(m, G, others: dict) -> list[tuple[str, np.ndarray]]:
    """[(row label, meshes)] for dsm model ``m`` on ground truth G (b, n, 3): the swaps of the
    docstring, ``others`` {label: its reconstruction of G}."""
    if m.n_bands != 2:
        raise SystemExit(f"{m.n_bands} bands: this attribution is written for dsm's two bands (one k)")
    true = m.split(G)
    pred = m.decode_bands(m.encode(G))
    low, high = 0, 1
    rows = [("both bands predicted", m.assemble(pred)),
            ("low predicted, high true", m.assemble([pred[low], true[high]])),
            ("low true, high predicted", m.assemble([true[low], pred[high]]))]
    for label, R in others.items():
        parts = m.split(R)
        rows += [(label, R),
                 (f"{label}'s low band + dsm's high", m.assemble([parts[low], pred[high]])),
                 (f"dsm's low + {label}'s high band", m.assemble([pred[low], parts[high]]))]
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--k", type=Path, default=None, help="a k-plateau run: its finished members are added")
    ap.add_argument("--split", default="test", choices=["train", "val", "test"])
    ap.add_argument("--models", default="dsm,dsm-g04", help="dsm models of RUN (comma-separated)")
    ap.add_argument("--others", default="vae-dr-norm,vae-euclidean-std",
                    help="whole-mesh models of RUN to cross with dsm's bands (comma-separated; '' for none)")
    a = ap.parse_args()
    run = open_run(a.run)
    col, pre, cols = run_data(run)
    template = col.template.with_vertices(pre.mean_neutral)
    G = FitData(template, cols[a.split], cols[a.split], ["neutral"]).stack("train")
    reg = get_registry()
    metrics = [reg.get("metric", name)() for name in METRICS]
    dsms = {label: run.model(label) for label in a.models.split(",") if label}
    if a.k is not None:
        for member in sorted(a.k.glob("k*/"), key=lambda d: int(d.name[1:]) if d.name[1:].isdigit() else 0):
            try:
                dsms[f"dsm {member.name}"] = open_run(member).model("dsm")
            except Exception as exc:  # a member still training or not started: say so, go on
                print(f"{member}: skipped ({exc})")
    others = {label: np.asarray(run.model(label).reconstruct(G)) for label in a.others.split(",") if label}
    print(f"{a.run.name}, {a.split} split: {len(G)} meshes, {template.n_vertices} vertices, evaluation space; "
          "L1 x1e-3, DAME x1e-2, FMPD x1e-2 (means)")
    for label, m in dsms.items():
        print(f"\n### {label} (k = {m.cuts[0]})\n")
        print("| assembled from | L1 | DAME | FMPD |\n| --- | --- | --- | --- |")
        for row, P in attribute(m, G, others):
            print(f"| {row} | " + metric_cells(P, G, template, metrics))


if __name__ == "__main__":
    main()
