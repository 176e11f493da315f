"""Per-model training step time, inference time and parameter count at the thesis configuration
(section 3.4: channels [|f|, 16, 32, 64, 128], pooling factor 4, latent 64, batch 16), on a
~5k-vertex synthetic head and the 11k-vertex ICT-FaceKit face-head region (a synthetic head of
that size when the data is absent). CPU here; the same script uses CUDA when available.

    python benchmarks/training.py [--steps 5] [--sizes 5000 11248]

Prints a table and, as its last line, one JSON object {model: {n_vertices: {step_ms, infer_ms,
params}}} plus flat per-model ``step_ms``, ``params`` and ``n_vertices`` of the largest mesh.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fwk.plugins import get_registry  # noqa: E402
from fwk.recipes import make_spec  # noqa: E402

CONVS = {"spiral": {"name": "spiral"}, "spiral++": {"name": "spiral++", "length": 9},
         "feast": {"name": "feast", "heads": 8}, "lsa": {"name": "lsa"}}


def template_of(n):
    from _ict import face_head

    if n >= 11000:
        col, src = face_head(1)
        return col.template, src
    reg = get_registry()
    col = reg.get("dataset", "synthetic-heads")(n_subjects=1, n_vertices=n).load(None)
    return col.template, "synthetic-heads"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=5)
    ap.add_argument("--sizes", type=int, nargs="+", default=[5000, 11248])
    a = ap.parse_args()
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    reg = get_registry()
    out, flat = {}, {}
    print(f"device {dev}; batch 16; channels [3, 16, 32, 64, 128]; latent 64; pooling factor 4")
    print(f"{'model':<10} {'n':>6} {'step ms':>9} {'infer ms':>9} {'params':>10}")
    for n in a.sizes:
        t, src = template_of(n)
        x = torch.randn(16, t.n_vertices, 3, device=dev)
        for name, conv in {**CONVS, "vcconv": None}.items():
            if conv is None:  # the thesis's fully convolutional vcconv VAE (section 3.4)
                spec = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 35}, "channels": [32, 64, 128, 128, 8],
                        "latent_vertices": 8, "sampler": {"name": "simple", "levels": 4},
                        "residual_rate": 0.5}
            else:
                spec = {"name": "ae", "conv": conv, "channels": [16, 32, 64, 128], "latent": 64,
                        "sampler": {"name": "quadric", "factors": [4, 4, 4, 4]}}
            m = make_spec("model", spec, "model", reg).build()
            enc, dec = m.build_encoder(t, 3).to(dev), m.build_decoder(t, 3).to(dev)
            params = sum(p.numel() for p in list(enc.parameters()) + list(dec.parameters()))
            opt = torch.optim.Adam(list(enc.parameters()) + list(dec.parameters()), 1e-3)

            def step():
                opt.zero_grad()
                loss = (dec(enc(x)[0]) - x).abs().mean()
                loss.backward()
                opt.step()

            step()
            ts = []
            for _ in range(a.steps):
                t0 = time.perf_counter()
                step()
                if dev == "cuda":
                    torch.cuda.synchronize()
                ts.append(time.perf_counter() - t0)
            with torch.no_grad():
                t0 = time.perf_counter()
                dec(enc(x)[0])
                infer = time.perf_counter() - t0
            r = {"step_ms": 1000 * float(np.median(ts)), "infer_ms": 1000 * infer, "params": int(params),
                 "n_vertices": t.n_vertices, "source": src}
            out.setdefault(name, {})[t.n_vertices] = r
            flat[name] = {k: r[k] for k in ("step_ms", "params", "n_vertices")}
            print(f"{name:<10} {t.n_vertices:>6} {r['step_ms']:>9.1f} {r['infer_ms']:>9.1f} {params:>10}")
    print(json.dumps({**flat, "detail": out, "device": dev}))


if __name__ == "__main__":
    main()
