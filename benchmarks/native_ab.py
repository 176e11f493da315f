"""A training step on two builds of vcconv's native kernels, alternating in one process: the code at
a git revision against the working tree's, the same network, input, threads and heap.

    OMP_NUM_THREADS=2 python benchmarks/native_ab.py REV [--rounds 40] [--network ch5|thesis]

Why one process: pairs of processes (one per version, one after the other) on this shared machine
moved a step by 10-30 % between runs, and a change of a few percent came out as 1.07x in 16 pairs
and as 1.01-1.04x when the same two builds alternated step by step here (session 24). Both builds
of ``plugins/convs/fwk_vcconv/native.cpp``, each with the shared header ``fwk_native.h`` of its own
revision, are compiled under names of their own (once per pair of texts, kept under
``TORCH_EXTENSIONS_DIR`` or torch's default root) and ``fwk_vcconv.native._load`` is pointed at one
or the other before each step; everything else (the Python side, the network, Adam,
``fwk.engine.memory``'s heap) is the working tree's and shared. The order within a round swaps
every round. Prints each build's median step, their ratio and in how many rounds the working tree's
was faster; the two builds' gradients are compared first (they must agree to 1e-4).

Only the C++ may differ between the two: a revision whose ``native.py`` calls its kernels with
other arguments cannot be timed this way (the call fails and says so).
"""
from __future__ import annotations

import argparse
import hashlib
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _ict import face_head  # noqa: E402
from fwk.engine.memory import retain_freed_memory  # noqa: E402
from fwk.native import HEADER_DIR  # noqa: E402
from training import BATCH, VCCONV_VAE, VCCONV_VAE_CH5, networks, stepper  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SOURCE = "plugins/convs/fwk_vcconv/native.cpp"
HEADER = "fwk_native.h"


def build(text: str, header: str):
    """The module compiled from one native.cpp's text with one ``fwk_native.h``'s (the shared header
    of fwk.native, put beside it), named after the hash of both."""
    from torch.utils.cpp_extension import _get_build_directory, load

    name = "fwk_vcconv_ab_" + hashlib.sha256((text + "\0" + header).encode()).hexdigest()[:12]
    folder = Path(tempfile.mkdtemp(prefix="fwk-ab-"))
    src = folder / f"{name}.cpp"
    src.write_text(text)
    (folder / HEADER).write_text(header)
    return load(name=name, sources=[str(src)], build_directory=_get_build_directory(name, False),
                extra_include_paths=[str(folder)], extra_cflags=["-O3", "-fopenmp", "-DFWK_NATIVE_H=ab"],
                extra_ldflags=["-fopenmp"], verbose=False)


def at_rev(rev: str, path: str) -> str:
    try:
        return subprocess.run(["git", "show", f"{rev}:{path}"], cwd=ROOT, check=True, capture_output=True,
                              text=True).stdout
    except subprocess.CalledProcessError as e:
        raise SystemExit(f"git show {rev}:{path}: {e.stderr.strip()}") from None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("rev", help="the git revision whose native.cpp is 'before'")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--network", choices=("ch5", "thesis"), default="ch5")
    a = ap.parse_args()
    before, before_h = at_rev(a.rev, SOURCE), at_rev(a.rev, (HEADER_DIR / HEADER).relative_to(ROOT).as_posix())
    import fwk_vcconv.native as native

    if not native.available():
        raise SystemExit(f"vcconv's native kernels are not built here: {native.failed()}")
    retain_freed_memory()
    libs = {"before": build(before, before_h),
            "after": build((ROOT / SOURCE).read_text(), (HEADER_DIR / HEADER).read_text())}
    torch.manual_seed(0)
    col, src = face_head(1)
    x = torch.randn(BATCH, col.template.n_vertices, 3)
    enc, dec, _ = networks(VCCONV_VAE_CH5 if a.network == "ch5" else VCCONV_VAE, col.template)
    grads = {}
    for k, lib in libs.items():  # the same gradients from both builds, before any step changes the weights
        native._load = lambda lib=lib: lib
        params = list(enc.parameters()) + list(dec.parameters())
        loss = (dec(enc(x)[0]) - x).abs().mean()
        grads[k] = torch.autograd.grad(loss, params)
    bad = [i for i, (g, h) in enumerate(zip(grads["before"], grads["after"])) if not torch.allclose(g, h, atol=1e-4)]
    if bad:
        raise SystemExit(f"the two builds' gradients differ (parameters {bad[:5]}): not the same computation")
    step = stepper(enc, dec, x)
    times = {"before": [], "after": []}
    for k, lib in libs.items():  # a warm-up step each
        native._load = lambda lib=lib: lib
        step()
    for r in range(a.rounds):
        for k in (("before", "after") if r % 2 == 0 else ("after", "before")):
            native._load = lambda lib=libs[k]: lib
            t0 = time.perf_counter()
            step()
            times[k].append(time.perf_counter() - t0)
    mb, ma = (statistics.median(times[k]) * 1e3 for k in ("before", "after"))
    wins = sum(b > t for b, t in zip(times["before"], times["after"]))
    print(f"{a.network} width, {src}, {torch.get_num_threads()} threads, {a.rounds} rounds: {a.rev} {mb:.1f} ms, "
          f"working tree {ma:.1f} ms a step ({mb / ma:.3f}x); the working tree faster in {wins} of {a.rounds}")


if __name__ == "__main__":
    main()
