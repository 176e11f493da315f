"""Task ``spectral-study``: the mass matrix in spectral partitioning (thesis 4.3, figs 4.2-4.5).

For every k in ``ks``, each mesh P (n vertices, ``n_meshes`` meshes of one shape) is low-pass
filtered two ways on the template (the mean of the meshes):

* without the mass matrix (eqs. 4.1, 4.3): L U = U Lambda, P_(k) = U_k U_k^T P;
* with it (eqs. 4.2, 4.4): L U = M U Lambda, P_(k) = U_k U_k^T M P;

and the L1 error per vertex ||p_j(k) - p_j||_1 (sum over coordinates) gives

    E_ave(k) = mean over meshes of the mean over vertices      (eqs. 4.6, 4.7)
    E_max(k) = mean over meshes of the max over vertices       (eqs. 4.8, 4.9)

with the CPU time per mesh of each projection (fig. 4.3). The thesis's claim (fig. 4.5): for a
given E_ave, E_max is lower with the mass matrix, i.e. the error is spread more evenly over a
mesh whose tessellation is finer on the face than on scalp and neck. The report checks it by
interpolating each curve's log E_max at the other curve's E_ave values (within the common
range) and says, with the numbers, whether it holds. Meshes are preprocessed as every fwk run
(centred, registered, scaled into [-1, 1]); errors are also reported in the dataset's units.
"""
from __future__ import annotations

import time
from typing import Annotated

import numpy as np

from fwk.data.preprocess import PreprocessConfig, Preprocessor
from fwk.errors import RecipeError
from fwk.evaluation.plots import line_plot
from fwk.evaluation.report import markdown_table, write_report
from fwk.geometry.operators import mass_matrix
from fwk.geometry.spectral import SpectralProjector, eigenbasis
from fwk.hookspecs import hookimpl
from fwk.recipes import Kind, Spec

THESIS_KS = [50, 100, 150, 200, 250, 300, 350, 400, 500, 600, 700, 900, 1000, 1200, 1500, 1700, 2000]


