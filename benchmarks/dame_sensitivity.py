"""How much fwk's DAME-style metric depends on its own choices: values and rankings of 42 pairs
under plausible alternatives of the masking scale, the masking function, the edge weight and
the roughness source.

    OMP_NUM_THREADS=1 python benchmarks/dame_sensitivity.py

Why: Váša & Rus's DAME (2012) could not be read here and has no public implementation, so the
masking in ``fwk_dame`` is fwk's own (docs/methods/metrics.md). Its defaults are not changed by
this script; it measures what they decide.

Meshes: the ICT-FaceKit face-head region (11,248 vertices; ict-facekit, seed 0, 20 sampled
identities), or a synthetic head of that size when the data is absent. 42 pairs (target,
prediction), 7 kinds x subjects 0-5:

* ``mean``: the subject's neutral, predicted by the mean of the 20 sampled neutrals;
* ``noise 0.01`` / ``noise 0.03``: the neutral, predicted by itself plus Gaussian noise of
  0.01 / 0.03 cm per coordinate (seeded per subject);
* ``smooth 5`` / ``smooth 20``: the neutral, predicted by 5 / 20 steps of uniform Laplacian
  smoothing (x <- x + 0.5 (mean of the one-ring - x), every vertex);
* ``neutral for expr``: an expression (face-compression, mouth-wide, oo-brow-raise-eyes-wide for
  subjects 0, 3 / 1, 4 / 2, 5), predicted by the subject's neutral;
* ``half expr``: the same expression, predicted by neutral + half of its displacement.

Variants (each changes one choice of the default: rational masking 1 / (1 + r / 0.1 rad), r the
target's mean |dihedral| over the edges of an edge's two faces, weights the mean target area of
the two faces):

* masking scale 0.025, 0.05, 0.2, 0.4 rad, and no masking;
* masking function exp(-r / s), 1 / (1 + (r / s)^2) (s = 0.1 rad);
* weights: none (every edge 1), the target's edge length, the mean of target and prediction
  areas;
* roughness of: the prediction, the mean of target and prediction, the larger of the two, the
  edge alone (|phi_e|), two rings (the face stencil applied twice), and the local spread of the
  oriented angle (sqrt(E[phi^2] - E[phi]^2) over the same stencil) instead of its mean magnitude.

Per variant: the median and largest relative change of the 42 values against the default, the
Spearman rank correlation of the 42 values with the default's, the Spearman correlation of the
7 kinds' median values (does the order of the kinds hold), and the lowest Spearman correlation
within one kind (6 pairs: coarse). The default column is checked against the ``dame`` metric
itself. Prints a table, then one JSON line.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ict import face_head  # noqa: E402

from fwk.geometry import one_ring  # noqa: E402
from fwk.plugins import get_registry  # noqa: E402

KINDS = ["mean", "noise 0.01", "noise 0.03", "smooth 5", "smooth 20", "neutral for expr", "half expr"]
SUBJECTS = range(6)
S_DEFAULT = 0.1


def smooth(X, A, steps):
    deg = np.asarray(A.sum(axis=1)).ravel()[:, None]
    for _ in range(steps):
        X = X + 0.5 * ((A @ X) / deg - X)
    return X


def pairs(col):
    X = np.asarray(col.positions)
    neutrals = X[:, 0]
    mean = neutrals.mean(0)
    A = one_ring(col.template.triangles, col.template.n_vertices).astype(float)
    out = []
    for kind in KINDS:
        for s in SUBJECTS:
            N = neutrals[s]
            e = 1 + s % (X.shape[1] - 1)
            rng = np.random.default_rng([s, KINDS.index(kind)])
            if kind == "mean":
                out.append((kind, N, mean))
            elif kind.startswith("noise"):
                out.append((kind, N, N + rng.normal(0, float(kind.split()[1]), N.shape)))
            elif kind.startswith("smooth"):
                out.append((kind, N, smooth(N, A, int(kind.split()[1]))))
            elif kind == "neutral for expr":
                out.append((kind, X[s, e], N))
            else:
                out.append((kind, X[s, e], N + 0.5 * (X[s, e] - N)))
    return out


def edge_terms(T, P, template):
    """Per interior edge: |wrapped dihedral difference|, |phi| of target and prediction, the
    signed target phi, face-area weights of both meshes, target edge length, and the stencil."""
    import fwk_dame

    p = fwk_dame._prep(template)
    phi, area = fwk_dame._dihedral(fwk_dame._soa(np.stack([T, P])), p)
    d = np.abs(fwk_dame.wrap(phi[1] - phi[0]))
    w_t = 0.5 * (area[0][p.f1] + area[0][p.f2])
    w_p = 0.5 * (area[1][p.f1] + area[1][p.f2])
    length = np.linalg.norm(T[p.b] - T[p.a], axis=1)
    return d, phi[0], phi[1], w_t, w_p, length, p.rough


def variants():
    """name -> function(terms) -> score."""
    def score(mask="rational", s=S_DEFAULT, weight="area", rough="target"):
        def f(t):
            d, phi_t, phi_p, w_t, w_p, length, R = t
            if rough == "target":
                r = R @ np.abs(phi_t)
            elif rough == "prediction":
                r = R @ np.abs(phi_p)
            elif rough == "mean of both":
                r = 0.5 * (R @ np.abs(phi_t) + R @ np.abs(phi_p))
            elif rough == "max of both":
                r = np.maximum(R @ np.abs(phi_t), R @ np.abs(phi_p))
            elif rough == "edge alone":
                r = np.abs(phi_t)
            elif rough == "two rings":
                r = R @ (R @ np.abs(phi_t))
            elif rough == "spread":
                r = np.sqrt(np.maximum(R @ phi_t ** 2 - (R @ phi_t) ** 2, 0.0))
            if mask == "rational":
                m = 1.0 / (1.0 + r / s)
            elif mask == "exp":
                m = np.exp(-r / s)
            elif mask == "rational^2":
                m = 1.0 / (1.0 + (r / s) ** 2)
            elif mask == "none":
                m = np.ones_like(r)
            w = {"area": w_t, "none": np.ones_like(d), "edge length": length, "area of both": 0.5 * (w_t + w_p)}[weight]
            return float((w * m * d).sum() / w.sum())
        return f

    v = {"default (rational, 0.1 rad, area, target)": score()}
    for s in (0.025, 0.05, 0.2, 0.4):
        v[f"masking scale {s} rad"] = score(s=s)
    v["no masking"] = score(mask="none")
    v["masking exp(-r/s)"] = score(mask="exp")
    v["masking 1/(1+(r/s)^2)"] = score(mask="rational^2")
    for w in ("none", "edge length", "area of both"):
        v[f"weights: {w}"] = score(weight=w)
    for r in ("prediction", "mean of both", "max of both", "edge alone", "two rings", "spread"):
        v[f"roughness: {r}"] = score(rough=r)
    return v


def main():
    col, source = face_head(20)
    t = col.template
    ps = pairs(col)
    dame = get_registry().get("metric", "dame")()
    var = variants()
    names = list(var)
    vals = np.empty((len(names), len(ps)))
    check = np.empty(len(ps))
    rough_t = []
    for j, (kind, T, P) in enumerate(ps):
        terms = edge_terms(T, P, t)
        if kind == "mean":
            rough_t.append(terms[-1] @ np.abs(terms[1]))
        for i, n in enumerate(names):
            vals[i, j] = var[n](terms)
        check[j] = dame(P[None], T[None], t)[0][0]
    base = vals[0]
    assert np.allclose(base, check, rtol=1e-10, atol=0), "the default variant must be the dame metric"
    kinds = np.array([k for k, _, _ in ps])
    print(f"meshes: {source}, {t.n_vertices} vertices; {len(ps)} pairs ({len(KINDS)} kinds x {len(SUBJECTS)} subjects)")
    print("default DAME per kind, median [min-max] (rad): " + ", ".join(
        f"{k} {np.median(base[kinds == k]):.4f} [{base[kinds == k].min():.4f}-{base[kinds == k].max():.4f}]"
        for k in KINDS))
    print("target roughness r (rad) over the interior edges of the 6 neutrals, quantiles 10/50/90 %: "
          + " / ".join(f"{q:.3f}" for q in np.quantile(np.concatenate(rough_t), [0.1, 0.5, 0.9])))
    hdr = f"{'variant':<42} {'median rel':>10} {'max rel':>8} {'Spearman':>9} {'kinds':>6} {'worst kind':>10}"
    print(hdr)
    rows = []
    for i, n in enumerate(names):
        v = vals[i]
        rel = np.abs(v - base) / base
        rho = float(spearmanr(v, base)[0])
        rho_k = float(spearmanr([np.median(v[kinds == k]) for k in KINDS], [np.median(base[kinds == k]) for k in KINDS])[0])
        within, worst = min((float(spearmanr(v[kinds == k], base[kinds == k])[0]), k) for k in KINDS)
        rows.append({"variant": n, "median_rel_change": float(np.median(rel)), "max_rel_change": float(rel.max()),
                     "spearman": rho, "spearman_kinds": rho_k, "worst_within_kind_spearman": within,
                     "worst_kind": worst})
        print(f"{n:<42} {np.median(rel):>10.3f} {rel.max():>8.3f} {rho:>9.3f} {rho_k:>6.3f} {within:>10.3f} ({worst})")
    others = rows[1:]
    print(json.dumps({"source": source, "n_vertices": int(t.n_vertices), "pairs": len(ps), "kinds": KINDS,
                      "default_median_by_kind": {k: float(np.median(base[kinds == k])) for k in KINDS},
                      "default_range_by_kind": {k: [float(base[kinds == k].min()), float(base[kinds == k].max())] for k in KINDS},
                      "min_spearman": min(r["spearman"] for r in others),
                      "min_spearman_kinds": min(r["spearman_kinds"] for r in others),
                      "variants": rows}))


if __name__ == "__main__":
    main()
