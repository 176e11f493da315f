"""Measure, on ICT-FaceKit face-head pairs, how far fwk's FMPD was from the authors' code before
the per-corner clamp (issue 17), how far it is now, and how much the quad triangulation moves it.
Not a test; run by hand (about a minute on one core):

    OMP_NUM_THREADS=1 python tests/references/measure_fmpd_fix.py [--subjects 10] [--before COMMIT]

Pairs (ict-facekit, seed 0, ``n_subjects`` sampled identities): every pair of identities'
neutrals (i < j), and each of the three built-in expressions against its own neutral. Columns:
``before`` is ``fwk_fmpd`` as of COMMIT (default 5b25de3, which clamped the *sum* of an edge's two
half-cotangents), ``after`` is the metric in the tree, both against the literal port
``wang2012_fmpd`` of the authors' MATLAB code; ``other diagonal`` is the tree's metric with
every quad (a, b, c, d) split into (a, b, d), (b, c, d) instead of fwk's fan (a, b, c), (a, c, d),
relative to the fan. Prints a table and a JSON line.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.references import wang2012_fmpd as W  # noqa: E402


def _module_at(commit: str):
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{commit}:plugins/metrics/fwk_fmpd/__init__.py"],
                         capture_output=True, text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "fwk_fmpd_before.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("fwk_fmpd_before", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def other_diagonal(t):
    """Triangles of ``t``'s polygons with every quad split along its other diagonal."""
    off, pv = t.poly_offsets, t.poly_vertices
    tris = []
    for p in range(len(off) - 1):
        f = pv[off[p]:off[p + 1]]
        if len(f) == 4:
            tris += [[f[0], f[1], f[3]], [f[1], f[2], f[3]]]
        else:
            tris += [[f[0], f[k], f[k + 1]] for k in range(1, len(f) - 1)]
    return np.asarray(tris, dtype=np.int64)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--subjects", type=int, default=10)
    ap.add_argument("--before", default="5b25de3")
    args = ap.parse_args()
    from fwk.cache import Cache
    from fwk.data import Template
    from fwk.plugins import get_registry
    from fwk.testing import ICT_SKIP_REASON, ict_path

    if ict_path() is None:
        sys.exit(ICT_SKIP_REASON)
    reg = get_registry()
    col = reg.get("dataset", "ict-facekit")(path=str(ict_path()), n_subjects=args.subjects).load(Cache())
    t = col.template
    t_alt = Template(t.vertices, other_diagonal(t))
    X = np.asarray(col.positions)
    S = len(X)
    pairs = [("identity", (i, 0), (j, 0)) for i in range(S) for j in range(i + 1, S)]
    pairs += [("expression", (s, e), (s, 0)) for s in range(S) for e in range(1, X.shape[1])]
    before, after = _module_at(args.before).FMPD(), reg.get("metric", "fmpd")()
    rows = []
    for kind, a, b in pairs:
        A, B = X[a], X[b]
        ref = W.perceptual_distance(B, t.triangles, A)     # target B, prediction A
        old = float(before(A[None], B[None], t)[0][0])
        new = float(after(A[None], B[None], t)[0][0])
        alt = float(after(A[None], B[None], t_alt)[0][0])
        rows.append((kind, ref, old, new, alt))
    from scipy.stats import spearmanr

    print(f"ICT face-head, {t.n_vertices} vertices, {len(t.triangles)} triangles; {len(rows)} pairs")
    print("relative differences |x - port| / port (before, after) and |other - fan| / fan; abs: in FMPD units")
    print(f"{'pairs':<11} {'n':>3} {'FMPD median':>11} | {'before: med':>11} {'p90':>8} {'max abs':>8} {'rho':>6} | "
          f"{'after: max':>10} | {'diagonal: med':>13} {'p90':>8} {'max abs':>8} {'rho':>6}")
    out = {"n_subjects": S, "before_commit": args.before}
    for kind in ("identity", "expression", "all"):
        v = np.array([x[1:] for x in rows if kind in ("all", x[0])])
        ref, old, new, alt = v.T
        rb, ra, rd = np.abs(old - ref) / ref, np.abs(new - ref) / ref, np.abs(alt - new) / new
        rho_b, rho_d = spearmanr(old, ref)[0], spearmanr(alt, new)[0]
        print(f"{kind:<11} {len(v):>3} {np.median(ref):>11.4g} | {np.median(rb):>11.2e} {np.quantile(rb, 0.9):>8.2e} "
              f"{np.abs(old - ref).max():>8.1e} {rho_b:>6.3f} | {ra.max():>10.1e} | {np.median(rd):>13.2e} "
              f"{np.quantile(rd, 0.9):>8.2e} {np.abs(alt - new).max():>8.1e} {rho_d:>6.3f}")
        out[kind] = {"pairs": len(v), "fmpd_median": float(np.median(ref)),
                     "before_median_rel": float(np.median(rb)), "before_p90_rel": float(np.quantile(rb, 0.9)),
                     "before_max_rel": float(rb.max()), "before_max_abs": float(np.abs(old - ref).max()),
                     "before_spearman": float(rho_b), "after_max_rel": float(ra.max()),
                     "other_diagonal_median_rel": float(np.median(rd)), "other_diagonal_p90_rel": float(np.quantile(rd, 0.9)),
                     "other_diagonal_max_abs": float(np.abs(alt - new).max()), "other_diagonal_spearman": float(rho_d)}
    print(json.dumps(out))


if __name__ == "__main__":
    main()
