"""Where PBS's two networks err, by frequency band: why its k sweep looks as it does (issue 13, item 3).

    python benchmarks/pbs_band_errors.py RUN [--split val|test] [--model pbs] [--expressions a,b]

RUN is a finished blendshapes run with a ``pbs`` model (e.g. the main job,
``fwk run recipes/pbs_synthetic_heads.yaml``). The split is rebuilt as the run made it (its
recipe, seed and preprocessing). For every expression and every subject of the split it takes
the two networks' predictions P_s (spatial) and P_d (differential, placed rigidly onto P_s, as PBS
does at inference) and the ground truth G, and prints:

* the M-weighted energy ||E||_M^2 = sum_i m_i |E_i|^2 of the true displacement D = G - N and of
  the two errors E_s = P_s - G, E_d = P_d - G, and its share in eigenvector bands
  [0, 10), [10, 30), [30, 100), [100, 300), [300, K) and beyond the fitted basis (K: the PBS
  assembler's basis size), from the coefficients U^T M E (U: the assembler's M-orthonormal
  eigenvectors of the mean neutral);
* the correlation of E_s and E_d (and of each with D) within each band;
* a per-subject gain: the least-squares scalar g with P - N ~ g D, its mean and spread over the
  subjects, and the energy left after it (how much of an error is "the right shape, the wrong
  amount");
* for k in a few cuts: the assembled error's L1 (fwk's metric), its M-energy, its spread (mean
  over RMS of the per-vertex error lengths: 1 for an error of equal size everywhere, small for a
  concentrated one; at equal energy a more spread error has a larger L1), and the L1 with
  the differential network placed on the ground truth instead of on P_s (does the rigid placement
  cost anything?).

The assembly (eq. 5.10) takes the bands below k from P_s and the rest from P_d, so it can only
beat both networks where E_s is the smaller in the low bands and E_d in the high ones; these
numbers say whether that holds.

Last, at the chosen k, where PBS's perceptual error comes from (L1, DAME, FMPD; means over the
subjects): PBS itself; the truth below k with the differential network above it (the
differential network's error above k alone); the spatial network below k with the truth above
it (the spatial network's error below k alone); and each network alone. Threads: torch's
default (``OMP_NUM_THREADS``).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fwk.evaluation import evaluate
from fwk.lifecycle import open_run
from fwk.plugins import get_registry

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _runs import METRICS, metric_cells, run_data  # noqa: E402


def band_table(U, m, E, edges):
    """(energy shares per band incl. the part beyond U, total M-energy), averaged over subjects."""
    c = np.einsum("nk,bnc,n->bkc", U, E, m)
    per_k = (c ** 2).sum(-1).mean(0)
    total = float(np.einsum("bnc,bnc,n->b", E, E, m).mean())
    parts = [float(per_k[a:b].sum()) for a, b in zip(edges[:-1], edges[1:])] + [total - float(per_k.sum())]
    return parts, total, c


def swaps(m, Ps, Pd, G, k) -> list[tuple[str, np.ndarray]]:
    """[(row label, meshes)]: PBS at k and the swaps of the docstring's last paragraph."""
    pbs, low_true, high_true = (m.assemble(a, b, [k])[0] for a, b in ((Ps, Pd), (G, Pd), (Ps, G)))
    return [(f"PBS (k = {k})", pbs), ("truth below k, differential above", low_true),
            ("spatial below k, truth above", high_true), ("differential network alone", Pd),
            ("spatial network alone", Ps)]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run")
    ap.add_argument("--split", default="val", choices=["train", "val", "test"])
    ap.add_argument("--model", default="pbs")
    ap.add_argument("--expressions", default=None, help="comma-separated; default: all of the model's")
    a = ap.parse_args()
    run = open_run(a.run)
    m = run.model(a.model)
    _, _, cols = run_data(run)
    c = cols[a.split]
    U, w = m.assembler.proj.U, m.assembler.proj.m
    w = np.ones(U.shape[0]) if w is None else w
    n, K = U.shape
    edges = [e for e in (0, 10, 30, 100, 300) if e < K] + [K]
    names = [f"[{lo},{hi})" for lo, hi in zip(edges[:-1], edges[1:])] + [f">={K}"]
    metrics = [get_registry().get("metric", name)() for name in METRICS]
    l1 = metrics[0]
    j0 = c.shape_index("neutral")
    chosen = m.expressions if a.expressions is None else a.expressions.split(",")
    unknown = sorted(set(chosen) - set(m.expressions))
    if unknown:
        ap.error(f"--expressions: not expressions of {a.model}: {', '.join(unknown)}")
    for e in chosen:
        je = c.shape_index(e)
        ok = c.present[:, j0] & c.present[:, je]
        N, G = np.asarray(c.positions[ok, j0]), np.asarray(c.positions[ok, je])
        Ps, Pd = m.branches(N, e)
        print(f"{e}: {len(N)} {a.split} subjects, {n} vertices, chosen k = {m.k.get(e)}")
        coef = {}
        for label, E in (("displacement D = G - N", G - N), ("spatial error P_s - G", Ps - G),
                         ("differential error P_d - G", Pd - G)):
            parts, total, coef[label] = band_table(U, w, E, edges)
            print(f"  {label:<28} M-energy {total:.3e}; shares " +
                  "  ".join(f"{nm} {100 * x / total:4.1f}%" for nm, x in zip(names, parts)))
        cs, cd, cD = coef["spatial error P_s - G"], coef["differential error P_d - G"], coef["displacement D = G - N"]
        for lo, hi in zip(edges[:-1], edges[1:]):
            x, y, z = (v[:, lo:hi].ravel() for v in (cs, cd, cD))
            cor = lambda u, v: float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-300))  # noqa: E731
            print(f"  band [{lo},{hi}): energy spatial {float((x ** 2).sum()) / len(N):.2e} differential "
                  f"{float((y ** 2).sum()) / len(N):.2e}; corr(E_s, E_d) {cor(x, y):+.2f}, "
                  f"corr(E_s, D) {cor(x, z):+.2f}, corr(E_d, D) {cor(y, z):+.2f}")
        D = G - N
        for label, P in (("spatial", Ps), ("differential", Pd)):
            g = np.einsum("bnc,bnc,n->b", P - N, D, w) / np.einsum("bnc,bnc,n->b", D, D, w)
            r = P - N - g[:, None, None] * D
            print(f"  {label}: gain of the predicted displacement over the true one: mean {g.mean():.3f}, "
                  f"sd {g.std():.3f}; M-energy left after it {np.einsum('bnc,bnc,n->b', r, r, w).mean():.3e}")
        ks = sorted({k for k in (0, 10, 20, 30, 50, 100, 200, 500, 1000) if k <= K} | {n})
        on_truth = m.branch_predict(N, e, 1, target=G)
        for k, P, Q in zip(ks, m.assemble(Ps, Pd, ks), m.assemble(Ps, on_truth, ks)):
            E = P - G
            d = np.linalg.norm(E, axis=-1)
            print(f"  k={k:<6} L1 {evaluate(P, G, m.template, [l1])['l1']['scores'].mean():.4e}  M-energy "
                  f"{np.einsum('bnc,bnc,n->b', E, E, w).mean():.4e}  spread (mean / RMS of |E_i|) "
                  f"{d.mean() / np.sqrt((d ** 2).mean()):.3f}  L1 with P_d placed on the truth "
                  f"{evaluate(Q, G, m.template, [l1])['l1']['scores'].mean():.4e}")
        if m.k.get(e) is not None:
            print("  at the chosen k: | assembled from | L1 x1e-3 | DAME x1e-2 | FMPD x1e-2 |")
            for label, P in swaps(m, Ps, Pd, G, m.k[e]):
                print(f"  | {label} | " + metric_cells(P, G, m.template, metrics))


if __name__ == "__main__":
    main()
