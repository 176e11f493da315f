"""Training-step throughput of the thesis's networks, today's code against the code as it was
before issue 17's kernel work (``benchmarks/_before.py``, a frozen copy of commit 5b25de3's
convs and networks), side by side in one process.

    OMP_NUM_THREADS=2 python benchmarks/training.py [--steps 7] [--bf16] [--feast] [--all]
    OMP_NUM_THREADS=1 python benchmarks/training.py --cpu-time ...   # a loaded machine: CPU seconds
    OMP_NUM_THREADS=2 python benchmarks/training.py --profile spiralpp   # one step by operator

Networks (thesis 3.4 / appendix A), batch 16, on the ICT-FaceKit face-head region (11,248
vertices) when ICT-FaceKit is present, else a synthetic head of the same size (printed):

Today's rows run on the native kernels (``fwk_vcconv.native``, ``fwk_spiralpp.native``; issue 28);
the line below each ("torch code") times the same network on its conv's torch evaluation
(``FWK_VCCONV_NATIVE=0``, ``FWK_SPIRALPP_NATIVE=0``) in the same alternation; for the two vcconv
rows, "no tall" times the native kernels with the products with the basis on torch's product
instead of ``fwk_vcconv.native.tall_product``, and "no lanes" with the narrow ``basis`` and ``kernel``
layers on the BLAS kernels (the tall product and ``basis_product``, ``kernel_product``) instead of
``fwk_vcconv.native.basis_lanes`` and ``kernel_lanes``, the ``sum`` order's forward on its
per-vertex BLAS call instead of lanes (``sum_vertex_lanes``), and the tall products on BLAS calls per
row block (``tall_mm``) instead of ``tall_lanes``.

* ``vcconv VAE``: the fully convolutional VAE at the thesis's width (its Mesh Autoencoder and
  Deep Spectral Meshes' bands, issue 28's "thesis-width" network), channels [3, 32, 64, 128,
  128, 8], 8 latent vertices, weight_num 35, residual rate 0.5, ``simple`` sampler with 4 levels;
* ``vcconv ch5``: the same VAE at the chapter 5 study's and the ICT rig's width, channels
  [3, 8, 16, 32, 32, 2] (``recipes/thesis/ch5/base.yaml``), today's code only;
* ``main job PB``: the main job's PB network (spiral++ VAE [3, 8, 16, 32], latent 16, ``quadric``
  factors [4, 4, 4]), at this template's size, today's code only;
* ``spiral++ AE``: channels [3, 16, 32, 64, 128], latent 64, ``quadric`` sampler, factors
  [4, 4, 4, 4], spirals of length 9 (today: each pooling fused into its conv, spiral++ playing
  ``fwk.protocols.FusedPoolingConv``).

A step is forward, L1 loss, backward and an Adam step (fused, as ``fwk.engine.trainer`` trains;
the frozen code's with torch's per-parameter Adam, as it trained). The versions alternate step by step after
one warm-up step each; the table gives the median step time of each, their ratio, the GFLOP per
step (3x the dense products of one forward pass, counted by ``torch.utils.flop_counter``;
sparse products left out, see ``gflop``) and the achieved rate against an fp32 matmul (2048^3)
with the same threads, timed as one more member of the row's alternation (its median; the last
column): on this shared machine a matmul timed once at the start moved 131-186 GFLOP/s between
runs minutes apart, and a row's fraction with it (the chapter 5 width 26 % and 37 % in two runs,
2026-12-07); timed beside the steps it sees the load they see. Like ``fwk.engine.trainer``, the script keeps
freed memory in the heap (``fwk.engine.memory``) unless ``--default-malloc``: that is a process-wide
setting, so the two are compared in two runs.

``--bf16`` also times today's code (every row) under CPU autocast (bfloat16, what ``train.precision:
bf16-mixed`` gives Lightning) and, for the first two rows, trains both precisions for a few steps from the same
initialisation to report the per-step loss deviation. ``--feast`` adds the FeaStNet AE (the
spiral++ AE's layout with conv ``feast``, 8 heads: the thesis's FeaStNet), torch_geometric's
``FeaStConv.forward`` (per-edge messages; ``order: edges``, the model pooling after each conv) as
"before" against today's reordered sums (``order: auto``, pooling fused), from the same seeded
initialisation (their first losses printed). ``--all`` adds the step time of the spiral, feast and lsa AEs (today's code). Threads: torch's
default (``OMP_NUM_THREADS``); the machine's load average is printed with the figures.

The last line is one JSON object with every figure.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import sys
from pathlib import Path
from unittest import mock

import torch
from torch.utils.flop_counter import FlopCounterMode

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _before  # noqa: E402
from _ict import alternate, face_head  # noqa: E402
from fwk.engine.losses import l1_mean  # noqa: E402
from fwk.engine.memory import retain_freed_memory  # noqa: E402
from fwk.plugins import get_registry  # noqa: E402
from fwk.recipes import make_spec  # noqa: E402

BATCH = 16
VCCONV_VAE = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 35}, "channels": [32, 64, 128, 128, 8],
              "latent_vertices": 8, "sampler": {"name": "simple", "levels": 4}, "residual_rate": 0.5}
SPIRALPP_AE = {"name": "ae", "conv": {"name": "spiral++", "length": 9}, "channels": [16, 32, 64, 128],
               "latent": 64, "sampler": {"name": "quadric", "factors": [4, 4, 4, 4]}}
FEAST_AE = {**SPIRALPP_AE, "conv": {"name": "feast", "heads": 8}}
#: the chapter 5 study's and the ICT rig's network (recipes/thesis/ch5/base.yaml): 1/16 of the thesis's width
VCCONV_VAE_CH5 = {**VCCONV_VAE, "channels": [8, 16, 32, 32, 2], "sampler": {"name": "simple", "levels": 4,
                                                                           "stride": 2, "radius": 2}}
#: the main job's PB network (recipes/pbs_face_compression.yaml's two networks), timed at this template's size
MAIN_JOB_PB = {"name": "vae", "conv": {"name": "spiral++", "length": 9}, "channels": [8, 16, 32], "latent": 16,
               "sampler": {"name": "quadric", "factors": [4, 4, 4]}}
OTHER_CONVS = {"spiral": {"name": "spiral"}, "feast": {"name": "feast", "heads": 8}, "lsa": {"name": "lsa"}}


def networks(spec, template):
    """Today's (encoder, decoder) of a model spec, and its hierarchy."""
    m = make_spec("model", spec, "model", get_registry()).build()
    enc, dec = m.build_encoder(template, 3), m.build_decoder(template, 3)
    return enc, dec, m.hierarchy


