"""How much an autoencoder's decoder output depends on its code, layer by layer, at
initialisation and after training (issue 13: why FeaStNet stayed at the mean shape).

    python benchmarks/decoder_signal.py RUN [RUN ...] [--codes 16] [--seed 0]

Each RUN is a finished reconstruct run (or a grid member) whose first model is an ``ae``/``vae``.
For ``--codes`` codes z ~ N(0, I) the script records the output of each decoder layer (the fully
connected layer, each conv block after its activation, the output conv) and prints its *spread*: the standard deviation
across the codes, averaged over vertices and channels, divided by the mean absolute activation.
A spread near 0 means the layer's output is (almost) the same for every code: the code does not
reach it. Printed for the trained decoder and for a copy whose parameters are drawn afresh (each
module's own ``reset_parameters``, seeded), with the gradient norm of the L1 loss against
unit-normal targets (the scale of Euclidean Std. targets) on the fully connected layer and on the
output conv at initialisation: how much of the training signal reaches the code's first layer.
"""
from __future__ import annotations

import argparse
import copy

import torch

from fwk.lifecycle import open_run


def layers(dec):
    """(name, module) of the decoder's first (fully connected) and output layers."""
    out = [("fc", dec.fc)] if getattr(dec, "fc", None) is not None else []
    return out + [("out", dec.out)]


def spreads(dec, z) -> dict:
    """{layer: spread} of the decoder's layers for the codes z (b, latent): the fully connected
    layer, each conv block (read at its activation, which every conv path calls, fused pooling
    included) and the output conv."""
    acts, hooks = {}, []
    for name, mod in layers(dec):
        hooks.append(mod.register_forward_hook(lambda m, i, o, name=name: acts.__setitem__(name, o.detach())))
    blocks = []
    if isinstance(getattr(dec, "act", None), torch.nn.Module):  # decoders of strided convs have none: fc and out only
        hooks.append(dec.act.register_forward_hook(lambda m, i, o: blocks.append(o.detach())))
    try:
        with torch.no_grad():
            dec(z)
    finally:
        for h in hooks:
            h.remove()
    order = ([("fc", acts["fc"])] if "fc" in acts else []) + [(f"conv{i}", a) for i, a in enumerate(blocks)]
    order.append(("out", acts["out"]))
    return {k: (a.std(0).mean() / a.abs().mean().clamp_min(1e-30)).item() for k, a in order}


def redrawn(dec, seed: int):
    """A copy of the decoder with every module's parameters drawn afresh (seeded), children before
    their parents: a module's own ``reset_parameters`` has the last word over its children's (the
    feast conv re-draws its ``FeaStConv`` and then applies its ``init`` scaling, which a reset of
    the ``FeaStConv`` afterwards would undo)."""
    fresh = copy.deepcopy(dec)
    torch.manual_seed(seed)

    def reset(mod):
        for child in mod.children():
            reset(child)
        if mod is not fresh and hasattr(mod, "reset_parameters"):
            mod.reset_parameters()

    reset(fresh)
    return fresh


def grad_norms(dec, z, seed: int) -> tuple[float, float]:
    """|dL/dW| of the first and the last layer for L = mean |dec(z) - T|, T ~ N(0, 1)."""
    named = layers(dec)
    dec.zero_grad()
    G = dec(z)
    T = torch.randn(G.shape, generator=torch.Generator().manual_seed(seed))
    (G - T).abs().mean().backward()

    def norm(mod):
        g = [p.grad.norm() ** 2 for p in mod.parameters() if p.grad is not None and p.dim() > 1]
        return float(sum(g) ** 0.5) if g else float("nan")
    return norm(named[0][1]), norm(named[-1][1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--codes", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    for r in a.runs:
        run = open_run(r)
        label = next(iter(run.specs))
        model = run.model(label)
        dec = model.net.dec
        z = torch.randn(a.codes, model.latent_size, generator=torch.Generator().manual_seed(a.seed))
        fresh = redrawn(dec, a.seed)
        trained, init = spreads(dec, z), spreads(fresh, z)
        g_first, g_last = grad_norms(fresh, z, a.seed)
        with torch.no_grad():
            absolute = [d(z).std(0).mean().item() for d in (fresh, dec)]
        print(f"\n{r} ({label}, conv {model.conv.name}, representation {model.rep.name})")
        print("| layer | spread at init | spread trained |\n| --- | --- | --- |")
        for k in init:
            print(f"| {k} | {init[k]:.2e} | {trained[k]:.2e} |")
        print(f"output spread in the representation's units (std across codes): {absolute[0]:.2e} at init, "
              f"{absolute[1]:.2e} trained")
        print(f"gradient norm at init: first layer {g_first:.2e}, output layer {g_last:.2e} "
              f"(ratio {g_first / g_last:.2e})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
