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
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.rig.test_register import ICT, ICT_EXPRESSIONS, RemeshedScan, held_out_direct_rig  # noqa: E402

SCALES = (1.0, 0.5, 0.35, 0.25, 0.0)


def main(kinds: list[str]) -> None:
    import fwk.apply as fwk_apply
    from fwk.apply import Applier, apply
    from fwk.data import Template
    from fwk.plugins import get_registry
    from fwk.rig.carry import DeformationCarry
    from fwk.rig.register import closest_points

    if ICT is None:
        raise SystemExit("register_accuracy: needs ICT-FaceKit (set FWK_ICT_PATH to the unpacked FaceXModel)")
    tmp = Path(tempfile.mkdtemp(prefix="fwk-register-accuracy-"))
    (tmp / "run").mkdir()
    rig = held_out_direct_rig(tmp / "run")
    run, P, F = rig.run, rig.P, rig.template.triangles
    dame = get_registry().get("metric", "dame")()
    app = Applier(run, say=None)
    for kind in kinds:
        d = tmp / kind
        d.mkdir()
        sc = RemeshedScan(kind, P[0], F, d)
        regs, real = [], fwk_apply.register_neutral
        fwk_apply.register_neutral = lambda *a, **k: regs.append(real(*a, **k)) or regs[-1]
        try:
            apply(run, sc.scan, d / "rig", landmarks=sc.landmarks, log=lambda *_: None, say=None)
        finally:
            fwk_apply.register_neutral = real
        reg = regs[-1]
        sub = Template(sc.fn(P[0]), sc.faces)
        Xs = (sc.remesh(P[0]) - reg.translation) @ reg.rotation * reg.unit  # the scan in the template frame
        Y = ((10.0 * P[0] @ sc.R.T + sc.t) - reg.translation) @ reg.rotation * reg.unit  # the exact registration
        err = reg.neutral - Y
        for s in SCALES:
            Ys = Y + s * err
            tri, bary, dist = closest_points(Ys, F, Xs)
            r = dataclasses.replace(reg, neutral=Ys, triangle=tri, bary=bary, distance=dist / reg.unit,
                                    weight=np.ones(len(Xs)))
            dc = DeformationCarry(r, sc.scan_faces)
            preds = app.predict([Ys], ICT_EXPRESSIONS)[0]
            out = []
            for i, e in enumerate(ICT_EXPRESSIONS, start=1):
                truth = sc.fn(P[i])
                es = float(dame(sc.fn(rig.direct[e])[None], truth[None], sub)[0][0])
                got = sc.back(dc.carry(preds[e]))
                out.append(f"{e} {float(dame(got[None], truth[None], sub)[0][0]) / es:.2f}x")
            print(f"{kind} s={s:.2f}: mean vertex error {np.linalg.norm(s * err, axis=1).mean():.3f} cm; DAME over "
                  "the direct rig remeshed alike: " + ", ".join(out), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["loop", "decimated", "midpoint"])
