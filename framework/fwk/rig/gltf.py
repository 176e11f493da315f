"""glTF 2.0 binary (``.glb``) rig writer (pygltflib): the neutral with its UVs and one morph
target per expression.

Layout (valid under the Khronos glTF validator, tested): one scene, one node (scaled to metres
when the units are known: glTF's unit is the metre, the positions stay in the neutral's units;
translated to the centre of the neutral's bounding box, the positions relative to it, which
halves float32's rounding error: they read back to within 1e-6 of the OBJ for a head in cm), one mesh with one triangle primitive (the polygons fan-triangulated
from their first corner, as fwk triangulates everywhere), attributes POSITION (min/max set),
NORMAL (area-weighted vertex normals), TEXCOORD_0 (OBJ ``vt`` with v flipped: glTF's origin is
the top left) and ``_VERTEX_INDEX`` (the OBJ vertex each glTF vertex comes from, as floats:
exact below 2^24), one target per expression with POSITION deltas (min/max set) and NORMAL
deltas, ``mesh.weights`` all 0, the names in ``mesh.extras.targetNames`` (where Blender and
three.js read them). glTF vertices are the distinct (vertex, uv) corners: a vertex on a UV seam
is split, its copies move together.
"""
from __future__ import annotations

import numpy as np

from ..data import Template
from ..data.io import fan_triangulate
from . import METRES_PER_UNIT, missing, vertex_normals

ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
FLOAT, UNSIGNED_SHORT, UNSIGNED_INT = 5126, 5123, 5125


def corners(template: Template):
    """(vertex of each glTF vertex, uv index of each or None, glTF vertex of each polygon corner):
    one glTF vertex per distinct (vertex, vt) pair of the polygons' corners; without UVs, the
    vertices themselves (every one, used or not)."""
    pv = np.asarray(template.poly_vertices, dtype=np.int64)
    if template.uvs is None or template.poly_uvs is None or len(template.uvs) == 0:
        return np.arange(template.n_vertices), None, pv
    pt = np.asarray(template.poly_uvs, dtype=np.int64)
    key = pv * (len(template.uvs) + 1) + (pt + 1)
    uniq, first, inv = np.unique(key, return_index=True, return_inverse=True)
    return pv[first], pt[first], inv.reshape(-1)


def write_glb(path, neutral: np.ndarray, template: Template, shapes: dict[str, np.ndarray], units: str = "unit",
              normals: bool = True, name: str = "head") -> bytes:
    """The .glb bytes of the rig (and written to ``path`` when it is not None): ``neutral`` (n, 3)
    on ``template``'s polygons and UVs, one morph target per entry of ``shapes`` (name -> (n, 3)
    positions on the same topology, same units); mesh and node are called ``name``."""
    try:
        import pygltflib as g  # deferred: optional extra `rig`, 70 ms of import time
    except ImportError:  # pragma: no cover - depends on the environment
        raise missing("pygltflib", "--format gltf") from None
    vert, uv, corner = corners(template)
    tris = fan_triangulate(corner, np.asarray(template.poly_offsets, dtype=np.int64))
    base = np.asarray(neutral, dtype=np.float64)
    centre = (base.min(0) + base.max(0)) / 2  # float32 positions about the centre: half the rounding error
    blob = bytearray()
    views, accessors = [], []

    def add(arr, kind, target=None, minmax=False):
        arr = np.ascontiguousarray(arr)
        while len(blob) % 4:
            blob.append(0)
        views.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=arr.nbytes, target=target))
        blob.extend(arr.tobytes())
        comp = {np.dtype(np.float32): FLOAT, np.dtype(np.uint16): UNSIGNED_SHORT,
                np.dtype(np.uint32): UNSIGNED_INT}[arr.dtype]
        acc = g.Accessor(bufferView=len(views) - 1, componentType=comp, count=len(arr), type=kind)
        if minmax:  # the float32 values themselves: the validator compares them exactly
            acc.min = [float(x) for x in arr.min(0)]
            acc.max = [float(x) for x in arr.max(0)]
        accessors.append(acc)
        return len(accessors) - 1

    p32 = (base - centre)[vert].astype(np.float32)
    attrs = g.Attributes(POSITION=add(p32, g.VEC3, ARRAY_BUFFER, True))
    # normals of the centred positions, in float32 as stored (a head far from the origin keeps its precision)
    n0 = vertex_normals(base - centre, template.triangles, dtype=np.float32) if normals else None
    if normals:
        attrs.NORMAL = add(n0[vert].astype(np.float32), g.VEC3, ARRAY_BUFFER)
    if uv is not None:
        st = np.asarray(template.uvs, dtype=np.float64)[np.maximum(uv, 0)]
        st[uv < 0] = 0.0
        st[:, 1] = 1.0 - st[:, 1]
        attrs.TEXCOORD_0 = add(st.astype(np.float32), g.VEC2, ARRAY_BUFFER)
    attrs._VERTEX_INDEX = add(vert.astype(np.float32), g.SCALAR, ARRAY_BUFFER)
    targets = []
    shape_normals = vertex_normals(np.stack([np.asarray(V, dtype=np.float64) - centre for V in shapes.values()]),
                                   template.triangles, dtype=np.float32) if normals and shapes else None
    for i, V in enumerate(shapes.values()):
        V = np.asarray(V, dtype=np.float64)
        # the delta of the float32 positions: base + delta reads back as V to float32 precision
        d = ((V - centre)[vert].astype(np.float32).astype(np.float64) - p32.astype(np.float64)).astype(np.float32)
        t = {"POSITION": add(d, g.VEC3, ARRAY_BUFFER, True)}
        if normals:
            t["NORMAL"] = add((shape_normals[i] - n0)[vert].astype(np.float32), g.VEC3, ARRAY_BUFFER)
        targets.append(t)
    idx = tris.reshape(-1).astype(np.uint16 if len(vert) < 65535 else np.uint32)
    indices = add(idx, g.SCALAR, ELEMENT_ARRAY_BUFFER)
    names = list(shapes)
    prim = g.Primitive(attributes=attrs, indices=indices, material=0, mode=4, targets=targets or None)
    mesh = g.Mesh(name=name, primitives=[prim], weights=[0.0] * len(names) or None,
                  extras={"targetNames": names} if names else {})
    mpu = METRES_PER_UNIT.get(units)
    s = mpu or 1.0
    node = g.Node(mesh=0, name=name, scale=[s] * 3 if s != 1.0 else None,
                  translation=[float(x) * s for x in centre] if centre.any() else None)
    material = g.Material(name="skin", pbrMetallicRoughness=g.PbrMetallicRoughness(
        baseColorFactor=[0.8, 0.66, 0.58, 1.0], metallicFactor=0.0, roughnessFactor=0.7))
    gltf = g.GLTF2(asset=g.Asset(generator="fwk apply", version="2.0"), scene=0, scenes=[g.Scene(nodes=[0])],
                   nodes=[node], meshes=[mesh], materials=[material], accessors=accessors, bufferViews=views,
                   buffers=[g.Buffer(byteLength=len(blob))],
                   extras={"fwk": {"units": units, "metres_per_unit": mpu or 1.0}})
    gltf.set_binary_blob(bytes(blob))
    data = b"".join(gltf.save_to_bytes())
    if path is not None:
        with open(path, "wb") as f:
            f.write(data)
    return data