class SpectralStudy:
    """Spectral low-pass error with and without the mass matrix against k (thesis 4.3)."""

    name = "spectral-study"

    def __init__(self, dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads", ks: list[int] | None = None,
                 shape: str = "neutral", n_meshes: int | None = None, preprocess: PreprocessConfig | None = None):
        self.dataset, self.shape, self.n_meshes = dataset, shape, n_meshes
        self.ks = sorted(set(ks or THESIS_KS))
        if self.ks[0] <= 0:
            raise RecipeError(f"ks: values must be positive, got {self.ks}")
        self.preprocess = preprocess or PreprocessConfig()

    def run(self, ctx):
        """Filter the meshes at every k with and without M; the report, its figures and the verdict."""
        col = self.dataset.build().load(ctx.cache)
        P = np.asarray(col.shape(self.shape), dtype=np.float64)
        if self.n_meshes:
            P = P[: self.n_meshes]
        pre = Preprocessor(self.preprocess).fit(P)
        X, _ = pre.transform_neutrals(P)
        t = col.template
        n = t.n_vertices
        ks = [k for k in self.ks if k < n - 2]
        if len(ks) < len(self.ks):
            ctx.log(f"ks above n - 2 = {n - 2} dropped: {[k for k in self.ks if k >= n - 2]}")
        mean = X.mean(0)
        res = {}
        for label, weighted in (("without M (4.3)", False), ("with M (4.4)", True)):
            t0 = time.perf_counter()
            _, U = eigenbasis(mean, t.triangles, max(ks), weighted=weighted, cache=ctx.cache)
            eig_s = time.perf_counter() - t0
            proj = SpectralProjector(U, mass_matrix(mean, t.triangles).diagonal() if weighted else None)
            e_ave, e_max, ms = [], [], []
            for k in ctx.progress(ks, desc=label):
                t0 = time.perf_counter()
                low = proj.project(X, 0, k)
                ms.append(1000 * (time.perf_counter() - t0) / len(X))
                err = np.abs(low - X).sum(-1)  # (m, n): L1 of each vertex
                e_ave.append(float(err.mean(1).mean()))
                e_max.append(float(err.max(1).mean()))
            res[label] = {"k": ks, "E_ave": e_ave, "E_max": e_max, "ms_per_mesh": ms, "eigenbasis_s": eig_s}
            ctx.log(f"{label}: basis {eig_s:.1f} s; E_ave(k={ks[-1]}) {e_ave[-1]:.3g}")
        a, b = res["without M (4.3)"], res["with M (4.4)"]
        verdict, comparisons = self._compare(a, b)
        # the figures in the dataset's units (the errors are per-vertex L1 distances: evaluation space / scale)
        f, u = 1.0 / float(pre.scale), t.units or "input units"

        def cm(v):
            return [x * f for x in v]

        kx = "k (eigenvectors kept)"
        ea, em = f"E_ave, mean per-vertex L1 error ({u})", f"E_max, max per-vertex L1 error ({u})"
        figs = {
            "E_ave against k (fig. 4.2)": line_plot({k: (v["k"], cm(v["E_ave"])) for k, v in res.items()},
                                                    ctx.path("figures", "e_ave_k.png"), kx, ea, logy=True),
            "CPU time per mesh against k (fig. 4.3)": line_plot({k: (v["k"], v["ms_per_mesh"]) for k, v in res.items()},
                                                                ctx.path("figures", "time_k.png"), kx,
                                                                "CPU time per mesh (ms)"),
            "E_max against k (fig. 4.4)": line_plot({k: (v["k"], cm(v["E_max"])) for k, v in res.items()},
                                                    ctx.path("figures", "e_max_k.png"), kx, em, logy=True),
            "E_max against E_ave (fig. 4.5)": line_plot({k: (cm(v["E_ave"]), cm(v["E_max"])) for k, v in res.items()},
                                                        ctx.path("figures", "e_max_e_ave.png"), ea, em, logy=True),
        }
        rows = [[k, f"{a['E_ave'][i]:.4g}", f"{b['E_ave'][i]:.4g}", f"{a['E_max'][i]:.4g}", f"{b['E_max'][i]:.4g}",
                 f"{a['ms_per_mesh'][i]:.3g}", f"{b['ms_per_mesh'][i]:.3g}"] for i, k in enumerate(ks)]
        table = markdown_table(rows, ["k", "E_ave without M", "E_ave with M", "E_max without M", "E_max with M",
                                      "ms/mesh without M", "ms/mesh with M"])
        scale = pre.scale
        results = {"study": res, "claim": {"holds": verdict, "comparisons": comparisons},
                   "dataset": {"name": self.dataset.name, "n_vertices": n, "meshes": len(X), "units": t.units,
                               "scale": scale}}
        text = (f"Errors in the evaluation space (multiply by {1 / scale:.4g} for {t.units}).\n\n{table}\n\n"
                f"**Claim (thesis fig. 4.5): at equal E_ave, E_max is lower with the mass matrix.** {verdict}")
        write_report(ctx, f"Spectral study: {self.dataset.name}, {len(X)} meshes, {n} vertices", results, figs,
                     sections=[("E_ave, E_max and CPU time against k", text)])

    @staticmethod
    def _compare(a, b):
        """Compare log E_max of the two curves at matching E_ave (interpolated, common range)."""
        xa, ya = np.log(a["E_ave"]), np.log(a["E_max"])
        xb, yb = np.log(b["E_ave"]), np.log(b["E_max"])
        lo, hi = max(xa.min(), xb.min()), min(xa.max(), xb.max())
        if lo >= hi:
            return "The two curves share no range of E_ave: no comparison at equal E_ave is possible.", []
        oa, ob = np.argsort(xa), np.argsort(xb)
        grid = np.linspace(lo, hi, 25)
        ma = np.interp(grid, xa[oa], ya[oa])
        mb = np.interp(grid, xb[ob], yb[ob])
        lower = mb < ma
        comps = [{"E_ave": float(np.exp(g)), "E_max_without_M": float(np.exp(u)), "E_max_with_M": float(np.exp(v))}
                 for g, u, v in zip(grid, ma, mb)]
        share = lower.mean()
        ratio = float(np.exp(np.median(ma - mb)))
        if share == 1.0:
            verdict = (f"Holds here: at every compared E_ave, E_max is lower with M (median ratio without/with "
                       f"{ratio:.3g}).")
        elif share == 0.0:
            verdict = f"Does not hold here: E_max is higher with M at every compared E_ave (median ratio {ratio:.3g})."
        else:
            verdict = (f"Holds at {100 * share:.0f}% of the compared E_ave values (median ratio without/with "
                       f"{ratio:.3g}); not everywhere.")
        return verdict, comps


@hookimpl
def fwk_register_tasks():
    return [SpectralStudy]
