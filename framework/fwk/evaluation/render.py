"""Headless renders of meshes with smooth shading and optional per-vertex colour maps.

Backend: pyvista (VTK) off screen. On a machine with no display VTK draws with EGL or OSMesa
from Mesa's software driver (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` is set unless
the user chose another window class). If VTK cannot open any window at all, the same pictures
are drawn by matplotlib (``Poly3DCollection``: per-face colours with Lambert shading, slower
and flat-looking); ``FWK_RENDER_BACKEND=matplotlib`` forces that path. Measured here: about
0.3-0.5 s per 11k-vertex image once VTK is warm (the first image of a process pays about 3 s
of OpenGL start-up).

Cameras: a head looks along +z with y up. ``front`` looks at it from +z, ``three-quarter``
from 40 degrees to the head's left (its right cheek towards the viewer's left), ``side`` from
90 degrees; a number is an azimuth in degrees. The projection is parallel and every cell of a
grid uses the same scale, so sizes compare across cells.

Grids: ``cells[row][col]`` is a dict (``V``, and optionally ``scalars``, ``clim``, ``label``,
``bar`` (colour-bar title: the metric and its unit, ``DAME (rad)``), ``cmap``, ``color``,
``view``, ``show_bar``) or a tuple ``(V, scalars_or_None, label)``. Convention: ground truth
first, methods side by side, one row per mesh. Cells with scalars and the same ``bar`` title but
no ``clim`` share colour limits (``colour_limits``), so colours compare across methods.

Text: the meshes are rendered alone (``cell_size`` each); the cells' titles and the colour bars
are then drawn around them by matplotlib (``compose``), at a size readable where a report shows
the image: a viewer fits an image to about ``VIEW_WIDTH`` pixels, so text is
``TEXT_PX * max(1, width / VIEW_WIDTH)`` pixels high (at most ``MAX_TEXT_PX``), long titles
wrapped. One colour bar per (title, limits) group sits under the grid, its title naming the
metric and unit; an upper limit that clips the group's values is labelled ``≥ limit`` and the bar
ends in a triangle (likewise ``≤`` below).
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..errors import FwkError

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

VIEWS = {"front": 0.0, "three-quarter": 40.0, "side": 90.0}
SKIN = "#d9c7b8"
MARGIN = 0.03  # fraction of a cell's height left free above and below its mesh
VIEW_WIDTH = 900  # pixels: about the width a markdown viewer fits an image to
TEXT_PX = 13  # pixels: the smallest text height readable at that width
MAX_TEXT_PX = 36


def _azimuth(view) -> float:
    if isinstance(view, (int, float)):
        return float(view)
    if view not in VIEWS:
        raise FwkError(f"view {view!r}: expected one of {', '.join(VIEWS)} or an azimuth in degrees")
    return VIEWS[view]


def _faces(template) -> np.ndarray:
    F = np.asarray(template.triangles)
    return np.hstack([np.full((len(F), 1), 3), F]).ravel()


def _cells(cells) -> list[list[dict]]:
    out = []
    for row in cells:
        r = []
        for c in row:
            if isinstance(c, dict):
                r.append(dict(c))
            else:
                c = tuple(c)
                V, s, label = (c + (None, None))[:3]
                r.append({"V": V, "scalars": s, "label": label})
        out.append(r)
    return out


def _bars(cells: list[list[dict]]) -> None:
    """Where ``show_bar`` is not given: one colour bar per row and per (title, limits) group,
    under the group's last cell; titles made unique per row (pyvista keeps one bar per title)."""
    for i, row in enumerate(cells):
        last = {}
        for j, c in enumerate(row):
            if c.get("scalars") is not None and "show_bar" not in c:
                last[(c.get("bar", ""), tuple(c["clim"]) if c.get("clim") is not None else None)] = j
        for j, c in enumerate(row):
            if c.get("scalars") is not None and "show_bar" not in c:
                c["show_bar"] = j in last.values()


def colour_limits(maps) -> tuple[float, float]:
    """One colour range for several error maps: from min(0, smallest value) to the median over
    the maps of each map's 99th percentile. A far worse model then saturates instead of turning
    every other map black (seen on ICT-FaceKit: an undertrained VAE's DAME map is 12x the others',
    and the percentile of the pooled values left them unreadable)."""
    per = [np.asarray(v, dtype=np.float64).ravel() for v in maps]
    per = [v[np.isfinite(v)] for v in per]
    per = [v for v in per if v.size]
    if not per:
        return 0.0, 1.0
    lo = float(min(0.0, min(v.min() for v in per)))
    hi = float(np.median([np.percentile(v, 99) for v in per]))
    if not hi > lo:
        top = max(float(v.max()) for v in per)
        hi = top if top > lo else lo + 1e-12
    return lo, hi


