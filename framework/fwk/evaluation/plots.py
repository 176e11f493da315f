"""Scatter plots with the Pareto front (thesis figures 3.3, 4.9, 4.12, 5.8, 5.9) and line plots."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .core import pareto_front


def _plt():
    """matplotlib.pyplot on the Agg backend. Deferred: pyplot costs ~0.5 s of import time that
    `fwk list` and runs that draw nothing need not pay."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig, ax, path, xlabel, ylabel, title):
    plt = _plt()
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def scatter_pareto(points: dict, path, xlabel: str, ylabel: str, title: str | None = None,
                   annotate: bool = True, groups: dict | None = None) -> Path:
    """``points``: label -> (x, y), both minimised; the non-dominated points are joined by the
    front line and ringed. ``groups`` (label -> group name) colours points by group."""
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
    if annotate:
        for i, k in enumerate(labels):
            ax.annotate(str(k), P[i], fontsize=7, xytext=(3, 3), textcoords="offset points")
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
