"""Scatter plots with the Pareto front (thesis figures 3.3, 4.9, 4.12, 5.8, 5.9) and line plots.

Point labels never overprint (``place_labels``): the front's points are labelled first, each
label tries eight directions at growing distances around its point (beyond the nearest, tied to
it by a thin line), clear of every point and inside the axes, and one that fits nowhere is left
out. Axes carry at most six ticks, in scientific notation where values are small. Figures are
written atomically (a reader never sees half a PNG).
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ..cache import atomic_write_bytes
from .core import pareto_front

#: where a point's label may go, in order of preference: (dx, dy) directions (scaled by the
#: distance, in points) with the alignment that keeps the text clear of its point
_PLACES = ((1, 0.7, "left", "bottom"), (1, -0.7, "left", "top"), (-1, 0.7, "right", "bottom"),
           (-1, -0.7, "right", "top"), (0, 1, "center", "bottom"), (0, -1, "center", "top"),
           (1.2, 0, "left", "center"), (-1.2, 0, "right", "center"))
#: the distances (points) tried; a label placed beyond the first is tied to its point by a thin line
_DISTANCES = (4, 11, 20, 32, 46)
#: font sizes (points) of the figures' text: labels of points, ticks, axis titles, titles
LABEL_PT, TICK_PT, AXIS_PT, TITLE_PT = 8, 9, 10, 10.5


def _plt():
    """matplotlib.pyplot on the Agg backend. Deferred: pyplot costs ~0.5 s of import time that
    `fwk list` and runs that draw nothing need not pay."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _finish(fig, ax, path, xlabel, ylabel, title):
    _ticks(ax)
    ax.set_xlabel(xlabel, fontsize=AXIS_PT)
    ax.set_ylabel(ylabel, fontsize=AXIS_PT)
    if title:
        ax.set_title(title, fontsize=TITLE_PT)
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


def _hits(box, rects: np.ndarray) -> bool:
    """Whether the display-space ``box`` (x0, y0, x1, y1) overlaps any of ``rects`` ((m, 4))."""
    if not len(rects):
        return False
    x0, y0, x1, y1 = box
    return bool(np.any((rects[:, 0] < x1) & (rects[:, 2] > x0) & (rects[:, 1] < y1) & (rects[:, 3] > y0)))


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
    px = fig.dpi / 72.0  # pixels per point
    for i in order:
        # the text's box at each alignment, measured once (a text's extent moves with its anchor);
        # the candidates are then arithmetic: a trial annotation with its leader line per place
        # cost most of the main job's figure time (the arrow's path clipped each time)
        probe = ax.text(*P[i], str(labels[i]), fontsize=fontsize)
        rel = {}
        for _, _, ha, va in _PLACES:
            if (ha, va) not in rel:
                probe.set_ha(ha)
                probe.set_va(va)
                b = Text.get_window_extent(probe, renderer)
                rel[ha, va] = (b.x0 - xy[i, 0], b.y0 - xy[i, 1], b.x1 - xy[i, 0], b.y1 - xy[i, 1])
        probe.remove()
        for d, (ux, uy, ha, va) in ((d, p) for d in _DISTANCES for p in _PLACES):
            far = d > _DISTANCES[0]
            ox, oy = xy[i, 0] + ux * d * px, xy[i, 1] + uy * d * px
            r = rel[ha, va]
            box = (ox + r[0], oy + r[1], ox + r[2], oy + r[3])  # the text alone
            # with its leader line (within the box spanned by the text and its point): no two labels' overlap
            whole = (min(box[0], xy[i, 0]), min(box[1], xy[i, 1]), max(box[2], xy[i, 0]), max(box[3], xy[i, 1])) \
                if far else box
            inside = box[0] >= frame.x0 and box[2] <= frame.x1 and box[1] >= frame.y0 and box[3] <= frame.y1
            if inside and not _hits(whole, boxes) and not _hits(box, blocked):
                t = ax.annotate(str(labels[i]), tuple(P[i]), fontsize=fontsize, xytext=(ux * d, uy * d),
                                textcoords="offset points", ha=ha, va=va,
                                arrowprops=dict(arrowstyle="-", lw=0.5, color="0.45", shrinkA=0, shrinkB=3)
                                if far else None)
                t.get_window_extent(renderer)  # lays the annotation out (its text's extent is then box)
                placed.append(t)
                boxes = np.vstack([boxes, [whole]])
                break
    return placed