def stepper(enc, dec, x, bf16=False, fused=True):
    """One training step (forward ``dec(enc(x)[0])``, L1, backward, Adam) as a closure returning the loss.

    The L1 loss is the trainers' (``fwk.engine.l1_mean``: one native pass each way where it applies,
    ``torch.abs(a - b).mean()`` under autocast and elsewhere), for every version of a row alike.
    ``fused``: Adam as fwk trains with it (``fwk.engine.trainer.make_optimizer``: one fused kernel
    over every parameter); False: torch's default per-parameter Adam, as the code before issue 17
    (``_before``) trained."""
    opt = torch.optim.Adam(list(enc.parameters()) + list(dec.parameters()), 1e-3, fused=fused)

    def step():
        opt.zero_grad(set_to_none=True)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss = l1_mean(dec(enc(x)[0]).float(), x)
        loss.backward()
        opt.step()
        return loss.item()

    return step


class DenseFlopCounter(FlopCounterMode):
    """torch's counter, counting dense products only: torch's formulas take every operand as
    dense, so a sparse product (spiral++'s up-sampling ``S @ Z``, S CSR (11,248 x 25,308) with
    about 300,000 non-zeros) would count 146 GFLOP instead of its 0.16 (overrides the counter's
    ``_count_flops``, a private method of torch.utils.flop_counter)."""

    def _count_flops(self, func_packet, out, args, kwargs):
        from torch.utils._pytree import tree_leaves

        if any(isinstance(a, torch.Tensor) and a.layout != torch.strided for a in tree_leaves((args, kwargs))):
            return out
        return super()._count_flops(func_packet, out, args, kwargs)


