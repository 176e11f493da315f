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
``bar`` (colour-bar title), ``cmap``, ``color``, ``view``, ``show_bar``) or a tuple
``(V, scalars_or_None, label)``. Convention: ground truth first, methods side by side, one row
per mesh. Cells with scalars and the same ``bar`` title but no ``clim`` share colour limits
(0 to the 99th percentile of all their values), so colours compare across methods.
"""
from __future__ import annotations

import io
import os
import warnings
from pathlib import Path

import numpy as np

from ..cache import atomic_write_bytes
from ..errors import FwkError

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

VIEWS = {"front": 0.0, "three-quarter": 40.0, "side": 90.0}
SKIN = "#d9c7b8"
TITLE_BAND, BAR_BAND = 0.09, 0.16  # fractions of a cell's height kept free for its title and colour bar


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
            c["bar_title"] = (c.get("bar") or " ") + " " * (i * len(row) + j)


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
    """Render a grid of meshes into one PNG (one plotter, one screenshot); see the module doc.

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
    # one scale for every cell: the largest half-extent, with a margin for the bar and the title
    aspect = cell_size[0] / cell_size[1]
    scale = 0.0
    for row in cells:
        for c in row:
            c["centre"], hh, hw = _extent(c["V"], c["az"])
            scale = max(scale, hh, hw / aspect)
    scale *= 1.03
    if _backend() != "matplotlib":
        try:
            return _render_pyvista(cells, template, path, cell_size, cmap, titles, scale)
        except (ImportError, RuntimeError, OSError) as exc:  # no OpenGL context at all
            warnings.warn(f"pyvista could not render ({type(exc).__name__}: {exc}); drawing with matplotlib")
    return _render_matplotlib(cells, template, path, cell_size, cmap, titles, scale)


def _render_pyvista(cells, template, path, cell_size, cmap, titles, scale) -> Path:
    import pyvista as pv  # deferred: 0.25 s of import time that `fwk list` and runs without renders need not pay

    rows, cols = len(cells), max(len(r) for r in cells)
    faces = _faces(template)
    pl = pv.Plotter(off_screen=True, shape=(rows, cols), window_size=(cell_size[0] * cols, cell_size[1] * rows),
                    border=False)
    try:
        pl.set_background("white")
        has_bar = any(c.get("scalars") is not None and c.get("show_bar", True) for r in cells for c in r)
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
                    if cell.get("show_bar", True):
                        # two labels (the limits): a middle label would sit under the title
                        pl.add_scalar_bar(title=cell["bar_title"], n_labels=2, vertical=False, width=0.7,
                                          height=0.06, position_x=0.15, position_y=0.03, color="black",
                                          title_font_size=11, label_font_size=10, fmt="%.3g")
                if titles and cell.get("label"):
                    pl.add_text(str(cell["label"]), font_size=9, color="black", position="upper_edge")
                right, up, back = _frame(V, cell["az"])
                # keep the mesh inside the band left free by the title (top) and the bar (bottom)
                top = TITLE_BAND if titles and any(c.get("label") for c in row) else 0.03
                bottom = BAR_BAND if has_bar else 0.03
                ps = scale / (1.0 - top - bottom)
                c = cell["centre"] - (bottom - top) * ps * up
                pl.camera_position = [tuple(c + back * 10 * scale), tuple(c), tuple(up)]
                pl.enable_parallel_projection()
                pl.camera.parallel_scale = ps
                pl.camera.clipping_range = (1e-3 * scale, 30 * scale)
        img = pl.screenshot(None, return_img=True)
    finally:
        pl.close()
    return _write_png(img, path)


def _write_png(img, path) -> Path:
    """An (h, w, 3 or 4) uint8 image written as PNG atomically (never half a file)."""
    from matplotlib.image import imsave  # deferred: see _render_matplotlib

    buf = io.BytesIO()
    imsave(buf, np.ascontiguousarray(img), format="png")
    atomic_write_bytes(Path(path), buf.getvalue())
    return Path(path)


def _render_matplotlib(cells, template, path, cell_size, cmap_name, titles, scale) -> Path:
    """Fallback without OpenGL: painter's algorithm on per-face colours, Lambert-shaded."""
    import matplotlib  # deferred: matplotlib.pyplot costs ~0.5 s of import time (see plots._plt)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    from .plots import save_figure

    rows, cols = len(cells), max(len(r) for r in cells)
    dpi = 100
    fig = plt.figure(figsize=(cell_size[0] * cols / dpi, cell_size[1] * rows / dpi), dpi=dpi)
    F = np.asarray(template.triangles)
    light = np.array([0.3, 0.4, 1.0])
    light /= np.linalg.norm(light)
    for i, row in enumerate(cells):
        for j, cell in enumerate(row):
            ax = fig.add_subplot(rows, cols, i * cols + j + 1)
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
                if cell.get("show_bar", True):
                    sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cm)
                    cb = fig.colorbar(sm, ax=ax, orientation="horizontal", fraction=0.05, pad=0.02)
                    cb.ax.set_title(cell.get("bar") or "", fontsize=8)
            order = np.argsort(z[F].mean(1))
            order = order[visible[order]]
            pc = PolyCollection(tri[order], facecolors=np.clip(base[order] * shade[order, None], 0, 1),
                                edgecolors="none", antialiased=False)
            ax.add_collection(pc)
            ax.set_xlim(-scale * cell_size[0] / cell_size[1], scale * cell_size[0] / cell_size[1])
            ax.set_ylim(-scale, scale)
            ax.set_aspect("equal")
            if titles and cell.get("label"):
                ax.set_title(str(cell["label"]), fontsize=9)
    return save_figure(fig, path, dpi=dpi, facecolor="white")


def render_mesh(V, template, path, view: str | float = "front", scalars=None, clim=None, cmap: str = "viridis",
                colorbar_title: str | None = None, size=(400, 460)) -> Path:
    """One mesh, one view, optional per-vertex colour map with a colour bar."""
    cell = {"V": V, "scalars": scalars, "clim": clim, "cmap": cmap, "bar": colorbar_title or "", "view": view}
    return render_grid([[cell]], template, path, view=view, cell_size=size, titles=False)
