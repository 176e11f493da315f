"""DR on ICT-FaceKit: the distribution of its features and what each scaling makes of them.

    OMP_NUM_THREADS=1 python benchmarks/dr_distribution.py [--subjects 48] [--train 40]

Data: the ``ict-facekit`` dataset (face-head region, 11,248 vertices), ``--subjects`` sampled
identities, each with five expressions (the three built-in composites and two more defined
here: ``smile`` and ``blink``), preprocessed as every fwk task does (centred, rigidly
registered to the mean of the training neutrals, one scale into [-1, 1]: the evaluation
space). The first ``--train`` subjects are the training set, the rest the test set.

Two families of features, as fwk's models use them:

- identities: each neutral against the mean training neutral (``dr`` with ``ref: mean``, fitted
  on the training neutrals);
- expressions: each expression against the subject's own neutral (``ref: sample``, fitted on
  the training expressions; all expressions pooled).

Printed, for DR before issue 17 (``regularisation: 0, weight_ceiling: null``, the old
behaviour) and after (the defaults: ``regularisation: 0.01``, ``weight_ceiling: 10``), and for a
sweep of ``regularisation``:

1. the distribution over all subjects and vertices of the rotation angle |log R| and of the
   stretch ||S - I||_F (percentiles 50, 90, 99, 99.9, max), the number of vertices whose angle
   exceeds 0.5 rad for some subject, the number of (subject, vertex) pairs whose gradient is a
   reflection (det T <= 0: a fold), and the round trip (decode(encode(P)), registered onto P,
   L1 in the evaluation space, test subjects). Also measured on the data themselves: triangles
   whose normal reverses between the reference and the mesh (folds), and the angle between each
   vertex normal and the reference's (rotations that are really there);
2. for every scaling option (norm: granularity x range x centre; std): the share of [-1, 1]
   that the middle 98 % of the training values fill (per channel, over samples and vertices:
   (Q99 - Q1) / 2; median and minimum over the 9 channels), the share of test values outside
   [-1, 1], the median over vertices and channels of the interquartile range over the training
   samples as a share of [-1, 1] (``iqr``: how much of the range a typical vertex uses), and the L1 (evaluation space, test subjects) of decoding a zero network output,
   registered onto the truth as the thesis evaluates DR, next to the L1 of the mean shape
   (identities) or of the subject's neutral and of neutral + mean offset (expressions).

The last line is one JSON object with every figure. Needs the ICT-FaceKit data (exits with
status 2 and a message when it is absent).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from fwk.cache import Cache
from fwk.data.preprocess import Preprocessor
from fwk.geometry.operators import vertex_normals
from fwk.plugins import get_registry
from fwk.scaling import Scaler
from fwk.testing import ICT_SKIP_REASON, ict_path

EXTRA_EXPRESSIONS = {"smile": {"mouthSmile_L": 1.0, "mouthSmile_R": 1.0},
                     "blink": {"eyeBlink_L": 1.0, "eyeBlink_R": 1.0}}
EXPRESSIONS = ["face-compression", "mouth-wide", "oo-brow-raise-eyes-wide", *EXTRA_EXPRESSIONS]
PCTS = (50, 90, 99, 99.9, 100)
# (kind, granularity, range, centre); the first is the norm every dr used before issue 17
SCALINGS = [("norm", "channel", "minmax", "mid"), ("norm", "channel", "minmax", "mean"),
            ("norm", "channel", "quantile", "mid"), ("norm", "channel", "quantile", "mean"),
            ("norm", "vertex", "minmax", "mid"), ("norm", "vertex", "minmax", "mean"),
            ("norm", "vertex", "quantile", "mid"), ("norm", "vertex", "quantile", "mean"),
            ("std", "vertex", None, None), ("std", "channel", None, None)]
BEFORE = {"regularisation": 0.0, "weight_ceiling": None}
AFTER = "regularisation 1e-2 (default)"
SWEEP = [("before: none, no ceiling", BEFORE), ("ceiling only", {"regularisation": 0.0}),
         ("regularisation 3e-3", {"regularisation": 3e-3}), (AFTER, {}),
         ("regularisation 3e-2", {"regularisation": 3e-2})]


def l1(a, b) -> float:
    return float(np.abs(np.asarray(a) - np.asarray(b)).mean())


def load(n_subjects: int):
    folder = ict_path()
    if folder is None:
        print(ICT_SKIP_REASON, file=sys.stderr)
        sys.exit(2)
    ds = get_registry().get("dataset", "ict-facekit")(path=str(folder), n_subjects=n_subjects,
                                                      shapes=["neutral", *EXPRESSIONS],
                                                      expressions=EXTRA_EXPRESSIONS)
    return ds.load(Cache())


def flipped_triangles(P, ref, F) -> int:
    """(sample, triangle) pairs whose normal reverses between ref and P."""
    def nrm(V):
        return np.cross(V[..., F[:, 1], :] - V[..., F[:, 0], :], V[..., F[:, 2], :] - V[..., F[:, 0], :])
    return int(((nrm(P) * nrm(ref)).sum(-1) < 0).sum())


def normal_angles(P, ref, F) -> list[float]:
    """Percentiles of the angle between each vertex normal and the reference's (a rotation
    that is in the data, whatever DR makes of it)."""
    c = (vertex_normals(P, F) * vertex_normals(np.broadcast_to(ref, P.shape), F)).sum(-1)
    return [float(x) for x in np.percentile(np.arccos(np.clip(c, -1, 1)), PCTS)]


def distribution(r, P, ref, test, F) -> dict:
    """Angle / stretch percentiles, counts and the round trip of dr ``r`` (scaling none) on P."""
    f = r.raw_features(P, ref)
    ang = np.linalg.norm(f[..., :3], axis=-1)
    S = np.zeros((*f.shape[:2], 3, 3))
    iu = np.triu_indices(3)
    S[..., iu[0], iu[1]] = f[..., 3:]
    S[..., iu[1], iu[0]] = f[..., 3:]
    stretch = np.linalg.norm(S, axis=(-2, -1))  # ||S - I||_F
    det = np.linalg.det(S + np.eye(3))  # det T = det S (det R = 1)
    rr = None if ref is None else ref[test]
    X = r.decode(f[test], rr, P[test])
    return {"angle": [float(x) for x in np.percentile(ang, PCTS)],
            "stretch": [float(x) for x in np.percentile(stretch, PCTS)],
            "vertices_above_0.5": int((ang.max(0) > 0.5).sum()), "above_2": int((ang > 2).sum()),
            "folds": int((det <= 0).sum()), "round_trip_l1": l1(X, P[test])}, f


def scaling_rows(r, f, P, ref, train, test, baselines) -> list[dict]:
    """Each scaling option fitted on f[train]: fill of [-1, 1], test values outside, zero-output L1."""
    rows = []
    for kind, gran, rng, centre in SCALINGS:
        s = Scaler(kind, gran, range=rng or "minmax", centre=centre or "mid").fit(f[train])
        G = s.transform(f[train])
        q1, q99 = np.quantile(G.reshape(-1, G.shape[-1]), [0.01, 0.99], axis=0)
        share = (q99 - q1) / 2
        q25, q75 = np.quantile(G, [0.25, 0.75], axis=0)  # per vertex and channel, over the training samples
        iqr = float(np.median((q75 - q25) / 2))
        out = float((np.abs(s.transform(f[test])) > 1).mean())
        zero = s.inverse(np.zeros((len(test), *f.shape[1:])))
        rr = None if ref is None else ref[test]
        X0 = r.integrate(r.gradients(zero), rr, P[test])
        rows.append({"kind": kind, "granularity": gran, "range": rng, "centre": centre,
                     "fill_median": float(np.median(share)), "fill_min": float(share.min()), "vertex_iqr_fill": iqr,
                     "test_outside": out, "zero_l1": l1(X0, P[test]), **baselines})
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--subjects", type=int, default=48)
    ap.add_argument("--train", type=int, default=40)
    ap.add_argument("--no-sweep", action="store_true", help="only before / after, not the regularisation sweep")
    a = ap.parse_args()
    t0 = time.perf_counter()
    col = load(a.subjects)
    pos = np.asarray(col.positions)
    train, test = np.arange(a.train), np.arange(a.train, a.subjects)
    pre = Preprocessor().fit(pos[train, 0], pos[train])
    X, _ = pre.transform(pos, pos[:, 0])
    t = col.template
    F = t.triangles
    N = X[:, 0]  # (S, n, 3) neutrals
    E = X[:, 1:].transpose(1, 0, 2, 3).reshape(-1, *N.shape[1:])  # (expression-major) all expressions
    NE = np.broadcast_to(N, (len(EXPRESSIONS), *N.shape)).reshape(E.shape)  # each one's neutral
    etrain = np.concatenate([train + k * a.subjects for k in range(len(EXPRESSIONS))])
    etest = np.concatenate([test + k * a.subjects for k in range(len(EXPRESSIONS))])
    DR = get_registry().get("representation", "dr")
    mean = N[train].mean(0)
    out = {"n_vertices": t.n_vertices, "subjects": a.subjects, "train": a.train, "expressions": EXPRESSIONS,
           "omp_threads": os.environ.get("OMP_NUM_THREADS"),
           "data_flipped_triangles": {"identities": flipped_triangles(N, mean, F),
                                      "expressions": flipped_triangles(E, NE, F), "triangles": len(F)},
           "data_normal_angle": {"identities": normal_angles(N, mean, F), "expressions": normal_angles(E, NE, F)},
           "baselines": {"identity_mean_shape_l1": l1(mean[None], N[test]),
                         "expression_neutral_l1": l1(NE[etest], E[etest]),
                         "expression_mean_offset_l1": l1(NE[etest] + (E[etrain] - NE[etrain]).mean(0), E[etest])},
           "sweep": {}, "scaling": {}}
    feats = {}
    for label, params in SWEEP if not a.no_sweep else [SWEEP[0], SWEEP[3]]:
        ri = DR(scaling="none", **params)
        ri.fit(N[train], None, t)
        di, fi = distribution(ri, N, None, test, F)
        re = DR(scaling="none", ref="sample", **params)
        re.fit(E[etrain], NE[etrain], t)
        de, fe = distribution(re, E, NE, etest, F)
        out["sweep"][label] = {"identities": di, "expressions": de}
        if label.startswith("before") or label == AFTER:
            feats["before" if label.startswith("before") else "after"] = (ri, fi, re, fe)
        print(f"[{time.perf_counter() - t0:6.1f} s] {label}", file=sys.stderr, flush=True)
    b = out["baselines"]
    for when, (ri, fi, re, fe) in feats.items():
        out["scaling"][when] = {
            "identities": scaling_rows(ri, fi, N, None, train, test, {"baseline_l1": b["identity_mean_shape_l1"]}),
            "expressions": scaling_rows(re, fe, E, NE, etrain, etest, {"baseline_l1": b["expression_neutral_l1"]})}
    out["seconds"] = time.perf_counter() - t0

    print(f"ICT-FaceKit face-head, {t.n_vertices} vertices, {a.subjects} identities ({a.train} train), "
          f"expressions {', '.join(EXPRESSIONS)}; evaluation space")
    d = out["data_flipped_triangles"]
    print(f"triangles whose normal reverses in the data: identities vs mean {d['identities']} "
          f"(subject, triangle) pairs; expressions vs own neutral {d['expressions']} (of {d['triangles']} triangles)")
    na = out["data_normal_angle"]
    print("vertex normal against the reference's, rad (p50 p90 p99 p99.9 max): identities "
          + " ".join(f"{v:.3f}" for v in na["identities"]) + "; expressions " + " ".join(f"{v:.3f}" for v in na["expressions"]))
    print(f"baselines (test): mean shape L1 {b['identity_mean_shape_l1']:.4f}; expression: neutral L1 "
          f"{b['expression_neutral_l1']:.4f}, neutral + mean offset {b['expression_mean_offset_l1']:.4f}")
    print("\n1. distribution   |log R| rad: p50 p90 p99 p99.9 max      ||S-I||_F: p50 p90 p99 p99.9 max"
          "      v>0.5  >2rad  folds  round-trip L1")
    for label, r in out["sweep"].items():
        for fam in ("identities", "expressions"):
            x = r[fam]
            print(f"{label:26s} {fam[:5]}  " + " ".join(f"{v:5.3f}" for v in x["angle"]) + "   "
                  + " ".join(f"{v:6.3f}" for v in x["stretch"])
                  + f"  {x['vertices_above_0.5']:6d} {x['above_2']:6d} {x['folds']:6d}  {x['round_trip_l1']:.2e}")
    print("\n2. scaling (fill: share of [-1, 1] the middle 98 % of train values fill, median / min over channels;"
          " out: test values outside [-1, 1]; zero: L1 of a zero output)")
    for when, fams in out["scaling"].items():
        for fam, rows in fams.items():
            print(f"  dr {when}, {fam} (baseline L1 {rows[0]['baseline_l1']:.4f})")
            for x in rows:
                name = f"{x['kind']} {x['granularity']}" + (f" {x['range']} {x['centre']}" if x["range"] else "")
                print(f"    {name:34s} fill {x['fill_median']:5.3f} / {x['fill_min']:5.3f}  out {x['test_outside']:6.4f}"
                      f"  iqr {x['vertex_iqr_fill']:5.3f}  zero L1 {x['zero_l1']:.4f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