def gflop(enc, dec, x) -> float:
    """Estimated GFLOP of one training step: 3 x the dense matrix products of a forward pass
    (forward, and the two gradients of each product), counted by torch. Sparse products (the
    pooling, spiral++'s up-sampling) are left out (``DenseFlopCounter``; their real cost is
    negligible)."""
    sparse = {f"{type(net).__name__}.{name}" for net in (enc, dec) for name, mod in net.named_modules()
              if name and not any(True for _ in mod.parameters())}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the counter sees this thread only (spiral++ deals chunks to worker threads)
    try:
        with torch.no_grad(), DenseFlopCounter(display=False) as fc:
            dec(enc(x)[0])
    finally:
        torch.set_num_threads(threads)
    counts = fc.get_flop_counts()
    fwd = sum(counts["Global"].values()) - sum(sum(counts.get(k, {}).values()) for k in sparse)
    return 3 * fwd / 1e9


MATMUL_N = 2048
MATMUL_GFLOP = 2 * MATMUL_N ** 3 / 1e9


def matmul_step():
    """One fp32 MATMUL_N^3 matmul as a closure: a member of each row's alternation, so that the row's
    fraction of the matmul rate takes the rate measured beside its steps, under the same load."""
    a, b = torch.randn(MATMUL_N, MATMUL_N), torch.randn(MATMUL_N, MATMUL_N)
    return lambda: a @ b


def alternate_with_matmul(steps: dict, n: int, cpu: bool = False) -> tuple[dict, float]:
    """``alternate`` over the steps and one more member, a matmul (``matmul_step``): the median seconds
    of each step, and the fp32 GFLOP/s of the matmul timed among them."""
    ts = alternate({**steps, "matmul": matmul_step()}, n, cpu)
    return ts, MATMUL_GFLOP / ts["matmul"]


def matmul_rate(repeat: int = 7, cpu: bool = False) -> float:
    """fp32 GFLOP/s of a 2048 x 2048 x 2048 matmul (median), with torch's current threads; ``cpu``:
    per CPU second (as ``--cpu-time`` times the steps)."""
    return alternate_with_matmul({}, repeat, cpu)[1]


def loss_deviation(enc, dec, x, n: int = 8) -> list[float]:
    """Relative |loss_bf16 - loss_fp32| / loss_fp32 at each of n steps from the same initialisation."""
    e2, d2 = copy.deepcopy(enc), copy.deepcopy(dec)
    f32, b16 = stepper(enc, dec, x), stepper(e2, d2, x, bf16=True)
    out = []
    for _ in range(n):
        a, b = f32(), b16()
        out.append(abs(b - a) / a)
    return out


#: the variables that turn the native kernels off (fwk.native): vcconv's and spiral++'s
NATIVE_OFF = {"FWK_VCCONV_NATIVE": "0", "FWK_SPIRALPP_NATIVE": "0"}


def without_native(step):
    """The step on the convs' torch code (``NATIVE_OFF`` while it runs), for a side-by-side
    timing against the native kernels (``fwk_vcconv.native``, ``fwk_spiralpp.native``) in one process."""
    def run():
        with mock.patch.dict(os.environ, NATIVE_OFF):
            return step()

    return run


def add_torch_code(steps: dict, enc, dec, x) -> float:
    """Adds a copy of a network on its conv's torch code to ``steps`` (key ``after_torch``);
    returns that code's GFLOP a step (vcconv's: its padded products)."""
    steps["after_torch"] = without_native(stepper(copy.deepcopy(enc), copy.deepcopy(dec), x))
    return without_native(lambda: gflop(enc, dec, x))()


def native_line(r: dict, ts: dict, g_torch: float, rate: float) -> None:
    """Adds the torch code's figures to a row and prints them."""
    r.update({"torch_code_ms": 1e3 * ts["after_torch"], "native_speedup": ts["after_torch"] / ts["after"],
              "gflop_torch_code": g_torch, "of_matmul_torch_code": g_torch / ts["after_torch"] / rate})
    print(f"{'  torch code':<13} {'':>10} {r['torch_code_ms']:>9.0f} {'':>6} {'':>13} {g_torch:>12.1f} "
          f"{g_torch / ts['after_torch']:>14.1f} {100 * r['of_matmul_torch_code']:>9.0f}%   (native kernels off: "
          f"the native kernels are {r['native_speedup']:.2f}x faster)")


