"""Deformation Transfer of a registered template's expressions onto a scan's own triangles.

``fwk.rig.register`` fits the run's template to a head of any topology ("the scan") and carries
each predicted expression back barycentrically: every scan vertex takes the displacement of its
closest point on the registered template Y. ``DeformationCarry`` carries instead the template's
*deformation gradients* (Sumner & Popovic 2004) onto the scan's triangles and solves for the
scan's vertices in least squares, anchored softly to the barycentric carry:

1. Template gradients. For the expression E of Y (template frame), each template triangle t has
   Q_t = W~_t W_t^-1 with W_t = [y2 - y1, y3 - y1, n / sqrt|n|] on Y and W~_t the same on E
   (Sumner's fourth vertex; Q_t is exact for a rotation and a uniform scale, which map n/sqrt|n|
   alike).
2. A smooth gradient field on the scan (``field="smooth"``, the default). Each template vertex
   gets the area-weighted mean of the Q_t around it, each scan vertex the barycentric blend of
   those at its closest point (triangle tau_j, coordinates b_j), each scan triangle s the mean
   over its three corners: Q_s = (1/3) sum_{j in s} sum_k b_jk Qv[T[tau_j, k]] (template
   frame), taken into the scan's frame as R Q_s R^T (the similarity's rotation; a gradient has
   no units), and faded like the barycentric carry: Q_s <- I + wbar_s (Q_s - I), wbar_s the
   mean weight w_j of its corners (a part the template lacks keeps the identity).
   ``field="sharp"``: Q_s is the Q_t of the template triangle holding the closest point of the
   scan triangle's centroid (then faded and rotated alike).
   Measured, a held-out ICT-FaceKit head midpoint-subdivided (tests/rig/test_register.py), DAME
   over the direct rig's for jawOpen / mouthSmile_L / eyeBlink_L: smooth 2.03x / 2.44x / 1.27x,
   sharp 2.51x / 3.03x / 1.64x, the barycentric carry 2.54x / 3.24x / 2.05x; L1 within 0.02x of
   each other. The smooth field is not exact where the sharp one is: on a scan that is the
   template itself (permuted, moved) sharp gives the direct rig exactly, smooth blends each
   triangle's gradient with its neighbours' (on the rig tests' 8 x 8 grid heads, whose
   expressions span a few triangles, 15-18% of the motion off; the blend spans one to two
   template edges, 3-6 mm on the 11k-vertex ICT-FaceKit template).
3. The solve. The scan's displacement d (p, 3) minimises

       sum_s a_s |grad_s d - (Q_s - I) P_s|_F^2  +  mu sum_j m_j |d_j - c_j|^2

   with a_s the scan triangle's area, grad_s d the 3 x 3 gradient of the piecewise linear d on
   it (row c: the gradient of coordinate c), P_s = I - n_s n_s^T the projection onto its plane
   (grad_s d is tangent), m_j the barycentric vertex area (``fwk.geometry.mass_matrix``; the
   mean area for an isolated vertex), c_j the barycentric carry's displacement (the anchor: it
   holds the translation and the long wavelengths the gradients leave free) and
   mu = 1 / l^2, l = ``ANCHOR_LENGTH`` median template edges in scan units (both terms then
   have units of area: wavelengths above l follow the anchor, below it the gradients). The
   normal equations (G^T A G + mu M) d = G^T A g + mu M c, with G the (3 m_s x p) gradient
   operator and G^T A G the scan's cotangent Laplacian, are factorised once per scan (SuperLU
   ordered for symmetry, ``fwk.geometry.factor_spd``) and solved for every expression, three
   columns each. Degenerate scan triangles (area <= 1e-14 x the mean) carry no gradient term.

Properties (tests/rig/test_carry.py): a zero deformation gives the scan exactly; a rotation and
uniform scale of the template (about any point) is reproduced exactly when the scan lies on the
registered template (both terms vanish); with ``field="sharp"`` any expression is reproduced
exactly on a scan that is the template re-ordered; the sparse solve equals a dense least squares
built triangle by triangle in an orthonormal tangent basis.

Measured (tests/rig/test_register.py, a held-out ICT-FaceKit head midpoint-subdivided, 44,786
vertices, 2 cores shared with a training): setting up 0.5 s, 0.05 s per expression.
"""
from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp

from ..errors import DataError
from ..geometry import factor_spd, mass_matrix
from .register import Registration, closest_points, median_edge

#: the anchor's length l, in median template edges: mu = 1 / l^2. Measured on the ICT held-out
#: head (smooth field): 0.3, 1 and 3 edges gave DAME 2.18x / 2.03x / 2.01x of the direct rig for
#: jawOpen, L1 the same within 0.01x; 10 and 100 edges (sharp field) let the long wavelengths
#: drift: eyeBlink_L L1 0.84x, 1.00x against 0.75x. On the 8 x 8 grid heads the smooth field is
#: off by 15-18% of the motion with 1 edge, 22-26% with 3: 1.
ANCHOR_LENGTH = 1.0
#: how a scan triangle's gradient is taken from the template's (step 2; the first: default)
FIELDS = ("smooth", "sharp")
#: a scan triangle with area at most this fraction of the mean carries no gradient term
DEGENERATE = 1e-14


