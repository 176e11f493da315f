"""The main job's non-training stages, today's code against the code before issue 28's pipeline
work (``benchmarks/_before_pipeline.py``, a frozen copy from commit 162223a), side by side in one
process (alternating, medians).

    OMP_NUM_THREADS=2 python benchmarks/pipeline.py [--repeat 5]

* **Deformation Transfer's factorisation** (``TargetSystem``, once per target neutral: 260 of
  them in the one-expression main job): SciPy's default ``splu`` (COLAMD, partial pivoting)
  against ``fwk.geometry.factor_spd`` (symmetric ordering, no pivoting), on the main job's
  synthetic head (6,080 vertices) and on ICT-FaceKit's face-head region (11,248; a synthetic head
  of that size without the data, printed); factor and solve times, fill-in, and the largest difference of the solutions;
* **dr's polar decomposition** of 40 x 6,080 near-identity 3 x 3 matrices, before and today,
  and the largest difference of R;
* **dr's features of 160 meshes, fit then encode** (as pb fits a branch): computed twice before,
  once today (``fwk_dr.DR.raw_features`` remembers);
* **a k sweep's figure** (``fwk.evaluation.plots.scatter_pareto``, 40 points) with the label
  placement (``place_labels``) before and today, and the number of labels each placed.

The last line is one JSON object with every figure.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
from scipy.sparse.linalg import splu

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _before_pipeline as before  # noqa: E402
from _ict import alternate, face_head  # noqa: E402

import fwk_dr  # noqa: E402
import fwk_dt  # noqa: E402
from fwk.cache import forget  # noqa: E402
from fwk.geometry import factor_spd  # noqa: E402
from fwk.plugins import get_registry  # noqa: E402


def dt_row(name, V, F, n) -> dict:
    ts = fwk_dt.TargetSystem(V, F)
    K = (ts.Af.T @ ts.Af).tocsc()
    b = np.random.default_rng(0).standard_normal((K.shape[0], 3))
    f = alternate({"before": lambda: splu(K, permc_spec="COLAMD"), "today": lambda: factor_spd(K)}, n)
    lb, lt = splu(K, permc_spec="COLAMD"), factor_spd(K)
    s = alternate({"before": lambda: lb.solve(b), "today": lambda: lt.solve(b)}, n)
    xb, xt = lb.solve(b), lt.solve(b)
    r = {"mesh": name, "unknowns": K.shape[0], "factor_before_s": f["before"], "factor_today_s": f["today"],
         "solve_before_s": s["before"], "solve_today_s": s["today"], "fill_before": int(lb.L.nnz + lb.U.nnz),
         "fill_today": int(lt.L.nnz + lt.U.nnz), "max_rel_diff": float(np.abs(xt - xb).max() / np.abs(xb).max())}
    print(f"DT factor, {name} ({r['unknowns']} unknowns): {1e3 * r['factor_before_s']:.1f} -> "
          f"{1e3 * r['factor_today_s']:.1f} ms ({r['factor_before_s'] / r['factor_today_s']:.2f}x); solve "
          f"{1e3 * r['solve_before_s']:.2f} -> {1e3 * r['solve_today_s']:.2f} ms "
          f"({r['solve_before_s'] / r['solve_today_s']:.2f}x); fill {r['fill_before']} -> {r['fill_today']}; "
          f"largest difference {r['max_rel_diff']:.1e} of the largest value")
    return r


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5, help="timed calls per version (after one warm-up)")
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    import torch

    print(f"threads {torch.get_num_threads()} (OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS')}); "
          f"load average {load0:.2f}")
    out = {"load_avg": load0, "threads": torch.get_num_threads()}
    reg = get_registry()
    col = reg.get("dataset", "synthetic-heads")(n_vertices=6000, n_subjects=160, shapes=["neutral"]).load()
    N = np.asarray(col.positions)[:, 0]
    t = col.template
    out["dt"] = [dt_row(f"synthetic head, {t.n_vertices} vertices", N[0], t.triangles, a.repeat)]
    head, src = face_head(1)  # ICT-FaceKit's face-head region, or a synthetic head of its size
    out["dt"].append(dt_row(f"{src}, {head.template.n_vertices} vertices", head.template.vertices,
                            head.template.triangles, a.repeat))
    T = np.eye(3) + 0.1 * np.random.default_rng(1).standard_normal((40, t.n_vertices, 3, 3))
    p = alternate({"before": lambda: before.polar(T), "today": lambda: fwk_dr.polar(T)}, a.repeat)
    d = float(np.abs(before.polar(T)[0] - fwk_dr.polar(T)[0]).max())
    out["polar"] = {"matrices": int(T.size // 9), "before_s": p["before"], "today_s": p["today"], "max_diff": d}
    print(f"dr polar, {T.size // 9} matrices: {1e3 * p['before']:.0f} -> {1e3 * p['today']:.0f} ms "
          f"({p['before'] / p['today']:.2f}x); largest difference of R {d:.1e}")
    DR = reg.get("representation", "dr")

    def fit_encode(remember: bool):
        def go():
            forget(f"{fwk_dr.__name__}.raw_features")
            r = DR(scaling="std")
            r.fit(N, None, t)
            if not remember:
                forget(f"{fwk_dr.__name__}.raw_features")
            r.encode(N)
        return go

    e = alternate({"before": fit_encode(False), "today": fit_encode(True)}, max(1, a.repeat // 2))
    out["dr_fit_encode"] = {"meshes": len(N), "before_s": e["before"], "today_s": e["today"]}
    print(f"dr fit + encode, {len(N)} meshes: {e['before']:.2f} -> {e['today']:.2f} s ({e['before'] / e['today']:.2f}x)")
    from fwk.evaluation import plots

    pts = {str(k): (1 + 0.01 * k, 2 - 0.012 * k + 0.00005 * k * k) for k in range(0, 400, 10)}
    placed, today = {}, plots.place_labels
    png = Path(os.environ.get("TMPDIR", "/tmp")) / "fwk-pipeline-bench.png"

    def figure(fn, key):
        def spy(*args, **kw):
            texts = fn(*args, **kw)
            placed[key] = len(texts)
            return texts

        def go():  # the k sweep's figure as the main job draws it (scatter_pareto), with one placer or the other
            plots.place_labels = spy
            try:
                plots.scatter_pareto(pts, png, "L1 norm (validation, cm)", "FMPD (validation, unitless)",
                                     highlight="120", highlight_label="chosen k = 120")
            finally:
                plots.place_labels = today
        return go

    f = alternate({"before": figure(before.place_labels, "before"), "today": figure(today, "today")}, a.repeat)
    png.unlink(missing_ok=True)
    out["figure"] = {"points": len(pts), "before_s": f["before"], "today_s": f["today"],
                     "placed_before": placed["before"], "placed_today": placed["today"]}
    print(f"a k sweep's figure ({len(pts)} points, scatter_pareto): {1e3 * f['before']:.0f} -> "
          f"{1e3 * f['today']:.0f} ms ({f['before'] / f['today']:.2f}x); labels placed {placed['before']} -> "
          f"{placed['today']}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
