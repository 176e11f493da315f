"""Kabsch rigid registration with the reflection fix (thesis eqs. 3.2-3.5).

For point sets A, B (n, 3) with optional weights w, find R (proper rotation, det R = +1) and
t minimising sum_i w_i ||R a_i + t - b_i||^2: centre both by their weighted centroids,
H = A_c^T W B_c = U S V^T, d = sign(det(V U^T)), R = V diag(1, 1, d) U^T, t = b_bar - R a_bar.
"""
from __future__ import annotations

import numpy as np


def kabsch(A: np.ndarray, B: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """R (3, 3), t (3,) with R @ a + t ~ b; batched: A, B (b, n, 3) -> R (b, 3, 3), t (b, 3)."""
    A = np.asarray(A, dtype=np.float64)
    B = np.asarray(B, dtype=np.float64)
    batched = A.ndim == 3
    if not batched:
        A, B = A[None], B[None]
    B = np.broadcast_to(B, A.shape)
    if weights is None:
        w = np.full(A.shape[1], 1.0 / A.shape[1])
    else:
        w = np.asarray(weights, dtype=np.float64)
        w = w / w.sum()
    ca = np.einsum("n,bnk->bk", w, A)
    cb = np.einsum("n,bnk->bk", w, B)
    H = np.einsum("n,bni,bnj->bij", w, A - ca[:, None], B - cb[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", Vt, U)))
    d[d == 0] = 1.0
    D = np.zeros((len(A), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = np.einsum("bji,bjk,blk->bil", Vt, D, U)
    t = cb - np.einsum("bij,bj->bi", R, ca)
    return (R, t) if batched else (R[0], t[0])
