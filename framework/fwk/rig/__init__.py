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
from scipy import sparse

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
    """(n, 3) unit area-weighted vertex normals of V (n, 3), or (S, n, 3) of a stack V (S, n, 3):
    the sum of the incident triangles' cross products, normalised; a vertex with no area gets
    (0, 0, 1). The stack goes ``chunk`` shapes at a time, vertex-major (each triangle corner one
    contiguous row gather), the cross product written out by component: a 51-shape rig of
    ICT-FaceKit's full head took 6.1 s with np.cross on the whole stack in a fresh process (most of
    it touching ~0.5 GB of new temporaries), 0.9 s so. ``dtype``: the arithmetic's (float32 for a
    file that stores float32 normals)."""
    V = np.asarray(V, dtype=dtype)
    stack = V if V.ndim == 3 else V[None]
    S, n = stack.shape[:2]
    m = len(triangles)
    inc = sparse.csr_matrix((np.ones(3 * m, dtype=dtype), (triangles.T.reshape(-1), np.tile(np.arange(m), 3))),
                            shape=(n, m))
    out = np.empty((S, n, 3), dtype=dtype)
    t0, t1, t2 = (np.ascontiguousarray(triangles[:, k]) for k in range(3))
    for s0 in range(0, S, chunk):
        X = np.ascontiguousarray(stack[s0:s0 + chunk].transpose(1, 0, 2))  # (n, c, 3)
        c = X.shape[1]
        a = X[t0]
        e1, e2 = X[t1] - a, X[t2] - a  # (m, c, 3)
        fn = np.empty_like(e1)
        fn[..., 0] = e1[..., 1] * e2[..., 2] - e1[..., 2] * e2[..., 1]
        fn[..., 1] = e1[..., 2] * e2[..., 0] - e1[..., 0] * e2[..., 2]
        fn[..., 2] = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
        N = (inc @ fn.reshape(m, 3 * c)).reshape(n, c, 3)
        norm = np.sqrt(np.einsum("nck,nck->nc", N, N))[..., None]
        ok = norm[..., 0] > 0
        part = np.broadcast_to(np.array([0.0, 0.0, 1.0], dtype=dtype), N.shape).copy()
        part[ok] = N[ok] / norm[ok]
        out[s0:s0 + c] = part.transpose(1, 0, 2)
    return out if V.ndim == 3 else out[0]


