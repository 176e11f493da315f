"""Time of registering a head of another topology to an 11,248-vertex template (issue 27's target:
under 60 s for the registration on 2 cores) and of carrying expressions onto it.

The template is subject 0's face-head neutral of ICT-FaceKit (a synthetic head of the same size
when the data is absent); the scan is subject 1's, midpoint-subdivided (44,786 vertices),
permuted, in millimetres, rotated and moved, with 10 landmark pairs picked at random (seeded), as
``tests/rig/test_register.py``'s held-out test builds it. Prints the registration's own times
(the non-rigid fit and the correspondence), the Deformation Transfer carry's set-up and
per-expression time, the thread count and the load average: the machine is shared, so compare
numbers of one run, and read a time with its load.

    python benchmarks/register.py [--threads N] [--trimesh]

``--trimesh`` also registers with trimesh's own ``nricp_amberg`` (``register(fit="trimesh")``),
alternating with fwk's (fwk, trimesh, fwk), and prints both times and how far the two registered
templates are apart.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np

from _ict import face_head


def _rotation(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--trimesh", action="store_true", help="also time trimesh's nricp_amberg, alternating")
    args = ap.parse_args()
    import torch
    import trimesh

    from fwk.rig.carry import DeformationCarry
    from fwk.rig.register import register

    torch.set_num_threads(args.threads)
    col, what = face_head(n_subjects=2)
    F = col.template.triangles
    M, P = np.asarray(col.positions[0, 0]), np.asarray(col.positions[1, 0])
    rng = np.random.default_rng(5)
    V2, F2 = trimesh.remesh.subdivide(P, F)
    perm = rng.permutation(len(V2))
    inv = np.argsort(perm)
    R, t = _rotation(rng), np.array([250.0, -80.0, 40.0])
    scan = (10.0 * V2 @ R.T + t)[perm]
    Fs = inv[F2]
    picks = rng.choice(len(M), 10, replace=False)
    print(f"{what}: template {len(M)} vertices, scan {len(scan)} vertices ({len(Fs)} triangles), "
          f"{args.threads} thread(s), load average {os.getloadavg()[0]:.2f}")
    def timed(fit=None):
        t0 = time.perf_counter()
        reg = register(M, F, scan, Fs, picks, scan[inv[picks]], template_units=col.units, say=None, fit=fit)
        return reg, time.perf_counter() - t0

    reg, t_reg = timed()
    if args.trimesh:  # side by side: trimesh's fit, then fwk's again
        ref, t_tri = timed("trimesh")
        _, t_again = timed()
        print(f"registration with fwk.rig.nricp {t_reg:.1f} and {t_again:.1f} s, with trimesh's nricp_amberg "
              f"{t_tri:.1f} s ({t_tri / ((t_reg + t_again) / 2):.2f}x); registered templates apart by at most "
              f"{np.abs(ref.neutral - reg.neutral).max():.2g} template units")
    t0 = time.perf_counter()
    dc = DeformationCarry(reg, Fs)
    t_setup = time.perf_counter() - t0
    E = np.asarray(col.positions[1, 1:])  # subject 1's expressions, as stand-ins for a model's
    t0 = time.perf_counter()
    for X in E:
        dc.carry(X)
    t_each = (time.perf_counter() - t0) / max(len(E), 1)
    d = np.asarray(reg.distance) if hasattr(reg, "distance") else None
    res = f"; residual mean {d.mean():.3g}, max {d.max():.3g} scan units" if d is not None else ""
    print(f"registration {t_reg:.1f} s (target < 60 s){res}; Deformation Transfer carry: set-up {t_setup:.2f} s, "
          f"{t_each:.3f} s per expression ({len(E)} expressions); load average after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
