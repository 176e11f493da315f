"""Geometry timings on the ICT-FaceKit face-head region (11,248 vertices), k = 500.

    python benchmarks/geometry.py [--k 500] [--skip-scipy] [--backend auto|cholmod|splu]

Times, in one run on the same mesh: the eigenbasis (fwk's spectrum slicing and scipy's default
``eigsh(L, k, M, sigma)``), the spectral assembly of a batch of meshes (fwk's U (U^T (M P)) and
the dense n x n X = U U^T M product), and the peak memory of the eigenbasis. Also the columns of
thesis table 4.1 (l. 1836-1838: U, X and eq. 5.10's assembly per mesh) and its mass-matrix cost
(l. 1676: "The CPU time is consistently higher by 20 ms per mesh when using the mass matrix
normalisation"): ``x_s`` forms the dense X = U U^T M; ``eig_no_mass_s`` solves the un-weighted
L u = lambda u (eq. 4.1) alike; ``assembly_no_mass_ms`` and ``dense_assembly_no_mass_ms`` assemble
per mesh with M = I (the un-weighted basis, X = U U^T), so that ``*_mass_extra_ms`` is the mass
matrix's cost per mesh in each of the two ways. Prints a table and,
as its last line, one JSON object. ``eig_backend`` says which factorisation the eigen solver used
(CHOLMOD from the optional scikit-sparse, else SciPy's SuperLU); ``load_avg`` is the 1-minute
load average when the run started (the timings assume a quiet machine). ``eig_peak_mb`` is
traced by tracemalloc (NumPy/SciPy arrays; CHOLMOD's own factor, a few MB, is not traced).
"""
import os
import argparse
import json
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.sparse.linalg import eigsh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _ict import face_head  # noqa: E402

from fwk.geometry.operators import cotangent_laplacian, mass_matrix  # noqa: E402
from fwk.geometry.spectral import SpectralProjector, generalized_eigs  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--k", type=int, default=500)
    ap.add_argument("--batch", type=int, default=100)
    ap.add_argument("--skip-scipy", action="store_true")
    ap.add_argument("--backend", default="auto", choices=["auto", "cholmod", "splu"])
    a = ap.parse_args()
    col, source = face_head(a.batch)
    t = col.template
    V, F = t.vertices, t.triangles
    L, M = cotangent_laplacian(V, F).tocsc(), mass_matrix(V, F).tocsc()
    from fwk.geometry.spectral import has_cholmod

    backend = a.backend if a.backend != "auto" else ("cholmod" if has_cholmod() else "splu")
    out = {"n_vertices": t.n_vertices, "k": a.k, "source": source, "eig_backend": backend,
           "load_avg": os.getloadavg()[0], "omp_threads": os.environ.get("OMP_NUM_THREADS")}

    t0 = time.perf_counter()
    w, U = generalized_eigs(L, M, a.k, backend=backend)
    out["eig_s"] = time.perf_counter() - t0
    tracemalloc.start()  # a second run for the peak memory: tracing slows allocation down
    generalized_eigs(L, M, a.k, backend=backend)
    out["eig_peak_mb"] = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    out["eig_orthonormality_error"] = float(np.abs(U.T @ (M @ U) - np.eye(a.k)).max())
    out["eig_residual"] = float(np.abs(L @ U - (M @ U) * w).max())

    if not a.skip_scipy:
        t0 = time.perf_counter()
        ws, _ = eigsh(L, k=a.k, M=M, sigma=-1e-8)
        out["eig_scipy_s"] = time.perf_counter() - t0
        out["eig_max_eigenvalue_difference"] = float(np.abs(np.sort(ws) - w).max())
    else:
        out["eig_scipy_s"] = None

    from fwk.plugins import get_registry

    P = np.asarray(col.positions[:, 0])
    mean = P.mean(0)
    spec = get_registry().get("assembler", "spectral")(k=a.k)
    spec.load_state_dict({"cuts": [a.k], "mass": True, "U": U, "m": M.diagonal(), "mean": mean})
    bands = spec.split(P)
    spec.assemble(bands)
    reps = 5
    t0 = time.perf_counter()
    for _ in range(reps):
        out_p = spec.assemble(bands)  # eq. 4.15: two band projections for the whole batch
    out["assembly_ms"] = 1000 * (time.perf_counter() - t0) / reps / len(P)
    out["assembly_exactness"] = float(np.abs(out_p - P).max())
    proj = SpectralProjector(U, M.diagonal())
    t0 = time.perf_counter()
    for _ in range(reps):
        low = proj.project(P - mean, 0, a.k) + mean
    out["projection_ms"] = 1000 * (time.perf_counter() - t0) / reps / len(P)
    X = U @ (U.T * M.diagonal()[None])  # the dense n x n operator the thesis used
    t0 = time.perf_counter()
    low_dense = np.einsum("ij,bjk->bik", X, P - mean, optimize=True) + mean
    out["dense_assembly_ms"] = 1000 * (time.perf_counter() - t0) / len(P)
    out["dense_x_gb"] = X.nbytes / 2**30
    out["assembly_max_difference"] = float(np.abs(low - low_dense).max())
    del X, low_dense

    # thesis table 4.1: X's own time, and the mass matrix's cost (the un-weighted basis alike)
    m = M.diagonal()
    t0 = time.perf_counter()
    X = U @ (U.T * m[None])
    out["x_s"] = time.perf_counter() - t0
    del X
    from scipy.sparse import identity

    t0 = time.perf_counter()
    _, U0 = generalized_eigs(L, identity(len(m), format="csc"), a.k, backend=backend)
    out["eig_no_mass_s"] = time.perf_counter() - t0
    spec0 = get_registry().get("assembler", "spectral")(k=a.k, mass=False)
    spec0.load_state_dict({"cuts": [a.k], "mass": False, "U": U0, "m": None, "mean": mean})
    bands0 = spec0.split(P)
    spec0.assemble(bands0)
    t0 = time.perf_counter()
    for _ in range(reps):
        spec0.assemble(bands0)
    out["assembly_no_mass_ms"] = 1000 * (time.perf_counter() - t0) / reps / len(P)
    out["assembly_mass_extra_ms"] = out["assembly_ms"] - out["assembly_no_mass_ms"]
    X0 = U0 @ U0.T
    t0 = time.perf_counter()
    np.einsum("ij,bjk->bik", X0, P - mean, optimize=True)
    out["dense_assembly_no_mass_ms"] = 1000 * (time.perf_counter() - t0) / len(P)
    out["dense_mass_extra_ms"] = out["dense_assembly_ms"] - out["dense_assembly_no_mass_ms"]
    del X0
    dr = get_registry().get("representation", "dr")(scaling="norm")
    dr.fit(P, None, t)
    Q = np.asarray(col.positions[0, 1])[None]  # an expression of subject 0
    dr.decode(dr.encode(Q), target=Q)
    best = np.inf
    for _ in range(7):
        t0 = time.perf_counter()
        X = dr.decode(dr.encode(Q), target=Q)
        best = min(best, time.perf_counter() - t0)
    out["dr_roundtrip_ms"] = 1000 * best
    out["dr_roundtrip_max_error"] = float(np.abs(X - Q).max())

    print(f"mesh: {source}, {t.n_vertices} vertices, k = {a.k}, batch {len(P)}")
    for key, v in out.items():
        if key not in ("source",):
            print(f"  {key:<32} {v if v is None or isinstance(v, (int, str)) else f'{v:.4g}'}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