def patched(step, target, name, value):
    """The step with ``target.name`` set to ``value`` while it runs, for a side-by-side timing of one
    kernel alone: ``fwk_vcconv.native.TALL_MAX_B = 0`` puts vcconv's products with the basis on torch's
    product ("no tall"), ``fwk_vcconv.native.lanes`` answering False takes its layers out of lanes
    ("no lanes")."""

    def run():
        with mock.patch.object(target, name, value):
            return step()

    return run


def add_variants(steps, enc, dec, x) -> None:
    """The vcconv rows' "no tall" and "no lanes" steps (``patched``), on copies of the network."""
    from fwk_vcconv import native as vcconv_native

    steps["after_no_tall"] = patched(stepper(copy.deepcopy(enc), copy.deepcopy(dec), x), vcconv_native, "TALL_MAX_B", 0)
    steps["after_no_lanes"] = patched(stepper(copy.deepcopy(enc), copy.deepcopy(dec), x), vcconv_native, "lanes",
                                      lambda M=1: False)


def variant_lines(r: dict, ts: dict) -> None:
    """Adds the steps without ``tall_product`` and without lanes to a vcconv row and prints them."""
    r.update({"no_tall_ms": 1e3 * ts["after_no_tall"], "tall_speedup": ts["after_no_tall"] / ts["after"],
              "no_lanes_ms": 1e3 * ts["after_no_lanes"], "lanes_speedup": ts["after_no_lanes"] / ts["after"]})
    print(f"{'  no tall':<13} {'':>10} {r['no_tall_ms']:>9.0f}   (the basis products on torch's: tall_product is "
          f"{r['tall_speedup']:.2f}x faster)")
    print(f"{'  no lanes':<13} {'':>10} {r['no_lanes_ms']:>9.0f}   (the lane kernels off, BLAS per vertex: "
          f"basis_lanes, kernel_lanes, sum and tall in lanes are {r['lanes_speedup']:.2f}x faster)")


def load_average() -> float:
    return os.getloadavg()[0]


def feast_row(t, x, n, cpu: bool = False) -> dict:
    """The FeaStNet AE, FeaStConv's per-edge forward (``order: edges``) against today's reordered
    sums, from the same seeded initialisation, alternating; prints its table row and returns it."""
    torch.manual_seed(0)
    enc, dec, _ = networks(FEAST_AE, t)
    torch.manual_seed(0)
    oenc, odec, _ = networks({**FEAST_AE, "conv": {**FEAST_AE["conv"], "order": "edges"}}, t)
    with torch.no_grad():
        l_new, l_old = ((d(e(x)[0]) - x).abs().mean().item() for e, d in ((enc, dec), (oenc, odec)))
    g_new, g_old = gflop(enc, dec, x), gflop(oenc, odec, x)
    ts, rate = alternate_with_matmul({"before": stepper(oenc, odec, x), "after": stepper(enc, dec, x)}, n, cpu)
    r = {"before_ms": 1e3 * ts["before"], "after_ms": 1e3 * ts["after"], "ratio": ts["before"] / ts["after"],
         "gflop_before": g_old, "gflop_after": g_new, "gflops_before": g_old / ts["before"],
         "gflops_after": g_new / ts["after"], "matmul_gflops": rate, "of_matmul": g_new / ts["after"] / rate,
         "first_loss_before": l_old, "first_loss_after": l_new}
    print(f"{'feast AE':<13} {r['before_ms']:>10.0f} {r['after_ms']:>9.0f} {r['ratio']:>6.2f} {g_old:>13.1f} "
          f"{g_new:>12.1f} {r['gflops_after']:>14.1f} {100 * r['of_matmul']:>9.0f}% {rate:>7.0f}")
    print(f"{'':<13} before = torch_geometric FeaStConv.forward; first loss before / after: {l_old:.6f} / {l_new:.6f}")
    return r


PROFILED = {"vcconv": VCCONV_VAE, "spiralpp": SPIRALPP_AE, "vcconv-ch5": VCCONV_VAE_CH5, "main-job-pb": MAIN_JOB_PB}


