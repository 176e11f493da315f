"""Time of ``fwk rig`` with a shipped rig model (issue 29's target: OBJ, glb and USD with the 51
ARKit shapes in under 10 s on 2 cores, under 20 s with FBX; no training, no run directory).

Each row is one ``fwk rig`` process, started as a user starts it (imports included), on a head in
the model's topology: a test identity of the model's own split on ICT-FaceKit's full
26,719-vertex mesh when the data is present (``FWK_ICT_PATH`` or ../shared/data/ict-facekit; the
teeth, gums, tongue and eyes then follow the face), else the model's mean training neutral
(its 11,248-vertex region). Rows: a fresh machine (an empty ``FWK_CACHE``: the network's graph
hierarchy is built), then the same cache again (warm), then with ``--format obj,gltf,usd,fbx``
where bpy is installed. Prints each process's wall time, fwk rig's own line (loading, predicting,
writing), the thread count and the load average: the machine is shared, so compare numbers of one
run, and read a time with its load.

    python benchmarks/rig.py [--model ict-face] [--threads 2]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _head(folder: Path, out: Path) -> str:
    """Write the head to rig into ``out``; returns what it is."""
    from fwk.data.io import write_obj
    from fwk.safeio import load_npz
    from fwk.testing import ict_path

    card = json.loads((folder / "card.json").read_text())
    ict = ict_path()
    if ict is not None and (card.get("dataset") or {}).get("name") == "ict-facekit":
        from fwk.plugins import get_registry

        ids = card["identities"]
        n = sum(len(v) for v in ids.values())
        full = get_registry().get("dataset", "ict-facekit")(path=str(ict), region="full", n_subjects=n,
                                                             shapes=["neutral"]).load()
        s = ids["test"][0]
        write_obj(out, np.asarray(full.positions[full.subjects.index(s), 0]), full.template)
        return f"test identity {s}, ICT-FaceKit's full head ({full.template.n_vertices} vertices)"
    V = np.asarray(load_npz(folder / "stats" / "preprocess.npz")["mean_centred"])
    F = np.asarray(load_npz(folder / "stats" / "template.npz")["triangles"])
    out.write_text("".join(f"v {x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in V)
                   + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F))
    return f"the model's mean training neutral ({len(V)} vertices; no ICT-FaceKit data here)"


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=None, help="a shipped rig model's name or a folder from fwk pack")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    from fwk.pack import find_model
    from fwk.rig.fbx import import_bpy

    folder = find_model(args.model)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        what = _head(folder, tmp / "head.obj")
        print(f"fwk rig with {folder.name} on {what}; threads {args.threads}, load average "
              f"{os.getloadavg()[0]:.2f}")
        try:
            import_bpy()
            fbx = True
        except Exception:  # noqa: BLE001 - any failure to load bpy means: no FBX row
            fbx = False
        rows = [("fresh cache", "obj,gltf,usd", tmp / "cache"), ("warm cache", "obj,gltf,usd", tmp / "cache")]
        if fbx:
            rows.append(("warm cache, with FBX", "obj,gltf,usd,fbx", tmp / "cache"))
        for i, (label, fmt, cache) in enumerate(rows):
            env = {**os.environ, "FWK_CACHE": str(cache), "FWK_THREADS": str(args.threads)}
            cmd = [sys.executable, "-m", "fwk", "rig", str(tmp / "head.obj"), "--out", str(tmp / f"rig{i}"),
                   "--format", fmt] + (["--model", args.model] if args.model else [])
            t0 = time.perf_counter()
            r = subprocess.run(cmd, env=env, capture_output=True, text=True)
            seconds = time.perf_counter() - t0
            if r.returncode:
                print(f"{label}: failed ({r.returncode}): {r.stderr.strip()[-400:]}")
                continue
            line = next((x for x in r.stdout.splitlines() if x.startswith("fwk rig:")), "")
            n = len(list((tmp / f"rig{i}").glob("*.obj")))
            print(f"{label:24s} {seconds:6.2f} s wall, {n} shapes ({fmt}); {line}")
        if not fbx:
            print("with FBX: not measured (bpy is not installed: pip install -e \".[fbx]\", Python 3.11)")


if __name__ == "__main__":
    main()
