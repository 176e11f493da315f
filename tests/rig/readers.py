"""Readers for the tests that share no code with the writers: a GLB parsed with struct, json and
numpy alone (not pygltflib), a USD stage through pxr's UsdSkel API."""
from __future__ import annotations

import json
import struct

import numpy as np

TYPES = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}
DTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8}


def read_glb(path) -> tuple[dict, bytes]:
    """(JSON, BIN chunk) of a .glb file, checked against the GLB 2.0 container layout."""
    data = open(path, "rb").read()
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert magic == b"glTF" and version == 2 and length == len(data)
    n, kind = struct.unpack_from("<I4s", data, 12)
    assert kind == b"JSON"
    doc = json.loads(data[20:20 + n])
    m, kind = struct.unpack_from("<I4s", data, 20 + n)
    assert kind == b"BIN\x00"
    return doc, data[28 + n:28 + n + m]


def accessor(doc, blob, i) -> np.ndarray:
    """Accessor i as an array (tightly packed views, as the writer makes them)."""
    a = doc["accessors"][i]
    v = doc["bufferViews"][a["bufferView"]]
    k = TYPES[a["type"]]
    arr = np.frombuffer(blob, DTYPES[a["componentType"]], a["count"] * k, v.get("byteOffset", 0) + a.get("byteOffset", 0))
    return arr.reshape(a["count"], k) if k > 1 else arr


def glb_shapes(path):
    """{"neutral": (n, 3), name: (n, 3) ...} in the mesh's own units (the node's translation and
    scale undone into them), per OBJ vertex (glTF vertices mapped back through _VERTEX_INDEX),
    the (t, 3) triangles in OBJ vertices, the per-glTF-vertex UVs and vertex indices, the doc."""
    doc, blob = read_glb(path)
    node = doc["nodes"][doc["scenes"][doc["scene"]]["nodes"][0]]
    s = node.get("scale", [1.0, 1.0, 1.0])[0]
    t = np.asarray(node.get("translation", [0.0, 0.0, 0.0])) / s
    prim = doc["meshes"][node["mesh"]]["primitives"][0]
    vi = accessor(doc, blob, prim["attributes"]["_VERTEX_INDEX"]).astype(np.int64)
    n = int(vi.max()) + 1
    base = accessor(doc, blob, prim["attributes"]["POSITION"]).astype(np.float64)
    out = {}

    def per_vertex(P):
        V = np.full((n, 3), np.nan)
        V[vi] = P + t
        return V

    out["neutral"] = per_vertex(base)
    names = doc["meshes"][node["mesh"]]["extras"]["targetNames"]
    for name, tgt in zip(names, prim.get("targets", [])):
        out[name] = per_vertex(base + accessor(doc, blob, tgt["POSITION"]).astype(np.float64))
    tris = vi[accessor(doc, blob, prim["indices"]).astype(np.int64)].reshape(-1, 3)
    uv = accessor(doc, blob, prim["attributes"]["TEXCOORD_0"]) if "TEXCOORD_0" in prim["attributes"] else None
    return out, tris, uv, vi, doc


def usd_shapes(path):
    """{"neutral": (n, 3), name: (n, 3)}: the mesh's points (plus its translation) and each
    BlendShape's offsets at its point indices, through pxr; the mesh and stage too."""
    from pxr import Usd, UsdGeom, UsdSkel

    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    assert root.IsA(UsdSkel.Root)
    mesh = next(UsdGeom.Mesh(p) for p in Usd.PrimRange(root) if p.IsA(UsdGeom.Mesh))
    X = mesh.ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    P = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64) + np.asarray(X.ExtractTranslation())
    binding = UsdSkel.BindingAPI(mesh.GetPrim())
    out = {"neutral": P}
    for name, path_ in zip(binding.GetBlendShapesAttr().Get(), binding.GetBlendShapeTargetsRel().GetTargets()):
        bs = UsdSkel.BlendShape(stage.GetPrimAtPath(path_))
        Q = P.copy()
        idx = np.asarray(bs.GetPointIndicesAttr().Get(), dtype=np.int64)
        Q[idx] += np.asarray(bs.GetOffsetsAttr().Get(), dtype=np.float64)
        out[str(name)] = Q
    return out, mesh, stage