def _shared_clims(cells: list[list[dict]]) -> None:
    """One colour range per bar title across the grid (``colour_limits``), where not given."""
    groups: dict = {}
    for row in cells:
        for c in row:
            if c.get("scalars") is not None and c.get("clim") is None:
                groups.setdefault(c.get("bar", ""), []).append(c)
    for group in groups.values():
        lim = colour_limits([c["scalars"] for c in group])
        for c in group:
            c["clim"] = lim


def _frame(V: np.ndarray, az_deg: float):
    """Camera basis for an azimuth: (right, up, towards-viewer) unit vectors."""
    az = np.deg2rad(az_deg)
    back = np.array([np.sin(az), 0.0, np.cos(az)])
    up = np.array([0.0, 1.0, 0.0])
    right = np.cross(up, back)
    return right, up, back


def _extent(V: np.ndarray, az_deg: float):
    """Centre (3,) and half height/width (in world units) of V seen from this azimuth."""
    right, up, _ = _frame(V, az_deg)
    c = (V.max(0) + V.min(0)) / 2
    x, y = (V - c) @ right, (V - c) @ up
    cx, cy = (x.max() + x.min()) / 2, (y.max() + y.min()) / 2
    return c + cx * right + cy * up, (y.max() - y.min()) / 2, (x.max() - x.min()) / 2


def _backend() -> str:
    return os.environ.get("FWK_RENDER_BACKEND", "pyvista").lower()


def render_grid(cells: list[list], template, path, view: str | float | list = "front", cell_size=(300, 340),
                cmap: str = "viridis", titles: bool = True) -> Path:
    """Render a grid of meshes into one PNG; see the module doc. ``cell_size`` is each mesh's
    (width, height) in pixels; the titles and colour bars add bands above the rows and under the
    grid.

    ``view`` is one view for every cell, or a list giving each column's view (cycled); a cell's
    own ``view`` wins.
    """
    cells = _cells(cells)
    _shared_clims(cells)
    _bars(cells)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for row in cells:
        for j, c in enumerate(row):
            v = c.get("view", view if isinstance(view, (str, int, float)) else view[j % len(view)])
            c["az"] = _azimuth(v)
            c["V"] = np.asarray(c["V"], dtype=np.float64)
    # one scale for every cell: the largest half-extent, with a margin
    aspect = cell_size[0] / cell_size[1]
    scale = 0.0
    for row in cells:
        for c in row:
            c["centre"], hh, hw = _extent(c["V"], c["az"])
            scale = max(scale, hh, hw / aspect)
    scale *= 1.03
    img = None
    if _backend() != "matplotlib":
        try:
            img = _render_pyvista(cells, template, cell_size, cmap, scale)
        except (ImportError, RuntimeError, OSError) as exc:  # no OpenGL context at all
            warnings.warn(f"pyvista could not render ({type(exc).__name__}: {exc}); drawing with matplotlib")
    if img is None:
        img = _render_matplotlib(cells, template, cell_size, cmap, scale)
    return compose(img, cells, cell_size, path, cmap, titles)


def text_px(width: int) -> float:
    """The text height (pixels) readable in an image ``width`` pixels wide once a viewer fits it
    to ``VIEW_WIDTH``."""
    return float(min(MAX_TEXT_PX, TEXT_PX * max(1.0, width / VIEW_WIDTH)))


def wrap_label(label: str, max_chars: int) -> list[str]:
    """A title in lines of at most ``max_chars`` characters where it can be: broken after a
    ``:`` first (``pbs:`` / ``pb-euclidean-std``), then at spaces and hyphens."""
    import textwrap

    max_chars = max(4, int(max_chars))
    out = []
    pieces = [p + ":" for p in label.split(":")[:-1]] + [label.split(":")[-1]] if len(label) > max_chars else [label]
    for piece in pieces:
        if out and len(out[-1]) + len(piece) <= max_chars:
            out[-1] += piece
        else:
            out += textwrap.wrap(piece, max_chars, break_on_hyphens=True, break_long_words=False) or [piece]
    return out


def bar_ticks(lo: float, hi: float, clipped_low: bool = False, clipped_high: bool = False,
              n: int = 4) -> tuple[list[float], list[str]]:
    """Colour-bar ticks: round values inside [lo, hi] and the two limits, a clipped limit labelled
    ``≥ hi`` (``≤ lo``); round ticks too close to a limit are dropped so that labels do not touch."""
    from matplotlib.ticker import MaxNLocator  # deferred with matplotlib (see _render_matplotlib)

    span = hi - lo if hi > lo else 1.0
    inner = [float(t) for t in MaxNLocator(nbins=n).tick_values(lo, hi)
             if lo + 0.18 * span < t < hi - 0.18 * span]
    ticks = [lo, *inner, hi]

    def fmt(x):
        return "0" if x == 0 else f"{x:.3g}"

    labels = [fmt(t) for t in ticks]
    if clipped_low:
        labels[0] = "≤ " + labels[0]
    if clipped_high:
        labels[-1] = "≥ " + labels[-1]
    return ticks, labels


