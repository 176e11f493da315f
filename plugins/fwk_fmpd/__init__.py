"""Metric ``fmpd``: Fast Mesh Perceptual Distance (Wang, Torkhani & Montanvert 2012).

Per mesh (following the authors' MATLAB code, DESIGN.md "Reference notes"):

1. discrete Gaussian curvature K_i = c_i - sum of the angles at vertex i, c_i = 2 pi inside
   and pi on the border (not divided by an area);
2. L = D - W with W_ij = (cot alpha_ij + cot beta_ij) / 2 over the faces sharing edge ij, each
   clamped to [0.001, 1000]; local roughness R_i = |(L |K|)_i / L_ii|;
3. with barycentric vertex areas a_i, R-bar = sum a_i R_i / sum a_i for both meshes;
4. masking and saturation: eps = 0.0005, R_max = max(0.2, 5 min(R-bar_1, R-bar_2)),
   t = max(min(R-bar_1, R-bar_2), eps); R' = clamp(R, eps, R_max)^0.15 - eps^0.15 and, above
   T = t^0.15 - eps^0.15, R' <- (R' - T) * 0.5 + T;
5. global roughness GR = sum a_i R'_i / sum a_i; FMPD = min(1, 8 |GR_1 - GR_2|).

The per-vertex map is 8 |R'_1 - R'_2| (the local contribution before the area integral).
Everything is angle based, so FMPD is invariant to rigid motion and uniform scale.
"""
from __future__ import annotations

import numpy as np

from fwk.geometry import edge_topology
from fwk.hookspecs import hookimpl

EPS = 0.0005
EXP = 0.15


def _angles(V, F):
    """Corner angles (b, m, 3) and face areas (b, m)."""
    P = [V[:, F[:, k]] for k in range(3)]
    ang = []
    for k in range(3):
        u = P[(k + 1) % 3] - P[k]
        v = P[(k + 2) % 3] - P[k]
        cr = np.linalg.norm(np.cross(u, v), axis=-1)
        ang.append(np.arctan2(cr, np.einsum("bmk,bmk->bm", u, v)))
    area = 0.5 * np.linalg.norm(np.cross(P[1] - P[0], P[2] - P[0]), axis=-1)
    return np.stack(ang, -1), area


def roughness(V: np.ndarray, template) -> tuple[np.ndarray, np.ndarray]:
    """Local roughness R (b, n) and barycentric vertex areas (b, n)."""
    F = template.triangles
    n = template.n_vertices
    topo = edge_topology(F, n)
    ang, area = _angles(V, F)
    b = len(V)
    idx = F.ravel()
    angle_sum = np.stack([np.bincount(idx, ang[i].ravel(), minlength=n) for i in range(b)])
    c = np.where(topo.border_vertex, np.pi, 2 * np.pi)
    K = np.abs(c - angle_sum)
    cot = 1.0 / np.tan(np.clip(ang, 1e-12, np.pi - 1e-12))
    ne = len(topo.edges)
    eidx = topo.face_edges.ravel()  # edge opposite corner k
    W = np.stack([np.bincount(eidx, 0.5 * cot[i].ravel(), minlength=ne) for i in range(b)])
    W = np.clip(W, 0.001, 1000.0)
    i, j = topo.edges[:, 0], topo.edges[:, 1]
    D = np.stack([np.bincount(i, W[s], minlength=n) + np.bincount(j, W[s], minlength=n) for s in range(b)])
    WK = np.stack([np.bincount(i, W[s] * K[s, j], minlength=n) + np.bincount(j, W[s] * K[s, i], minlength=n)
                   for s in range(b)])
    R = np.abs((D * K - WK) / np.maximum(D, 1e-300))
    va = np.stack([np.bincount(idx, np.repeat(area[s] / 3.0, 3), minlength=n) for s in range(b)])
    return R, va


def modulate(R, t, r_max):
    Rm = np.clip(R, EPS, r_max[:, None]) ** EXP - EPS ** EXP
    T = (t ** EXP - EPS ** EXP)[:, None]
    return np.where(Rm > T, (Rm - T) * 0.5 + T, Rm)


class FMPD:
    """Fast Mesh Perceptual Distance (perceptual; unitless, in [0, 1])."""

    name = "fmpd"
    units = "1"
    power = 0
    display_scale = 1e-2
    rigid_invariant = True

    def __call__(self, pred, target, template):
        pred = np.asarray(pred, dtype=np.float64)
        target = np.asarray(target, dtype=np.float64)
        if pred.ndim == 2:
            pred, target = pred[None], target[None]
        R1, a1 = roughness(target, template)
        R2, a2 = roughness(pred, template)
        rb1 = (R1 * a1).sum(-1) / a1.sum(-1)
        rb2 = (R2 * a2).sum(-1) / a2.sum(-1)
        lo = np.minimum(rb1, rb2)
        r_max = np.maximum(0.2, 5 * lo)
        t = np.maximum(lo, EPS)
        M1, M2 = modulate(R1, t, r_max), modulate(R2, t, r_max)
        g1 = (M1 * a1).sum(-1) / a1.sum(-1)
        g2 = (M2 * a2).sum(-1) / a2.sum(-1)
        return np.minimum(1.0, 8 * np.abs(g1 - g2)), 8 * np.abs(M1 - M2)


@hookimpl
def fwk_register_metrics():
    return [FMPD]
