"""Rig files: a neutral head and its blendshapes in the formats DCC tools and engines open.

``fwk apply RUN NEUTRAL.obj --out DIR --format obj,gltf,usd [--naming arkit]`` predicts every
expression of a blendshapes run for a neutral and hands the neutral and the expressions (each a
full set of positions on the neutral's topology, in its units) to these writers:

* ``gltf.write_glb``: glTF 2.0 binary (pygltflib): the neutral as the base mesh with its UVs and
  normals, one morph target per expression (POSITION and NORMAL deltas), names in
  ``mesh.extras.targetNames``; the vertices split at UV seams as glTF needs, the original vertex
  of each in the ``_VERTEX_INDEX`` attribute; positions in the neutral's units, the node scaled
  to metres (glTF's unit).
* ``usd.write_usd``: a UsdSkel rig (usd-core): SkelRoot > Skeleton (one root joint, an
  Animation with a weight per shape) and Mesh (polygons as in the OBJ, UVs as the ``st``
  primvar) with one BlendShape per expression (sparse offsets), the stage's metersPerUnit set.
* ``arkit``: ICT-FaceKit's blendshape names to Apple ARKit's 52 (the table is in
  docs/rig-quickstart.md).

pygltflib, usd-core and open3d (``fwk view``) are the optional extra ``rig``
(``pip install 'fwk[rig]'``): each writer imports its library when it runs, and says how to
install it when it is missing.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..data.template import METRES_PER_UNIT  # noqa: F401 (the writers' scale, re-exported)
from ..errors import FwkError, cut


def read_json_file(path, where: str, error: type[FwkError] = FwkError):
    """A user's JSON file (a landmark file), parsed; one line ``where: ...`` as ``error`` when it
    is missing, unreadable or not UTF-8 JSON (the reader of ``fwk apply --landmarks`` and of
    ``fwk view --pick --template-landmarks``)."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise error(f"{where}: no such file") from None
    except OSError as exc:
        raise error(f"{where}: cannot be read ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise error(f"{where}: not JSON ({cut(str(exc))})") from None


def missing(package: str, what: str, extra: str = "rig", spec: str | None = None, note: str = "") -> FwkError:
    """The one-line error for a missing optional dependency of the extra ``extra`` (``spec``: the pip
    requirement, default ``package``; ``note``: said after the package, e.g. which Pythons it has)."""
    how = "pip install 'fwk[rig]'" if extra == "rig" else f"pip install -e '.[{extra}]'"
    return FwkError(f"{what} needs the Python package {package}{note}: {how} (or pip install {spec or package})")


def vertex_normals(V: np.ndarray, triangles: np.ndarray, chunk: int = 8, dtype=np.float64) -> np.ndarray:
    """``fwk.geometry.vertex_normals`` (unit area-weighted vertex normals of V (n, 3) or of a
    stack (S, n, 3), ``chunk`` shapes at a time, in ``dtype``) with (0, 0, 1) for a vertex with no
    area: what the rig files store."""
    from ..geometry import vertex_normals as normals  # deferred: fwk.geometry loads scipy's solvers

    return normals(V, triangles, chunk=chunk, dtype=dtype, fallback=(0.0, 0.0, 1.0))