def _groups(cells) -> list[dict]:
    """The colour bars to draw: one per (title, limits) of the cells showing a bar, with its
    colour map and whether the limits clip the group's values."""
    groups: dict = {}
    for row in cells:
        for c in row:
            if c.get("scalars") is None:
                continue
            key = (c.get("bar") or "", tuple(c["clim"]))
            g = groups.setdefault(key, {"title": key[0], "clim": key[1], "cmap": c.get("cmap"), "values": [],
                                        "shown": False})
            g["values"].append(np.asarray(c["scalars"], dtype=np.float64).ravel())
            g["shown"] = g["shown"] or bool(c.get("show_bar", True))
    out = []
    titles = [g["title"] for g in groups.values() if g["shown"]]
    for g in groups.values():
        if not g["shown"]:
            continue
        v = np.concatenate(g["values"])
        v = v[np.isfinite(v)]
        lo, hi = g["clim"]
        tol = 1e-9 * max(abs(lo), abs(hi), 1e-300)
        g["high"] = bool(v.size and v.max() > hi + tol)
        g["low"] = bool(v.size and v.min() < lo - tol)
        if titles.count(g["title"]) > 1:  # two ranges under one title: say which is which
            g["title"] += f" ({lo:.3g} to {hi:.3g})"
        out.append(g)
    return out


def compose(img: np.ndarray, cells, cell_size, path, cmap: str = "viridis", titles: bool = True) -> Path:
    """The rendered meshes ``img`` (rows x cols cells of ``cell_size``) with each cell's title
    above it and the colour bars under the grid, in text sized by ``text_px``; written to
    ``path`` as PNG."""
    import matplotlib  # deferred: see _render_matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .plots import save_figure

    cw, ch = cell_size
    rows, cols = len(cells), max(len(r) for r in cells)
    W = cw * cols
    F = text_px(W)
    line = 1.25 * F
    chars = cw / (0.56 * F)  # characters of a line that fit a cell (average glyph width ~0.56 em)
    labels = [[wrap_label(str(c["label"]), chars) if titles and c.get("label") else [] for c in row] for row in cells]
    bands = [max((len(x) for x in row), default=0) for row in labels]
    bands = [(n * line + 0.5 * F) if n else 0.0 for n in bands]
    bars = _groups(cells)
    bar_h = 0.9 * F
    bar_band = (line + bar_h + line + 0.8 * F) if bars else 0.0  # title, bar, tick labels, margin
    H = sum(bands) + rows * ch + bar_band
    dpi = 100
    pt = F * 72 / dpi
    fig = plt.figure(figsize=(W / dpi, H / dpi), dpi=dpi)
    fig.patch.set_facecolor("white")
    y = H  # from the top, in pixels
    for i, row in enumerate(cells):
        for j, text in enumerate(labels[i]):
            if text:
                fig.text((j + 0.5) * cw / W, (y - 0.25 * F) / H, "\n".join(text), ha="center", va="top",
                         fontsize=pt, linespacing=1.1)
        y -= bands[i]
        ax = fig.add_axes([0, (y - ch) / H, min(1.0, len(row) * cw / W), ch / H])
        ax.imshow(img[i * ch:(i + 1) * ch, :len(row) * cw], interpolation="nearest", aspect="auto")
        ax.set_axis_off()
        y -= ch
    if bars:
        slot = W / len(bars)
        for k, g in enumerate(bars):
            width = min(0.8 * slot, 0.5 * W if len(bars) == 1 else slot)
            x0 = k * slot + (slot - width) / 2
            cax = fig.add_axes([x0 / W, (bar_band - line - bar_h) / H, width / W, bar_h / H])
            lo, hi = g["clim"]
            extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get((g["low"], g["high"]),
                                                                                           "neither")
            sm = matplotlib.cm.ScalarMappable(norm=matplotlib.colors.Normalize(lo, hi),
                                              cmap=plt.get_cmap(g["cmap"] or cmap))
            cb = fig.colorbar(sm, cax=cax, orientation="horizontal", extend=extend, extendfrac=0.04)
            ticks, tick_labels = bar_ticks(lo, hi, g["low"], g["high"])
            cb.set_ticks(ticks)
            cb.set_ticklabels(tick_labels)
            cb.ax.tick_params(labelsize=pt * 0.9, length=0.3 * F)
            cb.ax.set_title(g["title"], fontsize=pt, pad=0.3 * F)
    return save_figure(fig, path, dpi=dpi, facecolor="white")


