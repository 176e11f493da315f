"""How many validation subjects does PBS's knee (thesis 5.3.4) need to be stable?  (issue 17, item 2)

Trains PBS once (the main job's setting: synthetic heads, 6,000 vertices, face-compression,
euclidean std + dr std spiral++ networks, 15 epochs at lr 2e-3), then scores every held-out
subject of a pool at every k of the thesis's grid (L1 and FMPD, the thesis's knee pair). For
m validation subjects drawn at random from the pool (500 draws per m), the knee of the mean
curves is chosen as pbs does (Pareto front of (L1, FMPD), knee rule of fwk_pb.knee) and compared
with the knee chosen on the whole pool."""
import json
import os
import sys
import tempfile
import time
import numpy as np
from fwk.data.preprocess import Preprocessor
from fwk.evaluation import evaluate, pareto_front
from fwk.plugins import get_registry
from fwk.protocols import FitData
from fwk.runs import make_test_context
from fwk_pb import PBS, knee, thesis_ks

N_TRAIN, N_POOL = 120, 80
OUT = os.environ.get("FWK_BENCH_OUT") or tempfile.mkdtemp(prefix="pbs-knee-")  # where its run and JSON go
EPOCHS = int(sys.argv[1]) if len(sys.argv) > 1 else 15
reg = get_registry()
t0 = time.time()
col = reg.get("dataset", "synthetic-heads")(n_vertices=6000, n_subjects=N_TRAIN + N_POOL,
                                            shapes=["neutral", "face-compression"]).load(None)
pre = Preprocessor().fit(np.asarray(col.positions[:N_TRAIN, 0]), np.asarray(col.positions[:N_TRAIN]))
X, _ = pre.transform(np.asarray(col.positions), np.asarray(col.positions[:, 0]))
col.positions = X
data = FitData(col.template.with_vertices(pre.mean_neutral), col.select(np.arange(N_TRAIN)),
               col.select(np.arange(N_TRAIN, N_TRAIN + N_POOL)), ["neutral", "face-compression"])
net = {"name": "vae", "conv": {"name": "spiral++", "length": 9}, "channels": [8, 16, 32], "latent": 16,
       "sampler": {"name": "quadric", "factors": [4, 4, 4]}}
m = PBS(spatial={"name": "euclidean", "scaling": "std"}, differential={"name": "dr", "scaling": "std"},
        network=net, k=0)
ctx = make_test_context(os.path.join(OUT, f"knee_run{EPOCHS}"), epochs=EPOCHS, batch_size=16, lr=2e-3, lr_decay=0.99, kl_weight=1e-6)
m.fit(data, ctx)
print(f"trained in {time.time() - t0:.0f} s", flush=True)
n = data.template.n_vertices
ks = thesis_ks(n)
m._fit_assembler(data.template, max(k for k in ks if k < n))
pool = data.val
N, G = np.asarray(pool.positions[:, 0]), np.asarray(pool.positions[:, 1])
Ps, Pd = m.branches(N, "face-compression")
allP = m.assemble(Ps, Pd, ks)
metrics = [reg.get("metric", "l1")(), reg.get("metric", "fmpd")(), reg.get("metric", "dame")()]
S = {k: np.zeros((len(ks), N_POOL)) for k in ("l1", "fmpd", "dame")}
for i, P in enumerate(allP):
    r = evaluate(P, G, m.template, metrics)
    for k in S:
        S[k][i] = r[k]["scores"]
print(f"scored {len(ks)} k x {N_POOL} subjects in {time.time() - t0:.0f} s", flush=True)


def choose(idx, y_name):
    x, y = S["l1"][:, idx].mean(1), S[y_name][:, idx].mean(1)
    front = pareto_front(np.stack([x, y], 1))
    return int(front[knee(x[front], y[front])])


out = {"ks": ks, "epochs": EPOCHS}
for y_name in ("fmpd", "dame"):
    ref = choose(np.arange(N_POOL), y_name)
    front = pareto_front(np.stack([S["l1"].mean(1), S[y_name].mean(1)], 1))
    print(f"knee pair (L1, {y_name}); pool of {N_POOL}: knee k = {ks[ref]} (front {[ks[j] for j in front]})")
    rng = np.random.default_rng(0)
    out[y_name] = {"ref_k": ks[ref], "front": [ks[j] for j in front], "rows": []}
    print(f"m  | same k as the pool | on the pool's front | chosen k: 10% / 50% / 90% | pool L1 / {y_name} excess at the chosen k (mean, 90th percentile)")
    for mm in (1, 2, 3, 5, 10, 20, 40):
        ch = np.array([choose(rng.choice(N_POOL, mm, replace=False), y_name) for _ in range(500)])
        same = float(np.mean(ch == ref))
        onfront = float(np.mean(np.isin(ch, front)))
        kk = np.array([ks[c] for c in ch])
        l1 = S["l1"].mean(1)[ch] / S["l1"].mean(1)[ref] - 1
        fm = S[y_name].mean(1)[ch] / S[y_name].mean(1)[ref] - 1
        q = np.percentile(kk, [10, 50, 90])
        print(f"{mm:2d} | {same:.2f} | {onfront:.2f} | {q[0]:.0f} / {q[1]:.0f} / {q[2]:.0f} | "
              f"L1 {l1.mean():+.2%} ({np.percentile(l1, 90):+.2%}), {y_name} {fm.mean():+.2%} ({np.percentile(fm, 90):+.2%})", flush=True)
        out[y_name]["rows"].append({"m": mm, "same": same, "on_front": onfront, "k_q": q.tolist(),
                                    "l1_excess": float(l1.mean()), "y_excess": float(fm.mean())})
json.dump(out, open(os.path.join(OUT, f"knee_stability_{EPOCHS}.json"), "w"), indent=1)
print(f"total {time.time() - t0:.0f} s")
