"""What packing costs a rig model: the test metrics of a packed model (``fwk pack``) against the
run's own model, on the run's test identities, per expression.

    python benchmarks/pack_fidelity.py RUN PACKED [--metrics l1,dame,fmpd]

RUN is a finished blendshapes run (or one seed's sub-run), PACKED the folder ``fwk pack`` wrote
from it (a shipped model's name works too: ``ict-face``). The run's dataset is loaded as its
recipe says (ICT-FaceKit needs ``FWK_ICT_PATH``); each test identity's neutral goes through
``fwk apply``'s path (``fwk.apply.Applier``: registration, prediction, back into the dataset's
units) with both models, and each metric is computed against the identity's true expression in
those units. Prints per expression the run's mean, the packed model's and their relative
difference, then the largest relative difference per metric and the largest vertex difference
between the two models' predictions.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("packed")
    ap.add_argument("--metrics", default="l1,dame,fmpd")
    args = ap.parse_args(argv)
    from fwk.apply import Applier
    from fwk.lifecycle import open_run, seed_sub_run
    from fwk.pack import find_model
    from fwk.plugins import get_registry

    reg = get_registry()
    packed = find_model(args.packed)
    run_dir = seed_sub_run(Path(args.run), None, reg, say=lambda m: None)
    run = open_run(run_dir)
    split = json.loads((run_dir / "split.json").read_text())
    data = run.params["dataset"].build().load()
    a, b = Applier(run_dir, say=None), Applier(packed, say=None)
    exprs = a.expressions
    idx = [data.subjects.index(s) for s in split["test"]]
    j0 = data.shape_index("neutral")
    neutrals = [np.asarray(data.positions[i, j0], dtype=np.float64) for i in idx]
    pa, pb = a.predict(neutrals, exprs), b.predict(neutrals, exprs)
    metrics = [reg.get("metric", m)() for m in args.metrics.split(",")]
    tpl = data.template
    worst = {m.name: (0.0, "") for m in metrics}
    vdiff = 0.0
    print(f"{len(idx)} test identities of {run_dir}; packed: {packed}")
    print("expression | " + " | ".join(f"{m.name} run / packed (rel.)" for m in metrics))
    for e in exprs:
        je = data.shape_index(e)
        ok = [k for k, i in enumerate(idx) if data.present[i, je]]
        G = np.stack([np.asarray(data.positions[idx[k], je], dtype=np.float64) for k in ok])
        A = np.stack([pa[k][e] for k in ok])
        B = np.stack([pb[k][e] for k in ok])
        vdiff = max(vdiff, float(np.abs(A - B).max()))
        cells = []
        for m in metrics:
            x = float(np.mean(m(A, G, tpl)[0]))
            y = float(np.mean(m(B, G, tpl)[0]))
            rel = abs(y - x) / max(abs(x), 1e-300)
            if rel > worst[m.name][0]:
                worst[m.name] = (rel, e)
            cells.append(f"{x:.5g} / {y:.5g} ({100 * rel:.3f} %)")
        print(f"{e} | " + " | ".join(cells))
    print("largest relative difference: " + "; ".join(f"{k} {100 * v:.3f} % ({e})" for k, (v, e) in worst.items()))
    print(f"largest vertex difference between the two models' predictions: {vdiff:.3g} {a.units}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
