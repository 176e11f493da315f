"""Time the metrics for pairs of 11k-vertex meshes (target: DAME and FMPD <= 20 ms per pair on
2 cores) and one 11k-vertex render with an error map (target: <= 2 s).

    python benchmarks/metrics.py [--no-render]

Meshes: the ICT-FaceKit face-head region (11,248 vertices, 11,144 quads -> 22,288 triangles),
two sampled identities, or a synthetic head of that size when the data is absent. Prints a
table, then as its last line one JSON object with dame_ms, fmpd_ms, n_vertices (and more).
"""
import json
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ict import face_head, timeit  # noqa: E402

from fwk.plugins import get_registry  # noqa: E402


def main():
    col, source = face_head(2)
    t = col.template
    A, B = col.positions[0, 0][None], col.positions[1, 1][None]
    batch = 16
    rng = __import__("numpy").random.default_rng(0)
    PA = A + rng.normal(0, 0.05, (batch,) + A.shape[1:])
    PB = __import__("numpy").repeat(B, batch, axis=0)
    reg = get_registry()
    out = {"n_vertices": t.n_vertices, "n_triangles": int(len(t.triangles)), "source": source,
           "threads": os.environ.get("OMP_NUM_THREADS", "default"), "load_avg_1min": os.getloadavg()[0]}
    print(f"mesh: {source}, {t.n_vertices} vertices, {len(t.triangles)} triangles; load {out['load_avg_1min']:.1f}")
    print(f"{'metric':<10} {'ms per pair (best of 9)':>24} {f'ms per pair in a batch of {batch}':>28}")
    for name in ("l1", "l2", "euclidean", "dame", "fmpd"):
        m = reg.get("metric", name)()
        m(A, B, t)  # builds and caches the per-topology structures
        ms = 1000 * timeit(lambda: m(A, B, t), repeat=9)
        ms_b = 1000 * timeit(lambda: m(PA, PB, t), repeat=3) / batch
        out[f"{name}_ms"] = ms
        out[f"{name}_batch_ms"] = ms_b
        print(f"{name:<10} {ms:>24.2f} {ms_b:>28.2f}")
    if "--no-render" not in sys.argv:
        from fwk.evaluation.render import render_mesh

        err = reg.get("metric", "l1")()(A, B, t)[1][0]
        with tempfile.TemporaryDirectory() as d:
            t0 = time.perf_counter()
            render_mesh(A[0], t, Path(d) / "first.png", view="front", scalars=err, colorbar_title="L1")
            first = time.perf_counter() - t0
            times = []
            for view in ("front", "three-quarter", "front"):
                t0 = time.perf_counter()
                render_mesh(A[0], t, Path(d) / "r.png", view=view, scalars=err, colorbar_title="L1")
                times.append(time.perf_counter() - t0)
        out["render_first_s"] = first
        out["render_s"] = min(times)
        print(f"render (pyvista, 400x460, error map + colour bar): first in process {first:.2f} s, "
              f"then best of 3 {min(times):.2f} s")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
