"""``mesh-folder``: a user's own registered meshes (FaceScape, FaceWarehouse, a studio's scans).

Files are found with a pattern holding ``{subject}`` and ``{shape}``, relative to ``root``,
e.g. FaceWarehouse ``Tester_{subject}/TrainingPose/pose_{shape}.obj`` or FaceScape
``{subject}/models_reg/{shape}.obj``. Every file must share one topology (vertex count and
face list): the template's is the one most files share (the first file's among equals), so a
broken file (cut short, say) is the one named, with what differs from the others; a line that
cannot be read is named by file and line number. ``units`` is one of ``fwk.data.UNITS``. OBJ and PLY are read keeping vertex order; quads are fan-triangulated
the same way for every file and the original polygons and UVs are kept for writing back.
Shapes a subject lacks are marked missing (``present``); ``neutral`` names the shape that plays
the neutral (renamed to ``neutral``).
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from fwk.data import MeshCollection, Units
from fwk.data.io import read_mesh
from fwk.errors import DataError, RecipeError, TopologyError
from fwk.hookspecs import hookimpl


class MeshFolder:
    """Registered meshes from a folder, found by a {subject}/{shape} pattern."""

    name = "mesh-folder"

    def __init__(self, root: str, pattern: str = "{subject}/{shape}.obj", neutral: str = "neutral",
                 shapes: list[str] | None = None, units: Units = "unit"):
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
        rel = {k: p.relative_to(self.root) for k, p in files.items()}
        order = sorted(files, key=lambda k: str(files[k]))
        read = {k: read_mesh(files[k], self.units) for k in order}  # a file that cannot be read is named
        # the template's topology: the one most files share (the first file's among equals)
        groups: dict[str, list] = {}
        for k in order:
            groups.setdefault(read[k][1].topology_hash(), []).append(k)
        ranked = sorted(groups.values(), key=len, reverse=True)
        if len(ranked) > 1 and len(ranked[0]) == len(ranked[1]):  # no majority: name both sides
            a, b = ranked[0][0], ranked[1][0]
            raise TopologyError(f"{rel[a]} and {rel[b]} differ ({_difference(read[a][1], read[b][1])}) and "
                                f"{len(ranked[0])} file{'s' if len(ranked[0]) > 1 else ''} side with each; "
                                f"one of them is wrong (cut short?): every mesh must share one topology")
        ref = ranked[0][0]
        template = read[ref][1]
        template.units = self.units
        pos = np.full((len(subjects), len(shapes), template.n_vertices, 3), np.nan)
        present = np.zeros((len(subjects), len(shapes)), bool)
        for k in order:
            V, t = read[k]
            if t.topology_hash() != template.topology_hash():
                n_other = len(ranked[0]) - 1
                side = f"{rel[ref]}" + (f" and {n_other} other files" if n_other > 1 else
                                        (" and 1 other file" if n_other == 1 else ""))
                raise TopologyError(f"{rel[k]}: {_difference(t, template)} as in {side}; every mesh must share "
                                    f"one topology (is {rel[k]} cut short?)")
            if not np.all(np.isfinite(V)):
                raise DataError(f"{rel[k]}: vertex positions contain NaN or infinite values")
            i, j = subjects.index(k[0]), shapes.index(k[1])
            pos[i, j], present[i, j] = V, True
        missing = [subjects[i] for i in np.flatnonzero(~present[:, 0])]
        if missing:
            raise DataError(f"dataset: subjects without a neutral: {', '.join(missing[:5])}")
        template.vertices = pos[0, 0].copy()
        return MeshCollection(template, subjects, shapes, pos, present, name=self.name)


def _difference(t, ref) -> str:
    """What differs between two topologies, in words: ``280 polygons, not 320``."""
    if t.n_vertices != ref.n_vertices:
        return f"{t.n_vertices} vertices, not {ref.n_vertices}"
    if t.n_polygons != ref.n_polygons:
        return f"{t.n_polygons} polygons, not {ref.n_polygons}"
    return "a different face list"


@hookimpl
def fwk_register_datasets():
    return [MeshFolder]