def sumner_frames(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(m, 3, 3): columns y2 - y1, y3 - y1, n / sqrt|n| of every triangle (Sumner's frame)."""
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    n = np.cross(e1, e2)
    e3 = n / np.sqrt(np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300))
    return np.stack([e1, e2, e3], axis=-1)


def gradient_operator(V: np.ndarray, F: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """(G (3m x p), area (m,), unit normal (m, 3)): row 3s + r of G x is component r of the
    gradient of the piecewise linear x on triangle s (grad phi_k = n x e_k / (2a), e_k the edge
    opposite corner k, counter-clockwise); a degenerate triangle gets zero rows and zero area."""
    V = np.asarray(V, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    a0, a1, a2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    n = np.cross(a1 - a0, a2 - a0)
    dbl = np.linalg.norm(n, axis=1)
    ok = dbl > DEGENERATE * max(dbl.mean() if len(dbl) else 0.0, 1e-300)
    safe = np.where(ok, dbl, 1.0)
    nu = n / safe[:, None]
    g = np.stack([np.cross(nu, a2 - a1), np.cross(nu, a0 - a2), np.cross(nu, a1 - a0)], 1) / safe[:, None, None]
    g[~ok] = 0.0
    m = len(F)
    rows = np.repeat(3 * np.arange(m), 9) + np.tile(np.arange(3), 3 * m)   # (s, k, r) -> 3s + r
    cols = np.repeat(F.reshape(-1), 3)
    G = sp.csr_matrix((g.reshape(-1), (rows, cols)), shape=(3 * m, len(V)))
    return G, np.where(ok, 0.5 * dbl, 0.0), np.where(ok[:, None], nu, 0.0)


class DeformationCarry:
    """A registration's expressions carried onto the scan's triangles by Deformation Transfer
    (module docstring); ``carry(E)`` has ``Registration.carry``'s signature and units.
    ``field``: ``smooth`` (default) or ``sharp`` (step 2)."""

    def __init__(self, reg: Registration, scan_triangles: np.ndarray, anchor_length: float = ANCHOR_LENGTH,
                 field: str = "smooth"):
        t0 = time.perf_counter()
        if field not in FIELDS:
            raise DataError(f"Deformation Transfer field {field!r}: unknown (fields: {', '.join(FIELDS)})")
        SF = np.asarray(scan_triangles, dtype=np.int64)
        if SF.ndim != 2 or SF.shape[1] != 3 or not len(SF):
            raise DataError("the scan has no triangles: Deformation Transfer needs them (use the barycentric carry)")
        V = np.asarray(reg.scan, dtype=np.float64)
        p, Ft, Y = len(V), reg.triangles, reg.neutral
        self.reg = reg
        G, area, nu = gradient_operator(V, SF)
        GtA = (G.T @ sp.diags(np.repeat(area, 3))).tocsr()
        L = GtA @ G
        h = median_edge(Y, Ft) / reg.unit                     # scan units
        self.mu = 1.0 / (anchor_length * h) ** 2
        self.mass = mass_matrix(V, SF, kind="barycentric").diagonal()
        self.lu = factor_spd(L + sp.diags(self.mu * self.mass))
        self.GtA = GtA
        self.P = np.eye(3)[None] - nu[:, :, None] * nu[:, None, :]  # (m_s, 3, 3) tangent projections
        # the smooth field: scan triangle <- scan corners <- template vertices (bary) <- template triangles
        ta = 0.5 * np.linalg.norm(np.cross(Y[Ft[:, 1]] - Y[Ft[:, 0]], Y[Ft[:, 2]] - Y[Ft[:, 0]]), axis=1)
        vt = sp.csr_matrix((np.repeat(ta, 3), (Ft.reshape(-1), np.repeat(np.arange(len(Ft)), 3))),
                           shape=(len(Y), len(Ft)))
        tot = np.asarray(vt.sum(1)).ravel()
        vt = sp.diags(np.where(tot > 0, 1.0 / np.where(tot > 0, tot, 1.0), 0.0)) @ vt
        bary = sp.csr_matrix((reg.bary.reshape(-1), (np.repeat(np.arange(p), 3), Ft[reg.triangle].reshape(-1))),
                             shape=(p, len(Y)))
        corners = sp.csr_matrix((np.full(SF.size, 1.0 / 3), (np.repeat(np.arange(len(SF)), 3), SF.reshape(-1))),
                                shape=(len(SF), p))
        if field == "smooth":
            self.blend = (corners @ bary @ vt).tocsr()                # (m_s, m_t)
        else:  # sharp: the template triangle holding the closest point of the scan triangle's centroid
            X = (V - reg.translation) @ reg.rotation * reg.unit
            tri, _, _ = closest_points(Y, Ft, X[SF].mean(1))
            self.blend = sp.csr_matrix((np.ones(len(SF)), (np.arange(len(SF)), tri)), shape=(len(SF), len(Ft)))
        self.wbar = reg.weight[SF].mean(1)
        self.W0inv = np.linalg.inv(sumner_frames(Y, Ft))
        self.seconds = time.perf_counter() - t0

    def gradients(self, expression: np.ndarray) -> np.ndarray:
        """(m_s, 3, 3): each scan triangle's target gradient Q_s, scan frame, faded (step 2)."""
        E = np.asarray(expression, dtype=np.float64)
        Q = sumner_frames(E, self.reg.triangles) @ self.W0inv                  # (m_t, 3, 3) template frame
        Qs = (self.blend @ Q.reshape(-1, 9)).reshape(-1, 3, 3)
        R = self.reg.rotation
        Qs = R @ Qs @ R.T
        return np.eye(3)[None] + self.wbar[:, None, None] * (Qs - np.eye(3)[None])

    def carry(self, expression: np.ndarray) -> np.ndarray:
        """The scan's vertices (p, 3), its frame and units, moved by an expression (n, 3) of the
        registered neutral (template frame)."""
        g = (self.gradients(expression) - np.eye(3)[None]) @ self.P                # rows: grad of d^c
        target = np.transpose(g, (0, 2, 1)).reshape(-1, 3)                        # [(s, r), c]
        c = self.reg.carry(expression) - self.reg.scan
        d = self.lu.solve(self.GtA @ target + self.mu * self.mass[:, None] * c)
        return self.reg.scan + d
