"""Scatter plots with the Pareto front (thesis figures 3.3, 4.9, 4.12, 5.8, 5.9) and line plots.

Point labels never overprint (``place_labels``): the front's points are labelled first, each
label tries four places around its point, and one that fits nowhere is left out. Figures are
written atomically (a reader never sees half a PNG).
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..cache import atomic_write_bytes
from .core import pareto_front

#: where a point's label may go: (dx, dy) in points, horizontal and vertical alignment
_PLACES = ((4, 3, "left", "bottom"), (4, -3, "left", "top"), (-4, 3, "right", "bottom"), (-4, -3, "right", "top"))


def _plt():
    """matplotlib.pyplot on the Agg backend. Deferred: pyplot costs ~0.5 s of import time that
    `fwk list` and runs that draw nothing need not pay."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig, ax, path, xlabel, ylabel, title):
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def save_figure(fig, path, **savefig) -> Path:
    """Write ``fig`` to ``path`` (its format from the suffix) atomically, with the umask's mode,
    and close it; ``savefig``: matplotlib's options (dpi, facecolor, ...)."""
    plt = _plt()
    path = Path(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lstrip(".") or "png", **savefig)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


def place_labels(ax, points, labels, first=(), fontsize: float = 7) -> list:
    """Annotate ``points`` (k, 2, data coordinates) with ``labels`` without overprinting: the
    points ``first`` (indices) are labelled first, then the others in order; each label takes
    the first of four places around its point where it overlaps no earlier label, or is left
    out. Returns the placed matplotlib Text objects (a label left out has none)."""
    fig = ax.figure
    fig.canvas.draw()  # the limits and layout the labels are placed in
    renderer = fig.canvas.get_renderer()
    first = [int(i) for i in first]
    done = set(first)
    order = first + [i for i in range(len(labels)) if i not in done]
    placed, boxes = [], []
    for i in order:
        for dx, dy, ha, va in _PLACES:
            t = ax.annotate(str(labels[i]), tuple(points[i]), fontsize=fontsize, xytext=(dx, dy),
                            textcoords="offset points", ha=ha, va=va)
            box = t.get_window_extent(renderer)
            if not any(box.overlaps(b) for b in boxes):
                placed.append(t)
                boxes.append(box)
                break
            t.remove()
    return placed


def scatter_pareto(points: dict, path, xlabel: str, ylabel: str, title: str | None = None,
                   annotate: bool = True, groups: dict | None = None) -> Path:
    """``points``: label -> (x, y), both minimised; the non-dominated points are joined by the
    front line and ringed. ``groups`` (label -> group name) colours points by group. Labels
    that would overprint are left out, the front's kept first (``place_labels``)."""
    plt = _plt()
    labels = list(points)
    P = np.array([points[k] for k in labels], dtype=np.float64).reshape(-1, 2)
    front = pareto_front(P) if len(P) else np.zeros(0, int)
    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=120)
    if groups:
        names = sorted(set(groups.values()))
        cmap = plt.get_cmap("tab10")
        for gi, g in enumerate(names):
            idx = [i for i, k in enumerate(labels) if groups.get(k) == g]
            ax.scatter(P[idx, 0], P[idx, 1], color=cmap(gi % 10), label=g, zorder=3)
        ax.legend(fontsize=8)
    else:
        ax.scatter(P[:, 0], P[:, 1], color="#3b6ea8", zorder=3)
    if len(front):
        ax.plot(P[front, 0], P[front, 1], "--", color="#c0392b", zorder=2, label="Pareto front")
        ax.scatter(P[front, 0], P[front, 1], s=120, facecolors="none", edgecolors="#c0392b", zorder=4)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    if annotate and len(P):
        place_labels(ax, P, labels, first=front)
    return _finish(fig, ax, path, xlabel, ylabel, title)


def line_plot(series: dict, path, xlabel: str, ylabel: str, title: str | None = None, logy: bool = False,
              logx: bool = False) -> Path:
    """``series``: name -> (x values, y values); ``logx`` is ignored when an x value is <= 0."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    for name, (x, y) in series.items():
        ax.plot(x, y, marker="o", ms=3, label=name)
    if logy:
        ax.set_yscale("log")
    if logx and all(v > 0 for x, _ in series.values() for v in x):
        ax.set_xscale("log")
    ax.legend(fontsize=8)
    return _finish(fig, ax, path, xlabel, ylabel, title)
