"""Run the authors' FMPD MATLAB file under GNU Octave and compare it with the literal port
(``wang2012_fmpd``) and with fwk's ``fmpd`` metric. Not a test (it needs Octave and the .m file,
which fwk does not ship: its licence is the authors'); run by hand:

    apt-get install octave   # once
    python tests/references/check_against_octave.py PATH/TO/Wang_perceptual_distance.m

(the file is ``PScan3Dcompare/Wang_perceptual_distance.m`` of psapirstein/mesh-comparing). Prints
one line per case: Octave's FMPD, the port's and fwk's with their relative differences, and the
largest relative difference of the port's local roughness (where Octave's is > 1e-6), then a
JSON line. The ICT-FaceKit cases are skipped when the data is absent.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import scipy.io as sio

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tests.references import wang2012_fmpd as W  # noqa: E402

DRIVER = r"""
d = load('cases.mat');
fid = fopen('out.txt', 'w');
k = 0;
while isfield(d, sprintf('V1_%d', k))
  s1.Vs = d.(sprintf('V1_%d', k)); s1.F3s = double(d.(sprintf('F_%d', k)));
  s2.Vs = d.(sprintf('V2_%d', k)); s2.F3s = s1.F3s;
  [dist, r1, r2] = Wang_perceptual_distance(s1, s2);
  fprintf(fid, '%d %.17g\n', k, dist);
  save('-v6', sprintf('rough_%d.mat', k), 'r1', 'r2');
  k = k + 1;
end
fclose(fid);
"""


def cases():
    """(name, V1, V2, F) pairs: synthetic meshes with and without borders, degenerate cases,
    and ICT-FaceKit face-head pairs when the data is there."""
    import trimesh

    from fwk.cache import Cache
    from fwk.plugins import get_registry
    from fwk.testing import ict_path
    from fwk.testing.metric import small_mesh

    reg = get_registry()
    rng = np.random.default_rng(0)
    out = []
    V, t = small_mesh()
    F = t.triangles
    out.append(("grid 9x9 (border), noise 1e-3", V, V + rng.normal(0, 0.001, V.shape), F))
    m = trimesh.creation.icosphere(subdivisions=2)
    S, FS = np.asarray(m.vertices), np.asarray(m.faces)
    out.append(("icosphere 2 (closed), noise 2e-3", S, S + rng.normal(0, 0.002, S.shape), FS))
    keep = S[FS].mean(1)[:, 2] < 0.5
    used = np.unique(FS[keep])
    remap = -np.ones(len(S), dtype=np.int64)
    remap[used] = np.arange(len(used))
    So, Fo = S[used], remap[FS[keep]]
    out.append(("open sphere cap, stretched + noise", So, So * [1, 1.2, 0.9] + rng.normal(0, 0.01, So.shape), Fo))
    sh = reg.get("dataset", "synthetic-heads")(n_subjects=2, n_vertices=2000).load(Cache())
    out.append(("synthetic-heads 2000: expression vs neutral", sh.positions[0, 0], sh.positions[0, 1], sh.template.triangles))
    out.append(("synthetic-heads 2000: identity 0 vs 1", sh.positions[0, 0], sh.positions[1, 0], sh.template.triangles))
    V1 = V.copy()
    V1[40] = V1[41]
    V2 = V1 + rng.normal(0, 0.001, V.shape)
    V2[40] = V2[41]
    out.append(("grid, two coincident vertices", V1, V2, F))
    V1 = V.copy()
    V1[40] = 0.5 * (V1[39] + V1[41])
    out.append(("grid, a collinear triangle", V1, V, F))
    F2 = F.copy()
    F2[10] = F2[10][::-1]
    out.append(("grid, one flipped face", V, V + rng.normal(0, 0.001, V.shape), F2))
    Vi = np.vstack([V, [[3.0, 3.0, 3.0]]])
    out.append(("grid + an unreferenced vertex", Vi, Vi + rng.normal(0, 0.001, Vi.shape), F))
    Fn = np.vstack([F, [[F[5, 0], F[5, 1], 80]]])
    out.append(("grid, a non-manifold edge", V, V + rng.normal(0, 0.001, V.shape), Fn))
    folder = ict_path()
    if folder is not None:
        col = reg.get("dataset", "ict-facekit")(path=str(folder), n_subjects=3).load(Cache())
        T = col.template.triangles
        out.append(("ICT face-head: identity 0 vs 1", col.positions[0, 0], col.positions[1, 0], T))
        out.append(("ICT face-head: expression 1 vs neutral (id 1)", col.positions[1, 1], col.positions[1, 0], T))
        out.append(("ICT face-head: expression 2 vs neutral (id 2)", col.positions[2, 2], col.positions[2, 0], T))
        P = col.positions[0, 0]
        out.append(("ICT face-head: identity 0, noise 0.01 cm", P, P + rng.normal(0, 0.01, P.shape), T))
    return out


def main(mfile: str):
    from fwk.data import Template
    from fwk.plugins import get_registry

    if shutil.which("octave-cli") is None:
        sys.exit("octave-cli not found (apt-get install octave)")
    fmpd = get_registry().get("metric", "fmpd")()
    cs = cases()
    with tempfile.TemporaryDirectory() as d:
        shutil.copy(mfile, Path(d) / "Wang_perceptual_distance.m")
        (Path(d) / "driver.m").write_text(DRIVER)
        mats = {}
        for k, (_, a, b, f) in enumerate(cs):
            mats[f"V1_{k}"], mats[f"V2_{k}"] = np.asarray(a, float), np.asarray(b, float)
            mats[f"F_{k}"] = (np.asarray(f) + 1).astype(float)
        sio.savemat(Path(d) / "cases.mat", mats)
        subprocess.run(["octave-cli", "-q", "driver.m"], cwd=d, check=True)
        octv = {int(x.split()[0]): float(x.split()[1]) for x in (Path(d) / "out.txt").read_text().split("\n") if x}
        rough = [sio.loadmat(Path(d) / f"rough_{k}.mat") for k in range(len(cs))]
    ver = subprocess.run(["octave-cli", "--version"], capture_output=True, text=True).stdout.split("\n")[0]
    print(ver)
    print(f"{'case':<48} {'Octave':>12} {'port rel':>9} {'fwk rel':>9} {'R rel':>9}")
    res = []
    for k, (name, a, b, f) in enumerate(cs):
        ref = octv[k]
        dist, r1, r2 = W.wang_perceptual_distance(a, f, b)
        ours = float(fmpd(np.asarray(b)[None], np.asarray(a)[None], Template(a, f))[0][0])
        o1, o2 = rough[k]["r1"].ravel(), rough[k]["r2"].ravel()
        big = np.abs(o1) > 1e-6
        rr = float(np.max(np.abs(r1[big] - o1[big]) / np.abs(o1[big]))) if big.any() else 0.0
        rel = lambda x: abs(x - ref) / max(abs(ref), 1e-300)  # noqa: E731
        res.append({"case": name, "octave": ref, "port": dist, "fwk": ours, "port_rel": rel(dist), "fwk_rel": rel(ours),
                    "roughness_rel": rr})
        print(f"{name:<48} {ref:>12.6g} {rel(dist):>9.1e} {rel(ours):>9.1e} {rr:>9.1e}")
    print(json.dumps({"octave": ver, "cases": res}))


if __name__ == "__main__":
    main(sys.argv[1])
