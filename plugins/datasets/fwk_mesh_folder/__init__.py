"""``mesh-folder``: a user's own registered meshes (FaceScape, FaceWarehouse, a studio's scans).

Files are found with a pattern holding ``{subject}`` and ``{shape}``, relative to ``root``,
e.g. FaceWarehouse ``Tester_{subject}/TrainingPose/pose_{shape}.obj`` or FaceScape
``{subject}/models_reg/{shape}.obj``. The first file (in sorted order) defines the template;
every other file must share its topology (vertex count and face list): the error names the
file and what differs. OBJ and PLY are read keeping vertex order; quads are fan-triangulated
the same way for every file and the original polygons and UVs are kept for writing back.
Shapes a subject lacks are marked missing (``present``); ``neutral`` names the shape that plays
the neutral (renamed to ``neutral``).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from fwk.data import MeshCollection
from fwk.data.io import check_topology, read_mesh
from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl


class MeshFolder:
    """Registered meshes from a folder, found by a {subject}/{shape} pattern."""

    name = "mesh-folder"

    def __init__(self, root: str, pattern: str = "{subject}/{shape}.obj", neutral: str = "neutral",
                 shapes: list[str] | None = None, units: str = "unit"):
        if "{subject}" not in pattern:
            raise RecipeError(f"dataset.pattern: must contain {{subject}}, got {pattern!r}")
        self.root, self.pattern, self.neutral, self.shapes, self.units = Path(root), pattern, neutral, shapes, units

    def _files(self) -> dict[tuple[str, str], Path]:
        if not self.root.is_dir():
            raise DataError(f"dataset.root: {self.root} is not a folder")
        glob = self.pattern.replace("{subject}", "*").replace("{shape}", "*")
        rx = re.escape(self.pattern).replace(r"\{subject\}", r"(?P<subject>[^/]+)")
        rx = rx.replace(r"\{shape\}", r"(?P<shape>[^/]+)")
        rx = re.compile("^" + rx + "$")
        found = {}
        for p in sorted(self.root.glob(glob)):
            m = rx.match(p.relative_to(self.root).as_posix())
            if not m:
                continue
            shape = m.groupdict().get("shape") or "neutral"
            if shape == self.neutral:
                shape = "neutral"
            if self.shapes and shape not in self.shapes and shape != "neutral":
                continue
            found[(m["subject"], shape)] = p
        if not found:
            raise DataError(f"dataset: no file under {self.root} matches {self.pattern!r}")
        return found

    def load(self, cache=None) -> MeshCollection:
        files = self._files()
        subjects = sorted({s for s, _ in files})
        shapes = sorted({e for _, e in files}, key=lambda e: (e != "neutral", e))
        if "neutral" not in shapes:
            raise DataError(f"dataset: no neutral shape ({self.neutral!r}) among {', '.join(shapes)} under {self.root}")
        first = files[next(iter(sorted(files, key=lambda k: str(files[k]))))]
        V0, template = read_mesh(first, self.units)
        template.units = self.units
        pos = np.full((len(subjects), len(shapes), template.n_vertices, 3), np.nan)
        present = np.zeros((len(subjects), len(shapes)), bool)
        for (s, e), p in files.items():
            V, t = read_mesh(p, self.units)
            check_topology(template, t, p.relative_to(self.root))
            if not np.all(np.isfinite(V)):
                raise DataError(f"{p.relative_to(self.root)}: vertex positions contain NaN or infinite values")
            i, j = subjects.index(s), shapes.index(e)
            pos[i, j], present[i, j] = V, True
        missing = [subjects[i] for i in np.flatnonzero(~present[:, 0])]
        if missing:
            raise DataError(f"dataset: subjects without a neutral: {', '.join(missing[:5])}")
        template.vertices = pos[0, 0].copy()
        return MeshCollection(template, subjects, shapes, pos, present, name=self.name)


@hookimpl
def fwk_register_datasets():
    return [MeshFolder]