def _ticks(ax) -> None:
    """At most six ticks per linear axis, in scientific notation (a ×10^n factor at the axis end)
    where the values are small or large; a log axis at 1, 2, 5 x 10^n (more within a decade) written plainly
    (0.05, 0.1, 0.2); ticks a caller fixed are kept. Tick labels never run into each other."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, MaxNLocator, NullFormatter, ScalarFormatter

    for axis in (ax.xaxis, ax.yaxis):
        if isinstance(axis.get_major_locator(), FixedLocator):  # ticks a caller placed (every swept value)
            continue
        if axis.get_scale() == "log":  # plain numbers at 1, 2, 5 x 10^n (1 x 10^n only over many decades)
            lo, hi = (ax.get_xlim() if axis is ax.xaxis else ax.get_ylim())
            decades = np.log10(max(hi, 1e-300) / max(lo, 1e-300)) if lo > 0 else 9
            subs = (1.0, 1.5, 2.0, 3.0, 5.0, 7.0) if decades <= 1.2 else ((1.0, 2.0, 5.0) if decades <= 2.5 else (1.0,))
            axis.set_major_locator(LogLocator(base=10, subs=subs))
            axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
            axis.set_minor_formatter(NullFormatter())
            continue
        if axis.get_scale() != "linear":
            continue
        axis.set_major_locator(MaxNLocator(nbins=6, min_n_ticks=3))
        fmt = ScalarFormatter(useMathText=True)
        fmt.set_powerlimits((-2, 3))
        axis.set_major_formatter(fmt)
    ax.tick_params(labelsize=TICK_PT)


def scatter_pareto(points: dict, path, xlabel: str, ylabel: str, title: str | None = None,
                   annotate: bool = True, groups: dict | None = None, highlight: str | None = None,
                   highlight_label: str | None = None) -> Path:
    """``points``: label -> (x, y), both minimised; the non-dominated points are joined by the
    front line and ringed. ``groups`` (label -> group name) colours points by group. ``highlight``
    (a label: PBS's chosen k, say) is drawn as a star and named in the legend by
    ``highlight_label``. Labels that would overprint are left out, the front's and the
    highlighted point's kept first (``place_labels``). Axis titles should carry their units."""
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
    else:
        ax.scatter(P[:, 0], P[:, 1], color="#3b6ea8", zorder=3)
    if len(front):
        ax.plot(P[front, 0], P[front, 1], "--", color="#c0392b", zorder=2, label="Pareto front")
        ax.scatter(P[front, 0], P[front, 1], s=120, facecolors="none", edgecolors="#c0392b", zorder=4)
    hi = labels.index(highlight) if highlight is not None and highlight in labels else None
    if hi is not None:
        ax.scatter(P[hi:hi + 1, 0], P[hi:hi + 1, 1], s=260, marker="*", color="#f1c40f", edgecolors="black",
                   linewidths=0.8, zorder=5, label=highlight_label or str(highlight))
    _ticks(ax)
    ax.set_xlabel(xlabel, fontsize=AXIS_PT)
    ax.set_ylabel(ylabel, fontsize=AXIS_PT)
    if title:
        ax.set_title(title, fontsize=TITLE_PT)
    ax.grid(alpha=0.3)
    # room for labels at the edges: 6% of each range beyond the outermost points
    if len(P):
        for lim, col in ((ax.set_xlim, 0), (ax.set_ylim, 1)):
            lo, hi_ = float(P[:, col].min()), float(P[:, col].max())
            pad = 0.06 * (hi_ - lo) if hi_ > lo else max(abs(lo) * 0.05, 1e-12)
            lim(lo - pad, hi_ + pad)
    legend = ax.legend(fontsize=LABEL_PT + 0.5, loc="best") if (len(front) or groups or hi is not None) else None
    fig.tight_layout()
    if annotate and len(P):
        fig.canvas.draw()
        avoid = [legend.get_window_extent(fig.canvas.get_renderer())] if legend is not None else []
        radius = np.full(len(P), 5.0)
        radius[front] = 9.0
        if hi is not None:
            radius[hi] = 11.0
        first = ([hi] if hi is not None else []) + [int(i) for i in front if i != hi]
        place_labels(ax, P, labels, first=first, markers=radius, avoid=avoid,
                     lines=[P[front]] if len(front) > 1 else [])
    return save_figure(fig, path)


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
        xs = sorted({float(v) for x, _ in series.values() for v in x})
        if len(xs) <= 12:  # a tick at every swept value, written plainly (10, 40, 100), not 10^1, 10^2
            ax.set_xticks(xs, [f"{v:g}" for v in xs])
            ax.xaxis.set_minor_locator(_plt().NullLocator())
    ax.legend(fontsize=LABEL_PT + 0.5)
    return _finish(fig, ax, path, xlabel, ylabel, title)
