"""USD prim names never collide with the rig's own prims nor with each other, whatever the
neutral's file name or the shape names (issue 29 item 4: a neutral named ``Skel.obj`` replaced
the Skeleton prim and the rig stopped deforming). The check is UsdSkel's own pipeline through
pxr: the skeleton binding resolves to the Skeleton, the animation drives one BlendShape per
shape, and the blend shapes plus skinning, at random weights set on the animation, give the
neutral plus the weighted deltas."""
from __future__ import annotations

import numpy as np
import pytest

from .conftest import grid_obj, neutral

pytest.importorskip("pxr", reason="the rig extra: pip install 'fwk[rig]'")

#: names that collide with the rig's own prims (/Rig, /Rig/Skel, /Rig/Skel/Anim) or with USD's
#: schema and property names, are no identifiers, or sanitise to the same identifier
HOSTILE = ["Skel", "SkelRoot", "Rig", "Anim", "Mesh", "BlendShape", "points", "primvars", "skel", "Skel_1",
           "a b", "a.b", "a-b", "a_b", "3d", "3d scan.v2", "Zoë", "über", "", "_"]


def deformed(path, weights: dict[str, float]) -> tuple[np.ndarray, list[str]]:
    """The rig at ``path`` posed by UsdSkel: ``weights`` (shape name -> weight; others 0) set on
    the skeleton's animation, its blend shape weights mapped to the mesh's blend shapes, the
    BlendShapes applied to the mesh's points and the skinning (the bound skeleton's transforms,
    the mesh's geomBindTransform) after them; (n, 3) in the rig's space, and the shape names.
    Asserts on the way that every link of the binding resolves."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.Open(str(path))
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert root, "the default prim is no SkelRoot"
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.PrimDefaultPredicate)
    meshes = [p for p in Usd.PrimRange(root.GetPrim()) if p.IsA(UsdGeom.Mesh)]
    assert len(meshes) == 1
    mesh = meshes[0]
    skinning = cache.GetSkinningQuery(mesh)
    assert skinning and skinning.HasBlendShapes()
    binding = UsdSkel.BindingAPI(mesh)
    skel = binding.GetInheritedSkeleton()
    assert skel and skel.GetPrim().IsA(UsdSkel.Skeleton) and list(skel.GetJointsAttr().Get()) == ["root"]
    skel_query = cache.GetSkelQuery(skel)
    anim_query = skel_query.GetAnimQuery()
    assert anim_query and anim_query.GetPrim().IsA(UsdSkel.Animation)
    names = [str(n) for n in binding.GetBlendShapesAttr().Get()]
    targets = binding.GetBlendShapeTargetsRel().GetTargets()
    assert len(targets) == len(names) == len(set(targets))
    assert all(stage.GetPrimAtPath(t).IsA(UsdSkel.BlendShape) for t in targets)
    assert [str(n) for n in anim_query.GetBlendShapeOrder()] == names
    anim = UsdSkel.Animation(anim_query.GetPrim())
    anim.GetBlendShapeWeightsAttr().Set(Vt.FloatArray([float(weights.get(n, 0.0)) for n in names]))
    w = skinning.GetBlendShapeMapper().Remap(anim_query.ComputeBlendShapeWeights(Usd.TimeCode.Default()))
    shapes = UsdSkel.BlendShapeQuery(binding)
    assert shapes.GetNumBlendShapes() == len(names)
    sub_w, bs_idx, sub_idx = shapes.ComputeSubShapeWeights(w)
    points = UsdGeom.Mesh(mesh).GetPointsAttr().Get()
    assert shapes.ComputeDeformedPoints(sub_w, bs_idx, sub_idx, shapes.ComputeBlendShapePointIndices(),
                                        shapes.ComputeSubShapePointOffsets(), points)
    xforms = skel_query.ComputeSkinningTransforms(Usd.TimeCode.Default())
    assert skinning.ComputeSkinnedPoints(xforms, points, Usd.TimeCode.Default())
    return np.asarray(points, dtype=np.float64), names


def _grid(tmp_path, seed=0):
    from fwk.data.io import read_obj

    p = tmp_path / "g.obj"
    p.write_text(grid_obj(neutral(np.random.default_rng(seed))))
    return read_obj(p)


def test_identifiers_are_valid_and_unique():
    from pxr import Sdf

    from fwk.rig.usd import ANIMATION, SKELETON, identifier, prim_names

    assert identifier("face-compression") == "face_compression" and identifier("my head.v2") == "my_head_v2"
    assert identifier("3d") == "_3d" and identifier("") == "_" and identifier("Zoë") == "Zo_"
    names = prim_names(HOSTILE, taken=[SKELETON, ANIMATION])
    assert len(set(names)) == len(names) == len(HOSTILE)
    assert SKELETON not in names and ANIMATION not in names
    assert all(Sdf.Path.IsValidIdentifier(n) for n in names)
    # two names that sanitise alike, and a third that is the second's suffixed form
    assert prim_names(["a.b", "a b", "a_b_1"]) == ["a_b", "a_b_1", "a_b_1_1"]
    assert prim_names(["Skel"], taken=["Skel"]) == ["Skel_1"]


@pytest.mark.parametrize("mesh_name", ["Skel", "SkelRoot", "Rig", "Anim", "Mesh", "my head.v2", "3d scan", ""])
def test_hostile_names_still_deform(tmp_path, mesh_name):
    """A mesh named as the rig's own prims or as no identifier, with shapes named likewise (two
    of them sanitising alike): the rig deforms as the shapes say, under UsdSkel's evaluation."""
    from pxr import Usd, UsdSkel

    from fwk.rig.usd import write_usd

    V, tpl = _grid(tmp_path)
    rng = np.random.default_rng(1)
    shapes = {n: V + 0.3 * rng.standard_normal(V.shape) for n in HOSTILE}
    for suffix in (".usda", ".usdc"):
        path = tmp_path / f"rig{suffix}"
        write_usd(path, V, tpl, shapes, units="cm", name=mesh_name)
        w = dict(zip(HOSTILE, rng.uniform(0.1, 1.0, len(HOSTILE))))
        P, names = deformed(path, w)
        assert names == HOSTILE  # skel:blendShapes keeps the names themselves
        want = V + sum(w[n] * (shapes[n] - V) for n in HOSTILE)
        assert np.abs(P - want).max() < 1e-5
        stage = Usd.Stage.Open(str(path))
        assert stage.GetPrimAtPath("/Rig/Skel").IsA(UsdSkel.Skeleton)
        assert stage.GetPrimAtPath("/Rig/Skel/Anim").IsA(UsdSkel.Animation)
        # at zero weights: the neutral itself
        P0, _ = deformed(path, {})
        assert np.abs(P0 - V).max() < 1e-5


