"""USD rig writer (usd-core's ``pxr``): a UsdSkel rig with one BlendShape per expression.

Layout (the one Blender, Maya and Houdini import as shape keys / blend shapes)::

    /Rig                     SkelRoot (the default prim); stage up axis y, metersPerUnit from the units
      /Rig/Skel              Skeleton, one joint ``root`` (identity bind and rest transforms)
        /Rig/Skel/Anim       SkelAnimation: blendShapes = the names, blendShapeWeights all 0
      /Rig/<name>            Mesh: translated to the centre of the neutral's bounding box (xformOp:translate;
                             float32 points about it round half as much; the same translation is its
                             geomBindTransform, which UsdSkel uses instead), the neutral's points, polygons as in the OBJ (faceVertexCounts /
                             faceVertexIndices, subdivisionScheme none), UVs as the faceVarying
                             ``primvars:st`` with indices; SkelBindingAPI: skeleton, joint 0 at
                             weight 1, skel:blendShapes (the names as given) and
                             skel:blendShapeTargets
        /Rig/<name>/<name>   BlendShape: offsets and pointIndices of the vertices that move

Prim names (``prim_names``) are the mesh's and the shapes' names made valid identifiers, ASCII
letters, digits and ``_`` (``face-compression`` -> ``face_compression``, ``my head.v2`` ->
``my_head_v2``, ``3d`` -> ``_3d``) and unique: a name taken by the rig's own prims (the mesh beside
``Skel``: a neutral ``Skel.obj`` gives the mesh ``Skel_1``, which would otherwise redefine the
Skeleton and leave the rig without one) or by an earlier shape (``a.b`` and ``a b``: ``a_b`` and
``a_b_1``) gets the first free ``_1``, ``_2``, ...; ``skel:blendShapes`` keeps the names
themselves. ``.usda`` is text, ``.usdc`` binary (by the suffix). Offsets are float32, like every
point in USD.
"""
from __future__ import annotations

import re

import numpy as np

from ..data import Template
from . import METRES_PER_UNIT, missing

ROOT, SKELETON, ANIMATION = "Rig", "Skel", "Anim"  # the rig's own prims: /Rig, /Rig/Skel, /Rig/Skel/Anim


def identifier(name: str) -> str:
    """``name`` as a USD prim name: every character but ASCII letters, digits and ``_`` replaced
    by ``_``, and ``_`` before a leading digit (an empty name: ``_``)."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", str(name))
    return "_" + out if not out or out[0].isdigit() else out


def prim_names(names, taken=()) -> list[str]:
    """A distinct prim name (``identifier``) for each of ``names``, none of them in ``taken``
    (the names of the prims beside them): a name already used gets the first free ``_1``, ``_2``, ..."""
    used, out = set(taken), []
    for name in names:
        base = identifier(name)
        new, k = base, 0
        while new in used:
            k += 1
            new = f"{base}_{k}"
        used.add(new)
        out.append(new)
    return out


def write_usd(path, neutral: np.ndarray, template: Template, shapes: dict[str, np.ndarray],
              units: str = "unit", name: str = "head") -> None:
    """Write the rig to ``path`` (``.usda`` or ``.usdc``): ``neutral`` (n, 3) on ``template``'s
    polygons and UVs, one BlendShape per entry of ``shapes`` (name -> (n, 3) positions); the
    mesh prim is called ``name`` and each BlendShape by its shape (``prim_names``: valid
    identifiers that collide neither with the rig's own prims nor with each other)."""
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt  # deferred: optional extra `rig`, 140 ms
    except ImportError:  # pragma: no cover - depends on the environment
        raise missing("usd-core", "--format usd") from None
    base = np.asarray(neutral, dtype=np.float64)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, METRES_PER_UNIT.get(units, 1.0))
    root = UsdSkel.Root.Define(stage, f"/{ROOT}")
    stage.SetDefaultPrim(root.GetPrim())
    skel = UsdSkel.Skeleton.Define(stage, root.GetPath().AppendChild(SKELETON))
    skel.CreateJointsAttr(["root"])
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    names = list(shapes)
    anim = UsdSkel.Animation.Define(stage, skel.GetPath().AppendChild(ANIMATION))
    anim.CreateJointsAttr(["root"])
    anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(0, 0, 0)]))
    anim.CreateRotationsAttr(Vt.QuatfArray([Gf.Quatf(1, 0, 0, 0)]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
    anim.CreateBlendShapesAttr(names)
    anim.CreateBlendShapeWeightsAttr(Vt.FloatArray([0.0] * len(names)))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

    mesh = UsdGeom.Mesh.Define(stage, root.GetPath().AppendChild(prim_names([name or "head"], [SKELETON])[0]))
    centre = (base.min(0) + base.max(0)) / 2  # float32 points about the centre: half the rounding error
    mesh.AddTranslateOp().Set(Gf.Vec3d(*map(float, centre)))
    p32 = (base - centre).astype(np.float32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(p32))
    off = np.asarray(template.poly_offsets, dtype=np.int64)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.diff(off).astype(np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(template.poly_vertices, dtype=np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, p32.min(0))), Gf.Vec3f(*map(float, p32.max(0)))]))
    if template.uvs is not None and template.poly_uvs is not None and (np.asarray(template.poly_uvs) >= 0).all():
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(template.uvs, dtype=np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(template.poly_uvs, dtype=np.int32)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(True, 1).Set(Vt.FloatArray([1.0]))
    # a skinned prim's own transform is replaced by skinning: the bind transform places it the same
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*map(float, centre))))
    targets = []
    for prim_name, V in zip(prim_names(names), shapes.values()):  # the mesh's only child prims
        d = ((np.asarray(V, dtype=np.float64) - centre).astype(np.float32).astype(np.float64) - p32).astype(np.float32)
        moved = np.flatnonzero((d != 0).any(1)).astype(np.int32)
        bs = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(prim_name))
        bs.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(d[moved])))
        bs.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved))
        targets.append(bs.GetPath())
    binding.CreateBlendShapesAttr(names)
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)
    stage.GetRootLayer().Export(str(path))