def _render_pyvista(cells, template, cell_size, cmap, scale) -> np.ndarray:
    """The meshes alone, each in its cell: an (rows * h, cols * w, 3) image."""
    import pyvista as pv  # deferred: 0.25 s of import time that `fwk list` and runs without renders need not pay

    rows, cols = len(cells), max(len(r) for r in cells)
    faces = _faces(template)
    pl = pv.Plotter(off_screen=True, shape=(rows, cols), window_size=(cell_size[0] * cols, cell_size[1] * rows),
                    border=False)
    try:
        pl.set_background("white")
        for i, row in enumerate(cells):
            for j, cell in enumerate(row):
                pl.subplot(i, j)
                V = cell["V"]
                mesh = pv.PolyData(V, faces)
                s = cell.get("scalars")
                if s is None:
                    pl.add_mesh(mesh, color=cell.get("color", SKIN), smooth_shading=True, specular=0.2)
                else:
                    mesh.point_data["value"] = np.asarray(s, dtype=np.float64)
                    pl.add_mesh(mesh, scalars="value", cmap=cell.get("cmap", cmap), clim=cell.get("clim"),
                                smooth_shading=True, show_scalar_bar=False)
                right, up, back = _frame(V, cell["az"])
                ps = scale / (1.0 - 2 * MARGIN)
                c = cell["centre"]
                pl.camera_position = [tuple(c + back * 10 * scale), tuple(c), tuple(up)]
                pl.enable_parallel_projection()
                pl.camera.parallel_scale = ps
                pl.camera.clipping_range = (1e-3 * scale, 30 * scale)
        img = pl.screenshot(None, return_img=True)
    finally:
        pl.close()
    return np.ascontiguousarray(img[..., :3])


def _render_matplotlib(cells, template, cell_size, cmap_name, scale) -> np.ndarray:
    """Fallback without OpenGL: painter's algorithm on per-face colours, Lambert-shaded; the
    meshes alone, as ``_render_pyvista``."""
    import matplotlib  # deferred: matplotlib.pyplot costs ~0.5 s of import time (see plots._plt)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    rows, cols = len(cells), max(len(r) for r in cells)
    dpi = 100
    fig = plt.figure(figsize=(cell_size[0] * cols / dpi, cell_size[1] * rows / dpi), dpi=dpi)
    fig.patch.set_facecolor("white")
    F = np.asarray(template.triangles)
    light = np.array([0.3, 0.4, 1.0])
    light /= np.linalg.norm(light)
    ps = scale / (1.0 - 2 * MARGIN)
    for i, row in enumerate(cells):
        for j, cell in enumerate(row):
            ax = fig.add_axes([j / cols, 1 - (i + 1) / rows, 1 / cols, 1 / rows])
            ax.set_axis_off()
            V = cell["V"]
            right, up, back = _frame(V, cell["az"])
            c = cell["centre"]
            x, y, z = (V - c) @ right, (V - c) @ up, (V - c) @ back
            tri = np.stack([x[F], y[F]], -1)
            n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
            cam_n = np.stack([n @ right, n @ up, n @ back], 1)
            visible = cam_n[:, 2] > 0
            shade = 0.25 + 0.75 * np.clip(cam_n @ light, 0, 1)
            s = cell.get("scalars")
            if s is None:
                base = np.tile(matplotlib.colors.to_rgb(cell.get("color", SKIN)), (len(F), 1))
            else:
                lo, hi = cell.get("clim") or (float(np.min(s)), float(np.max(s)))
                face_s = np.asarray(s, dtype=np.float64)[F].mean(1)
                norm = matplotlib.colors.Normalize(lo, hi)
                cm = plt.get_cmap(cell.get("cmap", cmap_name))
                base = cm(norm(face_s))[:, :3]
            order = np.argsort(z[F].mean(1))
            order = order[visible[order]]
            pc = PolyCollection(tri[order], facecolors=np.clip(base[order] * shade[order, None], 0, 1),
                                edgecolors="none", antialiased=False)
            ax.add_collection(pc)
            ax.set_xlim(-ps * cell_size[0] / cell_size[1], ps * cell_size[0] / cell_size[1])
            ax.set_ylim(-ps, ps)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img


def render_mesh(V, template, path, view: str | float = "front", scalars=None, clim=None, cmap: str = "viridis",
                colorbar_title: str | None = None, size=(400, 460)) -> Path:
    """One mesh, one view, optional per-vertex colour map with a colour bar."""
    cell = {"V": V, "scalars": scalars, "clim": clim, "cmap": cmap, "bar": colorbar_title or "", "view": view}
    return render_grid([[cell]], template, path, view=view, cell_size=size, titles=False)
