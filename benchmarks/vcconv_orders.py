"""Every evaluation order of every vcconv layer of the thesis-width and the chapter 5 width VAE,
forward and backward, timed; with the order ``auto`` takes, and the multiply-adds and traffic of
its cost model (``fwk_vcconv.VCConv.costs``, ``FLOAT_COST``).

    OMP_NUM_THREADS=2 python benchmarks/vcconv_orders.py [--repeat 4]
    FWK_VCCONV_NATIVE=0 OMP_NUM_THREADS=2 python benchmarks/vcconv_orders.py   # vcconv's torch code

``sum`` and ``basis`` run on vcconv's native kernels where they are built (``fwk_vcconv.native``;
printed), and the cost model is priced for the code that runs (``costs(b, native_kernels)``).

Batch 16 on ICT-FaceKit's face-head (11,248 vertices) when ICT-FaceKit is present, else a
synthetic head of that size (printed). Each layer gets a random input of its shape; a time is the
best of ``--repeat`` forward + backward passes (sum of the output as the loss). The last lines
say which prices of a float (in multiply-adds) would have picked the fastest order on every
layer: the evidence behind ``FLOAT_COST``.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _ict import face_head  # noqa: E402
from training import BATCH, VCCONV_VAE, VCCONV_VAE_CH5, networks  # noqa: E402

ORDERS = ("sum", "basis", "kernel")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=4)
    a = ap.parse_args()
    from fwk_vcconv import FLOAT_COST, VCConv, native

    col, src = face_head(1)
    t = col.template
    nat = native.available()
    print(f"template: {src}, {t.n_vertices} vertices; batch {BATCH}; {torch.get_num_threads()} threads; "
          f"FLOAT_COST {FLOAT_COST}; sum and basis on " + ("the native kernels" if nat else "the torch code"))
    rows = []
    for label, spec in (("thesis", VCCONV_VAE), ("ch5", VCCONV_VAE_CH5)):
        enc, dec, _ = networks(spec, t)
        for side, net in (("enc", enc), ("dec", dec)):
            for name, m in net.named_modules():
                if not isinstance(m, VCConv):
                    continue
                M, c, o = m.basis.shape
                x = torch.randn(BATCH, m.n_in, c, requires_grad=True)
                auto, ms = m.chosen_order(BATCH, nat), {}
                for order in ORDERS:
                    m.order = order

                    def step():
                        m(x).sum().backward()

                    step()
                    best = float("inf")
                    for _ in range(a.repeat):
                        t0 = time.perf_counter()
                        step()
                        best = min(best, time.perf_counter() - t0)
                    ms[order] = 1e3 * best
                m.order = "auto"
                macs, floats = m.multiply_adds(BATCH, nat), m.traffic(BATCH, nat)
                rows.append((macs, floats, ms))
                mark = "" if ms[auto] <= 1.1 * min(ms.values()) else "  (auto not the fastest)"
                print(f"{label:6s} {side}.{name:9s} {m.n_in:6d} -> {m.n_out:6d}, {c:3d} -> {o:3d} ch, K {m.K:3d}: "
                      + ", ".join(f"{k} {ms[k]:7.1f} ms ({macs[k] / 1e6:.0f} M mult-adds, {floats[k] / 1e6:.1f} M floats)"
                                  for k in ORDERS) + f"; auto: {auto}{mark}", flush=True)
    good = []
    for beta in (0, 1, 2, 4, 6, 8, 12, 16, 24, 32, 48, 64):
        ok = all(ms[min(ORDERS, key=lambda k: macs[k] + beta * floats[k])] <= 1.1 * min(ms.values())
                 for macs, floats, ms in rows)
        good.append(beta) if ok else None
    print(f"prices of a float (multiply-adds) that pick an order within 10 % of the fastest on every layer: "
          f"{good or 'none'}")


if __name__ == "__main__":
    main()
