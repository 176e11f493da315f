"""Usage: python benchmarks/dsm_init_response.py [ict|synthetic]

At initialisation: how much does each dsm decoder move for a unit edit of its own band's code
against an equal edit of the other band's code? (issue 17, item 2)

Builds dsm's networks exactly as dsm.fit does (reconstruction.yaml's band network, channels 3 (euclidean)
and 9 (dr)) on a template, draws them with seed 0, and for 16 random base codes Z ~ N(0, I) edits
each latent entry by +1 in turn; reports the RMS change of D_b's output features, averaged over
entries and base codes, for edits of Z_b and of the other band's code, and their ratio."""
import sys, time
import numpy as np, torch
from fwk.plugins import get_registry
from fwk.recipes import make_spec
from fwk.engine import seed_everything

REG = get_registry()
which = sys.argv[1] if len(sys.argv) > 1 else "ict"
if which == "ict":
    ds = REG.get("dataset", "ict-facekit")(n_subjects=2, region="face-head", shapes=["neutral"])
    col = ds.load(None)
    t = col.template
    net = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 35, "radius": 2},
           "sampler": {"name": "simple", "levels": 4, "stride": 2, "radius": 2},
           "channels": [32, 64, 128, 128, 4], "latent_vertices": 8, "residual_rate": 0.5}
else:
    col = REG.get("dataset", "synthetic-heads")(n_subjects=2, n_vertices=500, shapes=["neutral"]).load(None)
    t = col.template
    net = {"name": "vae", "conv": {"name": "vcconv", "weight_num": 8}, "sampler": {"name": "simple", "levels": 2},
           "channels": [8, 16, 4], "latent_vertices": 4, "residual_rate": 0.5}
m = make_spec("model", {"name": "dsm", "k": 500, "network": net}, "dsm", REG).build()
m.channels = [3, 9]
seed_everything(0)
t0 = time.time()
dsm = m._make_net(t)
dsm.eval()
print(f"template {t.n_vertices} vertices, |Z| = {m.latents}, built in {time.time()-t0:.1f} s")
lin = [(n, x.in_features, x.out_features) for d in dsm.decoders for n, x in d.named_modules() if isinstance(x, torch.nn.Linear)]
print("decoder Linear layers (name, in, out):", [l for l in lin if l[1] >= sum(m.latents)] or "none reading all of Z")
g = torch.Generator().manual_seed(1)
B = 16
zs = [torch.randn(B, d, generator=g) for d in m.latents]
res = np.zeros((2, 2))
with torch.no_grad():
    base = dsm.decode(zs)
    for j, d in enumerate(m.latents):       # edited band
        acc = np.zeros(2)
        for e in range(d):
            z2 = [z.clone() for z in zs]
            z2[j][:, e] += 1.0
            out = dsm.decode(z2)
            for b in range(2):
                acc[b] += float((out[b] - base[b]).square().mean(dim=(1, 2)).sqrt().mean())
        res[:, j] = acc / d
names = m.band_names
for b in range(2):
    o = 1 - b
    print(f"D_{names[b]}: RMS change for a unit edit of Z_{names[b]} {res[b, b]:.4f}, of Z_{names[o]} {res[b, o]:.4f}, "
          f"ratio {res[b, o] / res[b, b]:.3f}")
