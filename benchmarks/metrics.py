"""Time DAME and FMPD for one pair of 11k-vertex meshes (target: <= 20 ms each on 2 cores).

    python benchmarks/metrics.py

Prints a table, then as its last line one JSON object with dame_ms, fmpd_ms, n_vertices.
"""
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ict import face_head, timeit  # noqa: E402

from fwk.plugins import get_registry  # noqa: E402


def main():
    col, source = face_head(2)
    t = col.template
    A, B = col.positions[0, 0][None], col.positions[1, 1][None]
    reg = get_registry()
    out = {"n_vertices": t.n_vertices, "source": source}
    print(f"{'metric':<8} {'ms per pair (best of 7)':>24}   mesh: {source}, {t.n_vertices} vertices")
    for name in ("l1", "dame", "fmpd"):
        m = reg.get("metric", name)()
        ms = 1000 * timeit(lambda: m(A, B, t))
        out[f"{name}_ms"] = ms
        print(f"{name:<8} {ms:>24.2f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