@pytest.mark.parametrize("stem", ["Skel", "SkelRoot", "Rig", "Anim", "my head.v2", "3d scan"])
def test_apply_with_a_neutral_named_like_the_rigs_prims(grid_run, tmp_path, stem):
    """End to end: ``fwk apply RUN Skel.obj --format obj,usd --naming arkit`` writes a rig that
    deforms into each OBJ at weight 1, and into their blend at other weights."""
    from fwk.apply import apply
    from fwk.data.io import read_obj

    V = neutral(np.random.default_rng(3))
    src = tmp_path / f"{stem}.obj"
    src.write_text(grid_obj(V))
    out = tmp_path / "out"
    files = apply(grid_run, src, out, formats="obj,usd", naming="arkit", log=lambda *_: None)
    usd = out / f"{stem}.usdc"
    assert usd in files
    objs = {p.stem: read_obj(p)[0] for p in out.glob("*.obj")}
    N = read_obj(src)[0]
    for name, X in objs.items():
        P, names = deformed(usd, {name: 1.0})
        assert sorted(names) == sorted(objs)
        assert np.abs(P - X).max() < 1e-5, name
    w = {n: 0.5 for n in objs}
    P, _ = deformed(usd, w)
    assert np.abs(P - (N + sum(0.5 * (X - N) for X in objs.values()))).max() < 1e-5
    # and fwk view reads it as the same rig
    from fwk.view import load_rig

    rig = load_rig(usd)
    assert sorted(rig.names) == sorted(objs) and np.abs(rig.neutral - N).max() < 1e-5
    for i, name in enumerate(rig.names):
        assert np.abs(rig.neutral + rig.deltas[i] - objs[name]).max() < 1e-5
