"""Headless renders of meshes with smooth shading and optional per-vertex colour maps.

pyvista (VTK) off-screen: on a machine with no display VTK uses EGL or OSMesa from Mesa's
software driver (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` is set unless the user chose
another window class). Cameras: a head looks along +z with y up; ``front`` looks at it from +z,
``three-quarter`` from 40 degrees to its left. One plotter draws a whole grid, so a grid of
many meshes costs one render.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

VIEWS = {"front": 0.0, "three-quarter": 40.0}


def _faces(template) -> np.ndarray:
    F = np.asarray(template.triangles)
    return np.hstack([np.full((len(F), 1), 3), F]).ravel()


def _place_camera(plotter, V, view: str):
    import pyvista as pv  # noqa: F401

    c = (V.max(0) + V.min(0)) / 2
    r = np.linalg.norm(V.max(0) - V.min(0))
    az = np.deg2rad(VIEWS.get(view, 0.0))
    pos = c + np.array([np.sin(az), 0.0, np.cos(az)]) * 2.2 * r
    plotter.camera_position = [tuple(pos), tuple(c), (0, 1, 0)]
    plotter.camera.view_angle = 30.0


def render_grid(cells: list[list[dict]], template, path, view: str | list[str] = "front", cell_size=(300, 340),
                cmap: str = "viridis", titles: bool = True) -> Path:
    """Render a grid: ``cells[row][col]`` is a dict with ``V`` (n, 3) and optionally
    ``scalars`` (n,), ``clim`` (lo, hi), ``label``, ``bar`` (colour-bar title), ``cmap``.

    Ground truth goes first in each row by convention; colour limits should be shared per
    metric by the caller so that colours compare across methods.
    """
    import pyvista as pv

    rows, cols = len(cells), max(len(r) for r in cells)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    faces = _faces(template)
    pl = pv.Plotter(off_screen=True, shape=(rows, cols), window_size=(cell_size[0] * cols, cell_size[1] * rows),
                    border=False)
    pl.set_background("white")
    for i, row in enumerate(cells):
        for j, cell in enumerate(row):
            pl.subplot(i, j)
            V = np.asarray(cell["V"], dtype=np.float64)
            mesh = pv.PolyData(V, faces)
            s = cell.get("scalars")
            if s is None:
                pl.add_mesh(mesh, color=cell.get("color", "#d9c7b8"), smooth_shading=True, specular=0.2)
            else:
                mesh.point_data["value"] = np.asarray(s, dtype=np.float64)
                bar = cell.get("bar", "")
                pl.add_mesh(mesh, scalars="value", cmap=cell.get("cmap", cmap), clim=cell.get("clim"),
                            smooth_shading=True, show_scalar_bar=False)
                if cell.get("show_bar", True):
                    pl.add_scalar_bar(title=bar or " ", n_labels=3, vertical=False, width=0.7, height=0.06,
                                      position_x=0.15, position_y=0.03, color="black", title_font_size=11,
                                      label_font_size=10, fmt="%.3g")
            if titles and cell.get("label"):
                pl.add_text(str(cell["label"]), font_size=9, color="black", position="upper_edge")
            v = cell.get("view", view if isinstance(view, str) else view[j % len(view)])
            _place_camera(pl, V, v)
    pl.screenshot(str(path))
    pl.close()
    return path


def render_mesh(V, template, path, view: str = "front", scalars=None, clim=None, cmap: str = "viridis",
                colorbar_title: str | None = None, size=(400, 460)) -> Path:
    """One mesh, one view, optional per-vertex colour map with a colour bar."""
    cell = {"V": V, "scalars": scalars, "clim": clim, "cmap": cmap, "bar": colorbar_title or "", "view": view}
    return render_grid([[cell]], template, path, view=view, cell_size=size, titles=False)
