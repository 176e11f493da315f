"""How accurate must the registration be for the rig on a user's own mesh to match the direct rig?

    FWK_ICT_PATH=... FWK_THREADS=2 python benchmarks/register_accuracy.py [loop decimated midpoint]

The set-up of ``tests/rig/test_register.py::test_ict_held_out_identity_remeshed`` (a DT run on 10
ICT-FaceKit subjects, a held-out subject remeshed, permuted, in mm, rotated and moved, registered
by ``fwk apply --landmarks`` from the 10 rigger landmarks). Its registration error e = Y_reg - Y
(Y: the subject's own head in ICT topology, in the template frame: an exact registration) is
scaled by s in (1, 0.5, 0.35, 0.25, 0); for each s the neutral Y + s e gets its correspondence
(each scan vertex's closest point on it), the model predicts on it, and the prediction is carried
by Deformation Transfer (the default carry). Printed per remeshing and s: the mean vertex error
(template units, cm) and each expression's DAME over the direct rig's remeshed alike (the test's
ratio (b)). Needs ICT-FaceKit (FWK_ICT_PATH) and the rig extra (open3d, for the decimated head).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.rig.conftest import _execute  # noqa: E402
from tests.rig.test_register import (ICT, ICT_EXPRESSIONS, RIGGER_LANDMARKS, _remeshing,  # noqa: E402
                                     _rotation)

SCALES = (1.0, 0.5, 0.35, 0.25, 0.0)


def main(kinds: list[str]) -> None:
    import fwk.apply as fwk_apply
    from fwk.apply import Applier, apply
    from fwk.data import Template
    from fwk.data.io import read_obj, write_obj
    from fwk.plugins import get_registry
    from fwk.rig.carry import DeformationCarry
    from fwk.rig.register import closest_points

    if ICT is None:
        raise SystemExit("register_accuracy: needs ICT-FaceKit (set FWK_ICT_PATH to the unpacked FaceXModel)")
    tmp = Path(tempfile.mkdtemp(prefix="fwk-register-accuracy-"))
    recipe = {"name": "ict-register", "task": "blendshapes", "seed": 0,
              "dataset": {"name": "ict-facekit", "path": str(ICT), "region": "face-head", "n_subjects": 10,
                          "shapes": ["neutral", *ICT_EXPRESSIONS]},
              "split": {"ratios": [0.6, 0.2, 0.2]},
              "models": {"dt": {"name": "dt", "sources": 0}}, "renders": 0, "metrics": ["l1", "l2"]}
    run = _execute(recipe, tmp)
    split = json.loads((run / "split.json").read_text())
    data = get_registry().get("dataset", "ict-facekit")(path=str(ICT), region="face-head", n_subjects=10,
                                                         shapes=["neutral", *ICT_EXPRESSIONS]).load()
    P = np.asarray(data.positions[data.subjects.index(split["test"][0])])
    _, tT = read_obj(run / "template.obj")
    F = tT.triangles
    write_obj(tmp / "head.obj", P[0], tT)
    apply(run, tmp / "head.obj", tmp / "direct", log=lambda *_: None, say=None)
    direct = {e: read_obj(tmp / "direct" / f"{e}.obj")[0] for e in ICT_EXPRESSIONS}
    dame = get_registry().get("metric", "dame")()
    app = Applier(run, say=None)
    picks = np.array(list(RIGGER_LANDMARKS.values()))
    for kind in kinds:
        fn, F2, lmk = _remeshing(kind, P[0], F)
        rng = np.random.default_rng(5)
        perm = rng.permutation(len(fn(P[0])))
        inv = np.argsort(perm)
        R, t = _rotation(rng), np.array([250.0, -80.0, 40.0])
        Fs = inv[F2]
        d = tmp / kind
        d.mkdir()
        V = (10.0 * fn(P[0]) @ R.T + t)[perm]
        (d / "scan.obj").write_text("".join(f"v {x:.10g} {y:.10g} {z:.10g}\n" for x, y, z in V)
                                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in Fs))
        (d / "lm.json").write_text(json.dumps(
            {"landmarks": [{"template": int(i), "scan": int(inv[j])} for i, j in zip(picks, lmk)]}))
        regs, real = [], fwk_apply.register_neutral
        fwk_apply.register_neutral = lambda *a, **k: regs.append(real(*a, **k)) or regs[-1]
        try:
            apply(run, d / "scan.obj", d / "rig", landmarks=d / "lm.json", log=lambda *_: None, say=None)
        finally:
            fwk_apply.register_neutral = real
        reg = regs[-1]
        sub = Template(fn(P[0]), F2)
        Xs = (V - reg.translation) @ reg.rotation * reg.unit
        Y = ((10.0 * P[0] @ R.T + t) - reg.translation) @ reg.rotation * reg.unit
        err = reg.neutral - Y
        for s in SCALES:
            Ys = Y + s * err
            tri, bary, dist = closest_points(Ys, F, Xs)
            r = dataclasses.replace(reg, neutral=Ys, triangle=tri, bary=bary, distance=dist / reg.unit,
                                    weight=np.ones(len(Xs)))
            dc = DeformationCarry(r, Fs)
            preds = app.predict([Ys], ICT_EXPRESSIONS)[0]
            out = []
            for i, e in enumerate(ICT_EXPRESSIONS, start=1):
                truth = fn(P[i])
                es = float(dame(fn(direct[e])[None], truth[None], sub)[0][0])
                got = ((dc.carry(preds[e])[inv] - t) @ R) / 10.0
                out.append(f"{e} {float(dame(got[None], truth[None], sub)[0][0]) / es:.2f}x")
            print(f"{kind} s={s:.2f}: mean vertex error {np.linalg.norm(s * err, axis=1).mean():.3f} cm; DAME over "
                  "the direct rig remeshed alike: " + ", ".join(out), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["loop", "decimated", "midpoint"])
