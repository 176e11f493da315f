"""Frozen copies of the main job's pipeline routines as they were before issue 28's pipeline work
(commit 162223a), for ``benchmarks/pipeline.py`` to time side by side with today's: dr's polar
decomposition (Newton on (..., 3, 3) slices) and the figures' label placement (a trial annotation,
with its leader line, per candidate place). Not used by fwk."""
from __future__ import annotations

import numpy as np

from fwk.evaluation.plots import _DISTANCES, _PLACES, LABEL_PT


def _cross_into(out, a, b):
    """out[..., :] = a x b for (..., 3) arrays (np.cross is several times slower on small rows)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    out[..., 0] = a1 * b2 - a2 * b1
    out[..., 1] = a2 * b0 - a0 * b2
    out[..., 2] = a0 * b1 - a1 * b0
    return out


def _cross(a, b):
    return _cross_into(np.empty(np.broadcast_shapes(a.shape, b.shape)), a, b)


def _cofactor(X):
    c = np.empty_like(X)
    _cross_into(c[..., 0, :], X[..., 1, :], X[..., 2, :])
    _cross_into(c[..., 1, :], X[..., 2, :], X[..., 0, :])
    _cross_into(c[..., 2, :], X[..., 0, :], X[..., 1, :])
    return c


def polar(T, iters: int = 30, tol: float = 1e-14):
    """T = R S with R a rotation and S symmetric: scaled Newton iteration (Higham 1986),
    X <- (g X + X^-T / g) / 2, g = |det X|^(-1/3), vectorised over (..., 3, 3); vertices whose
    T has det <= 0 (a reflection, or degenerate) use the SVD with det R = +1."""
    X = T.copy()
    det = np.einsum("...i,...i->...", X[..., 0, :], _cofactor(X)[..., 0, :])
    bad = det <= 1e-300
    X[bad] = np.eye(3)
    for _ in range(iters):
        cof = _cofactor(X)
        det = np.einsum("...i,...i->...", X[..., 0, :], cof[..., 0, :])
        g = np.abs(det) ** (-1.0 / 3.0)
        Xn = 0.5 * (g[..., None, None] * X + cof / (g * det)[..., None, None])
        done = np.abs(Xn - X).max() < tol
        X = Xn
        if done:
            break
    R = X
    if bad.any():
        U, sig, Vt = np.linalg.svd(T[bad])
        d = np.sign(np.linalg.det(U @ Vt))
        d[d == 0] = 1
        U[..., :, 2] *= d[..., None]
        R[bad] = U @ Vt
    S = np.einsum("...ji,...jk->...ik", R, T)
    S = 0.5 * (S + np.swapaxes(S, -1, -2))
    return R, S



def _hits(box, rects: np.ndarray) -> bool:
    """Whether the display-space ``box`` overlaps any of ``rects`` ((m, 4): x0, y0, x1, y1)."""
    if not len(rects):
        return False
    return bool(np.any((rects[:, 0] < box.x1) & (rects[:, 2] > box.x0) & (rects[:, 1] < box.y1) & (rects[:, 3] > box.y0)))


def place_labels(ax, points, labels, first=(), fontsize: float = LABEL_PT, markers=None, avoid=(), lines=()) -> list:
    """Annotate ``points`` (k, 2, data coordinates) with ``labels`` without overprinting: the
    points ``first`` (indices) are labelled first, then the others in order; each label takes
    the first place around its point (eight directions, growing distances; beyond the nearest a
    thin leader line ties it to its point) where it overlaps no earlier label, no point's marker
    (``markers``: each point's marker radius in pixels, default 5), no drawn line (``lines``:
    polylines in data coordinates, e.g. the Pareto front) and nothing of ``avoid`` (display-space
    boxes, e.g. the legend's), and stays inside the axes; a label that fits nowhere is left out.
    Returns the placed matplotlib Text objects (a label left out has none)."""
    from matplotlib.text import Text

    fig = ax.figure
    fig.canvas.draw()  # the limits and layout the labels are placed in
    renderer = fig.canvas.get_renderer()
    P = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    xy = ax.transData.transform(P) if len(P) else np.zeros((0, 2))
    radius = np.full(len(P), 5.0) if markers is None else np.asarray(markers, dtype=np.float64)
    blocked = [np.column_stack([xy - radius[:, None], xy + radius[:, None]])]
    for line in lines:  # each segment sampled every ~3 pixels, 1.5-pixel boxes
        L = ax.transData.transform(np.asarray(line, dtype=np.float64).reshape(-1, 2))
        for a, b in zip(L[:-1], L[1:]):
            t = np.linspace(0, 1, max(2, int(np.hypot(*(b - a)) / 3)))[:, None]
            q = a + t * (b - a)
            blocked.append(np.column_stack([q - 1.5, q + 1.5]))
    blocked += [np.array([[b.x0, b.y0, b.x1, b.y1]]) for b in avoid]
    blocked = np.concatenate(blocked) if blocked else np.zeros((0, 4))
    frame = ax.get_window_extent(renderer)
    first = [int(i) for i in first]
    done = set(first)
    order = first + [i for i in range(len(labels)) if i not in done]
    placed, boxes = [], np.zeros((0, 4))
    for i in order:
        for d, (ux, uy, ha, va) in ((d, p) for d in _DISTANCES for p in _PLACES):
            far = d > _DISTANCES[0]
            t = ax.annotate(str(labels[i]), tuple(P[i]), fontsize=fontsize, xytext=(ux * d, uy * d),
                            textcoords="offset points", ha=ha, va=va,
                            arrowprops=dict(arrowstyle="-", lw=0.5, color="0.45", shrinkA=0, shrinkB=3) if far else None)
            whole = t.get_window_extent(renderer)  # with its leader line: no two labels' overlap
            box = Text.get_window_extent(t, renderer)  # the text alone: clear of every point and line, inside
            inside = (box.x0 >= frame.x0 and box.x1 <= frame.x1 and box.y0 >= frame.y0 and box.y1 <= frame.y1)
            if inside and not _hits(whole, boxes) and not _hits(box, blocked):
                placed.append(t)
                boxes = np.vstack([boxes, [[whole.x0, whole.y0, whole.x1, whole.y1]]])
                break
            t.remove()
    return placed