def profile_step(spec, rows: int = 25) -> None:
    """Print where a training step of today's network spends its time: torch.profiler's operators by
    self CPU time over 3 steps after 2 warm-ups (the main thread's; spiral++'s chunks run partly in
    worker threads, ``fwk.parallel.in_workers``, which the table may not count)."""
    from torch.profiler import ProfilerActivity, profile

    torch.manual_seed(0)
    col, src = face_head(1)
    x = torch.randn(BATCH, col.template.n_vertices, 3)
    enc, dec, _ = networks(spec, col.template)
    step = stepper(enc, dec, x)
    for _ in range(2):
        step()
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(3):
            step()
    print(f"template: {src}; {torch.get_num_threads()} threads; 3 steps")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows, max_name_column_width=40))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--steps", type=int, default=7, help="timed steps per version (after one warm-up)")
    ap.add_argument("--bf16", action="store_true", help="also time bf16 autocast and its loss deviation")
    ap.add_argument("--all", action="store_true", help="also time every other conv's AE (today's code)")
    ap.add_argument("--cpu-time", action="store_true",
                    help="time CPU seconds, not wall seconds (one thread only: a loaded machine's waits left out)")
    ap.add_argument("--feast", action="store_true",
                    help="also time the FeaStNet AE: torch_geometric's FeaStConv forward against today's")
    ap.add_argument("--default-malloc", action="store_true",
                    help="glibc's default thresholds instead of fwk.engine.memory's (which fwk's training sets)")
    ap.add_argument("--profile", choices=sorted(PROFILED),
                    help="instead: one network's step by operator (torch.profiler, 3 steps after 2 warm-ups)")
    a = ap.parse_args()
    malloc = "glibc defaults (--default-malloc)" if a.default_malloc else retain_freed_memory()
    if a.profile:
        return profile_step(PROFILED[a.profile])
    if a.cpu_time and torch.get_num_threads() != 1:
        raise SystemExit(f"--cpu-time needs one thread (OMP_NUM_THREADS=1): with {torch.get_num_threads()} the "
                         "process's CPU seconds are not a step's time")
    torch.manual_seed(0)
    col, src = face_head(1)
    t = col.template
    threads = torch.get_num_threads()
    x = torch.randn(BATCH, t.n_vertices, 3)
    load0 = load_average()
    rate = matmul_rate(cpu=a.cpu_time)
    print(f"template: {src}, {t.n_vertices} vertices; batch {BATCH}; torch {torch.__version__}, {threads} threads; "
          f"fp32 matmul 2048^3 at the start: {rate:.0f} GFLOP/s (each row's fraction takes the matmul timed in its own "
          f"alternation: its last column); load average {load0:.2f}; freed memory kept "
          f"(fwk.engine.memory): {malloc}"
          + ("; step times in CPU seconds (--cpu-time)" if a.cpu_time else ""))
    result = {"template": src, "n_vertices": t.n_vertices, "batch": BATCH, "threads": threads, "cpu_time": a.cpu_time,
              "matmul_gflops": rate, "torch": torch.__version__, "malloc": malloc}
    print(f"{'network':<13} {'before ms':>10} {'after ms':>9} {'ratio':>6} {'GFLOP before':>13} {'GFLOP after':>12} "
          f"{'GFLOP/s after':>14} {'of matmul':>10} {'matmul':>7}")
    for label, key, spec in (("vcconv VAE", "vcconv_vae", VCCONV_VAE), ("spiral++ AE", "spiralpp_ae", SPIRALPP_AE)):
        torch.manual_seed(0)
        enc, dec, h = networks(spec, t)
        if key == "vcconv_vae":
            oenc, odec = _before.vcconv_vae(h, 3, spec["channels"], weight_num=35, residual_rate=0.5)
        else:
            oenc, odec = _before.spiralpp_ae(h, 3, spec["channels"], spec["latent"], length=9)
        g_new, g_old = gflop(enc, dec, x), gflop(oenc, odec, x)
        steps = {"before": stepper(oenc, odec, x, fused=False), "after": stepper(enc, dec, x)}
        g_torch = add_torch_code(steps, enc, dec, x)
        if key == "vcconv_vae":
            add_variants(steps, enc, dec, x)
        if a.bf16:
            e16, d16 = copy.deepcopy(enc), copy.deepcopy(dec)
            steps["after_bf16"] = stepper(e16, d16, x, bf16=True)
        ts, rate = alternate_with_matmul(steps, a.steps, a.cpu_time)
        r = {"before_ms": 1e3 * ts["before"], "after_ms": 1e3 * ts["after"], "ratio": ts["before"] / ts["after"],
             "gflop_before": g_old, "gflop_after": g_new, "gflops_before": g_old / ts["before"],
             "gflops_after": g_new / ts["after"], "matmul_gflops": rate, "of_matmul": g_new / ts["after"] / rate}
        print(f"{label:<13} {r['before_ms']:>10.0f} {r['after_ms']:>9.0f} {r['ratio']:>6.2f} {g_old:>13.1f} "
              f"{g_new:>12.1f} {r['gflops_after']:>14.1f} {100 * r['of_matmul']:>9.0f}% {rate:>7.0f}")
        native_line(r, ts, g_torch, rate)
        if key == "vcconv_vae":
            variant_lines(r, ts)
        if a.bf16:
            dev = loss_deviation(enc, dec, x)
            r.update({"after_bf16_ms": 1e3 * ts["after_bf16"], "bf16_speedup": ts["after"] / ts["after_bf16"],
                      "bf16_loss_rel_dev": dev})
            print(f"{'  bf16':<13} {'':>10} {r['after_bf16_ms']:>9.0f} {r['bf16_speedup']:>6.2f}x over fp32; "
                  f"per-step loss deviation (relative) max {max(dev):.2e}, "
                  f"steps {', '.join(f'{d:.1e}' for d in dev)}")
        result[key] = r
    # the width the chapter 5 study and the rig train, and the main job's network: today's code only
    for label, key, spec, what in (("vcconv ch5", "vcconv_vae_ch5", VCCONV_VAE_CH5,
                                    "channels [8, 16, 32, 32, 2]: the chapter 5 study's and the rig's"),
                                   ("main job PB", "main_job_pb", MAIN_JOB_PB,
                                    "spiral++ VAE [8, 16, 32]: recipes/pbs_face_compression.yaml's")):
        torch.manual_seed(0)
        enc, dec, _ = networks(spec, t)
        g = gflop(enc, dec, x)
        steps = {"after": stepper(enc, dec, x)}
        g_torch = add_torch_code(steps, enc, dec, x)
        if key == "vcconv_vae_ch5":
            add_variants(steps, enc, dec, x)
        if a.bf16:
            steps["after_bf16"] = stepper(copy.deepcopy(enc), copy.deepcopy(dec), x, bf16=True)
        ts, rate = alternate_with_matmul(steps, a.steps, a.cpu_time)
        r = {"after_ms": 1e3 * ts["after"], "gflop_after": g, "gflops_after": g / ts["after"], "matmul_gflops": rate,
             "of_matmul": g / ts["after"] / rate}
        print(f"{label:<13} {'':>10} {r['after_ms']:>9.0f} {'':>6} {'':>13} {g:>12.1f} {r['gflops_after']:>14.1f} "
              f"{100 * r['of_matmul']:>9.0f}% {rate:>7.0f}   ({what})")
        native_line(r, ts, g_torch, rate)
        if key == "vcconv_vae_ch5":
            variant_lines(r, ts)
        if a.bf16:
            r.update({"after_bf16_ms": 1e3 * ts["after_bf16"], "bf16_speedup": ts["after"] / ts["after_bf16"]})
            print(f"{'  bf16':<13} {'':>10} {r['after_bf16_ms']:>9.0f} {r['bf16_speedup']:>6.2f}x over fp32")
        result[key] = r
    if a.feast:
        result["feast_ae"] = feast_row(t, x, a.steps, a.cpu_time)
    if a.all:
        result["others"] = {}
        for name, conv in OTHER_CONVS.items():
            enc, dec, _ = networks({**SPIRALPP_AE, "conv": conv}, t)
            ms = 1e3 * alternate({"s": stepper(enc, dec, x)}, max(2, a.steps // 2), a.cpu_time)["s"]
            result["others"][name] = {"step_ms": ms}
            print(f"{name + ' AE':<13} {'':>10} {ms:>9.0f}")
    result["load_average"] = [load0, load_average()]
    print(f"load average at start / end: {load0:.2f} / {load_average():.2f}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
