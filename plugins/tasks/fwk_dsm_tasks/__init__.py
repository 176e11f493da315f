"""Tasks ``interpolate`` and ``edit``: what Deep Spectral Meshes is for (thesis 4.7.2, 4.7.3).

Where the models come from (both tasks):

* ``run: PATH`` names a finished ``reconstruct`` run (its ``models/<label>.safetensors``, ``split.json``
  and ``stats/preprocess.npz``; reopened with ``fwk.lifecycle.open_run``; the dataset is rebuilt
  from that run's recipe to get the topology with the user's polygons and UVs); of a run with
  ``seeds:`` the first seed's sub-run is used (the log says so), ``run: PATH/seed-S`` picks seed S;
* otherwise the task trains inline: the recipe's ``dataset``, ``split``, ``preprocess``,
  ``models``, ``metrics``, ``renders`` and ``train`` form a ``reconstruct`` recipe that runs as a
  sub-run in ``<run>/reconstruct/`` (its own report, metrics and saved models; a later recipe
  can point ``run:`` at it). ``fwk run --resume`` reuses a finished sub-run.

Models are chosen by role (``fwk.protocols``): the band models (``BandModel``: dsm) are edited
and interpolated (``dsm``: their labels, default every band model of the run); the comparison
models are the other generative models (``GenerativeModel``: vae, ae, mlp-vae, pca; ``compare``:
their labels).

``interpolate`` (4.7.2): two subjects of the test split (``subjects``) are encoded by each dsm
model, Z_1 = [Z_1l | Z_1h], Z_2 likewise, and decoded on a grid (eq. 4.16)

    Z_{alpha,beta} = [(1 - beta) Z_1l + beta Z_2l | (1 - alpha) Z_1h + alpha Z_2h]

(alpha: the high band, i.e. the last band; beta: every other band), next to plain vertex-space
interpolation P_delta = P_1 + delta (P_2 - P_1) (eq. 4.17) for delta in ``alphas``. One picture
per dsm model (rows beta, columns alpha, last row the vertex-space interpolation with the two
subjects); every mesh is saved as OBJ under ``interpolation/`` in the dataset's units with its
own polygons and UVs (the preprocessing's scale undone; the meshes sit in the registered frame of
the mean head).

``edit`` (4.7.3): for one test subject, latent entries (``directions``: indices within a
band's slice of Z) are moved by ``amounts`` (in units of the prior's standard deviation) in one
band at a time and decoded; the picture shows, per band, every dsm model's edits side by side
with the same edits of each single-band comparison model's latent (``compare``), each mesh
coloured by its displacement from the unedited decode.

Beyond the thesis, disentanglement, measured on up to ``max_subjects`` test subjects, every
direction and every non-zero amount. Notation: an edit of band j's entry d by a gives the output
change D = decode(Z + a e_{j,d}) - decode(Z) (n x 3); X_c is band c's spectral projector of the
band model (``split``: X_c D = split(D)[c] - split(0)[c]; the bands are M-orthogonal and sum to
D); M the Voronoi areas of the mean head; e_c(D) = ||X_c D||_M^2 = sum_i M_ii |(X_c D)_i|^2.

1. **Share of the M-weighted energy** (reported since the first version, ``shares``):
   share_c = e_c(D) / sum_c' e_c'(D), averaged over the edits; the band model's
   ``band_shares``. A single-band model's edits are measured with the same projectors.
   It is dominated by the bands' amplitudes: the low band carries most of a face's variation,
   so almost any change is "mostly low band" and a high-band edit scores low even when it
   touches nothing but the high band's (small) natural range.
2. **Normalised by the bands' training variance** (``normalised_shares``,
   ``variance_units``): with v_c = (1/N) sum_s e_c(P_s - P-bar) over the N training subjects of
   the run (P-bar their mean), epsilon_c(D) = e_c(D) / v_c is the edit's movement of band c in
   units of that band's typical variation (1: as far as a typical subject is from the mean in
   that band), and nu_c = epsilon_c / sum_c' epsilon_c' its share; both averaged over the
   edits. For a dsm edit of band b, nu_b is its disentanglement with each band on its own
   scale (1: the edit stays in its band).
3. **Cross-response of the decoders** (``cross_response``, dsm models only): decoder D_c's
   response to an edit of another band's code j against its response to an equal edit of its
   own code c,

       rho_{c<-j} = mean ||X_c D^{(j)}||_M / mean ||X_c D^{(c)}||_M,

   the means over the same subjects, entries d and amounts a (D^{(j)}: the output change of an
   edit of band j). Assembly (eq. 4.15) gives X_c D = X_c Delta P'_c: the band-c part of the
   output changes only through D_c, so this is D_c's own response as it reaches the mesh.
   rho = 0: D_c ignores Z_j (disentangled); rho = 1: it responds to Z_j as much as to Z_c
   (at initialisation, or with a dense layer over the whole Z, rho is about 1). Conditioning
   (gamma = 1) lets D_c read Z_j on purpose; a lower gamma should lower rho.

Reported in tables and in ``metrics.json`` (``disentanglement``: per dsm model and edited band
``shares``, ``own_share``, ``normalised_shares``, ``own_normalised_share``, ``variance_units``;
per dsm model ``band_variance`` and ``cross_response``; per comparison model ``shares``,
``normalised_shares``, ``variance_units``).

Each task can chain the other on the same models: ``interpolate: {...}`` inside an ``edit``
recipe (or ``edit: {...}`` inside ``interpolate``), so one run gives both pictures; the chained
settings are the other task's study settings (``InterpolateSettings``, ``EditSettings``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import yaml

from fwk.data.io import write_obj as write_mesh_obj
from fwk.data.preprocess import PreprocessConfig, Preprocessor, Transforms
from fwk.data.split import SplitConfig
from fwk.errors import DataError, FwkError, RecipeError
from fwk.evaluation import write_report
from fwk.evaluation.render import colour_limits, render_grid
from fwk.evaluation.report import markdown_table
from fwk.geometry.operators import mass_matrix
from fwk.hookspecs import hookimpl
from fwk.lifecycle import has_state, open_run
from fwk.protocols import RECONSTRUCT, BandModel, GenerativeModel
from fwk.recipes import Kind, Spec, resolve
from fwk.runs import RunContext, run_task
from fwk.safeio import load_json

INLINE_KEYS = ("dataset", "split", "preprocess", "shapes", "models", "metrics", "renders")
# the recipe key that lists the band models' labels, and the metrics.json key of their results
BAND_KEY = "dsm"  # name-ok: a recipe / metrics.json key (unchanged), not a lookup of the dsm model


# ---------------------------------------------------------------------------------------- models

class Env:
    """A trained reconstruct run reopened: models, template (user's polygons), preprocessing,
    the subjects of each split in the evaluation space, and the run's metrics."""

    def __init__(self, run_dir: Path, models: dict, template, pre: Preprocessor, splits: dict, metrics: dict):
        self.run_dir, self.models, self.template, self.pre = run_dir, models, template, pre
        self.splits, self.metrics = splits, metrics

    def to_input_units(self, X) -> np.ndarray:
        """Evaluation space -> the dataset's units in the mean head's frame (scale undone)."""
        X = np.asarray(X, dtype=np.float64)
        T = Transforms(np.broadcast_to(np.eye(3), (len(X), 3, 3)).copy(), np.zeros((len(X), 3)), self.pre.scale)
        return self.pre.inverse(X, T)

    def write_obj(self, path, X) -> Path:
        """Write one mesh (evaluation space) as OBJ in the dataset's units with its polygons and UVs."""
        return write_mesh_obj(path, self.to_input_units(np.asarray(X)[None])[0], self.template)


def load_models(run_dir, ctx=None, registry=None) -> Env:
    """Reopen a finished reconstruct run (``fwk.lifecycle.open_run``) with its trained models; of a
    run with ``seeds:``, its first seed's sub-run (logged), or the ``seed-<s>/`` given."""
    say = ctx.log if ctx is not None else None
    run = open_run(Path(run_dir), registry, task=RECONSTRUCT, say=say, choose="run: {run}/seed-S")
    run_dir = run.run_dir  # a seed's sub-run of a run with seeds
    for p in (run_dir / "split.json", run_dir / "stats" / "preprocess.npz"):
        if not p.exists():
            raise FwkError(f"run: {p} is missing; is {run_dir} a finished reconstruct run?")
    models = {label: run.model(label) for label in run.specs}
    pre = run.preprocessor
    cache = ctx.cache if ctx is not None else run.ctx.cache
    col = run.params["dataset"].build().load(cache)
    split = load_json(run_dir / "split.json")  # one line naming the file when it is not JSON
    index = {s: i for i, s in enumerate(col.subjects)}
    j = col.shape_index("neutral")
    splits = {}
    for name, subs in split.items():
        if not isinstance(subs, list) or not all(isinstance(s, str) and s in index for s in subs):
            raise DataError(f"{run_dir / 'split.json'}: split {str(name)[:40]!r} is not a list of the dataset's "
                            f"subjects (edited, or another run's)")
        idx = np.array([index[s] for s in subs], dtype=np.int64)
        if len(idx) == 0:
            splits[name] = np.zeros((0, col.template.n_vertices, 3))
            continue
        N = np.asarray(col.positions[idx, j])
        splits[name], _ = pre.transform(N, N)
    return Env(run_dir, models, col.template.with_vertices(pre.mean_neutral), pre, splits, run.metrics)


def train_inline(ctx, recipe: dict) -> Path:
    """Run the recipe's training keys as a reconstruct sub-run in ``<run>/reconstruct/``."""
    sub = ctx.run_dir / RECONSTRUCT  # the task of the reconstruct family trains and evaluates the models
    if (sub / "metrics.json").exists() and all(has_state(sub, k) for k in recipe.get("models", {})):
        ctx.log(f"reconstruct sub-run {sub} finished before: its models are reused")
        return sub
    data = {"task": RECONSTRUCT, "name": f"{recipe.get('name', 'run')}-reconstruct", "seed": ctx.seed,
            **({"train": recipe["train"]} if recipe.get("train") else {}),
            **{k: recipe[k] for k in INLINE_KEYS if k in recipe}}
    if ctx.source:
        data["source"] = ctx.source
    r = resolve(data, ctx.registry)
    sub.mkdir(parents=True, exist_ok=True)
    (sub / "recipe.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    child = RunContext(sub, ctx.registry, ctx.cache, r.seed, recipe=r.data, train=r.train, device=ctx.device,
                       quiet=ctx.quiet, resume=ctx.resume, log_file=ctx.log_file)
    child.source = ctx.source
    ctx.log(f"training inline: reconstruct sub-run in {sub}")
    run_task(r, child)
    return sub


def _resolve_run(path: str, ctx) -> Path:
    p = Path(path).expanduser()
    if not p.is_absolute() and not p.exists() and ctx.source:
        q = Path(ctx.source).parent / p
        if q.exists():
            p = q
    if not (p / "recipe.yaml").exists():
        raise FwkError(f"run: {path} is not a run directory (no recipe.yaml)")
    return p


def _pick(env: Env, labels, role, what: str, exclude=None) -> list[str]:
    """``labels`` (each a model of the run playing ``role``), else every model of the run that
    plays ``role`` and not ``exclude``, in the recipe's order."""
    if labels:
        for l in labels:
            if l not in env.models:
                raise RecipeError(f"{what}: {l!r} is not a model of {env.run_dir} (models: {', '.join(env.models)})")
            if not isinstance(env.models[l], role):
                raise RecipeError(f"{what}: {l!r} ({env.models[l].name}) does not play the {role.__name__} role")
        return list(labels)
    return [l for l, m in env.models.items() if isinstance(m, role) and not (exclude and isinstance(m, exclude))]


def _renders(ctx, rows, template, path, cell=(240, 270)):
    try:
        return render_grid(rows, template, path, view="front", cell_size=cell)
    except Exception as exc:  # no OpenGL at all: keep the numbers, say so
        ctx.log(f"warning: render {Path(path).name} skipped ({type(exc).__name__}: {exc})")
        return None


# ------------------------------------------------------------------------------------ studies

def _interp(ctx, env: Env, p: "InterpolateSettings") -> tuple[dict, dict, list]:
    P = env.splits.get(p.subjects_from)
    if P is None or len(P) == 0:
        raise DataError(f"subjects_from: the {p.subjects_from} split has no subjects")
    i1, i2 = p.subjects
    if max(i1, i2) >= len(P):
        raise RecipeError(f"subjects: {p.subjects} out of range for the {len(P)} subjects of {p.subjects_from}")
    P1, P2 = P[i1], P[i2]
    labels = _pick(env, p.dsm, BandModel, BAND_KEY)
    if not labels:
        raise RecipeError(f"the run {env.run_dir} has no dsm model to interpolate with")
    figures, results = {}, {"subjects": [int(i1), int(i2)], "split": p.subjects_from, "alphas": p.alphas,
                            "betas": p.betas, "models": {}}
    vertex = [P1 + d * (P2 - P1) for d in p.alphas]  # eq. 4.17
    if p.write_obj:
        for d, V in zip(p.alphas, vertex):
            env.write_obj(ctx.path("interpolation", "vertex", f"delta{d:g}.obj"), V)
    for label in labels:
        m = env.models[label]
        Z = m.encode(np.stack([P1, P2]))
        hi = m.latent_slice(m.band_names[-1])
        lo = np.ones(Z.shape[1], bool)
        lo[hi] = False
        grid = []
        for b in p.betas:
            for a in p.alphas:
                z = Z[0].copy()
                z[lo] = (1 - b) * Z[0, lo] + b * Z[1, lo]   # eq. 4.16, low band(s)
                z[hi] = (1 - a) * Z[0, hi] + a * Z[1, hi]   # high band
                grid.append(z)
        out = m.decode(np.stack(grid)).reshape(len(p.betas), len(p.alphas), -1, 3)
        # how far each grid mesh is from the two ends, to make "the grid spans new shapes" a number
        results["models"][label] = {"gamma": getattr(m, "gamma", None),
                                    "spread_l1": float(np.abs(out - out.mean((0, 1))).mean())}
        if p.write_obj:
            for bi, b in enumerate(p.betas):
                for ai, a in enumerate(p.alphas):
                    env.write_obj(ctx.path("interpolation", label, f"alpha{a:g}_beta{b:g}.obj"), out[bi, ai])
        rows = [[{"V": out[bi, ai], "label": f"a={a:g} b={b:g}"} for ai, a in enumerate(p.alphas)]
                for bi, b in enumerate(p.betas)]
        rows.append([{"V": V, "label": f"vertex d={d:g}", "color": "#b8c7d9"} for d, V in zip(p.alphas, vertex)])
        f = _renders(ctx, rows, env.template, ctx.path("figures", f"interpolation_{label}.png"))
        if f is not None:
            g = getattr(m, "gamma", None)
            figures[f"interpolation, {label} (gamma {g}): rows beta (low band), columns alpha (high band); "
                    "last row: vertex-space interpolation (eq. 4.17)"] = f
    notes = [f"interpolation between {p.subjects_from} subjects {i1} and {i2}; meshes under interpolation/ "
             f"(OBJ, dataset units)"]
    return results, figures, notes


def band_parts(model, D) -> np.ndarray:
    """(..., n, 3) displacements -> (..., bands, n, 3): X_c D for every band c of a band model,
    from its ``split`` (split(P)[c] = X_c (P - mean) + mean, so X_c D = split(D)[c] - split(0)[c])."""
    D = np.asarray(D, dtype=np.float64)
    flat = D.reshape(-1, *D.shape[-2:])
    parts, zero = model.split(flat), model.split(np.zeros((1, *D.shape[-2:])))
    out = np.stack([np.asarray(x) - np.asarray(z)[0] for x, z in zip(parts, zero)], axis=1)
    return out.reshape(*D.shape[:-2], len(parts), *D.shape[-2:])


def band_energies(model, D, weights) -> np.ndarray:
    """(..., n, 3) -> (..., bands): e_c(D) = sum_i w_i |(X_c D)_i|^2, the ``weights``-weighted
    energy of each band's part of D (``weights``: per-vertex areas, the mass matrix diagonal)."""
    X = band_parts(model, D)
    return np.einsum("...cni,...cni,n->...c", X, X, np.asarray(weights, dtype=np.float64))


def band_variances(model, P, weights) -> np.ndarray:
    """(bands,): v_c = (1 / N) sum_s e_c(P_s - P-bar) over the N meshes P (the training split), P-bar
    their mean: each band's training variance (total over vertices and coordinates)."""
    P = np.asarray(P, dtype=np.float64)
    return band_energies(model, P - P.mean(0), weights).mean(0)


def disentanglement_measures(energies: dict, variances, band_names) -> dict:
    """The two like-with-like measures from the band energies of the edits (module docstring).

    ``energies``: {edited band j: e(D) of shape (..., bands)} over the edits of band j (subjects,
    directions, non-zero amounts); ``variances``: v (bands,). Returns, per edited band j,
    ``variance_units`` (mean e_c / v_c per band c) and ``normalised_shares`` (mean over the edits
    of (e_c / v_c) / sum_c' (e_c' / v_c')), and ``cross_response`` {"c<-j": rho_{c<-j}}: decoder
    c's mean response norm sqrt(e_c) to edits of band j over that to equal edits of its own band
    c, for every pair of edited bands j != c."""
    v = np.maximum(np.asarray(variances, dtype=np.float64), 1e-300)
    out = {"edits": {}, "cross_response": {}}
    for j, E in energies.items():
        E = np.asarray(E, dtype=np.float64).reshape(-1, len(band_names))
        eps = E / v
        nu = eps / np.maximum(eps.sum(-1, keepdims=True), 1e-300)
        out["edits"][j] = {"variance_units": {n: float(x) for n, x in zip(band_names, eps.mean(0))},
                           "normalised_shares": {n: float(x) for n, x in zip(band_names, nu.mean(0))}}
    norms = {j: np.sqrt(np.asarray(E, dtype=np.float64).reshape(-1, len(band_names))).mean(0)
             for j, E in energies.items()}
    for c in [b for b in norms if b in band_names]:  # edits of the bands' own codes (a single-band model has none)
        own = norms[c][band_names.index(c)]
        for j in norms:
            if j != c and j in band_names:
                out["cross_response"][f"{c}<-{j}"] = float(norms[j][band_names.index(c)] / max(own, 1e-300))
    return out


def measure_edits(env: Env, p: "EditSettings", weights=None):
    """The edits of ``edit`` and their disentanglement (old and new measures, module docstring):
    (results, decoded meshes of the pictured subject, dsm labels, comparison labels, bands)."""
    P = env.splits.get("test")
    if P is None or len(P) == 0:
        raise DataError("edit: the test split has no subjects")
    if p.subject >= len(P):
        raise RecipeError(f"subject: {p.subject} out of range for the {len(P)} test subjects")
    dsm_labels = _pick(env, p.dsm, BandModel, BAND_KEY)
    if not dsm_labels:
        raise RecipeError(f"the run {env.run_dir} has no dsm model to edit")
    cmp_labels = _pick(env, p.compare, GenerativeModel, "compare", exclude=BandModel)
    ref = env.models[dsm_labels[0]]
    bands = p.bands or list(ref.band_names)
    amounts = [float(a) for a in p.amounts]
    keep = [i for i, a in enumerate(amounts) if a != 0.0]
    S = P[: max(p.max_subjects, p.subject + 1)]
    if weights is None:  # the Voronoi areas of the mean head: the M of the M-weighted energies
        weights = mass_matrix(env.template.vertices, env.template.triangles).diagonal()
    train = env.splits.get("train")
    if train is None or len(train) < 2:
        raise DataError("edit: the band variances need the training split (at least 2 subjects)")
    results = {"directions": p.directions, "amounts": amounts, "n_subjects": int(len(S)), BAND_KEY: {}, "compare": {}}
    decoded = {}

    def edited(z0, sl, zeros):
        """z0 (s, d) -> (s, dirs, amounts, d) with entry sl.start + dir moved by amount."""
        Z = np.repeat(np.repeat(z0[:, None, None], len(p.directions), 1), len(zeros), 2).copy()
        for di, d in enumerate(p.directions):
            if sl.start + d >= sl.stop:
                raise RecipeError(f"directions: entry {d} is outside a band of {sl.stop - sl.start} latent entries")
            Z[:, di, :, sl.start + d] += np.asarray(zeros)
        return Z

    for label in dsm_labels:
        m = env.models[label]
        names = list(m.band_names)
        var = band_variances(m, train, weights)
        z0 = m.encode(S)
        base = m.decode(z0)
        res = results[BAND_KEY][label] = {"gamma": getattr(m, "gamma", None),
                                          "band_variance": {n: float(x) for n, x in zip(names, var)}}
        energies = {}
        for b in bands:
            Z = edited(z0, m.latent_slice(b), amounts)
            out = m.decode(Z.reshape(-1, Z.shape[-1])).reshape(*Z.shape[:3], -1, 3)
            D = out - base[:, None, None]
            sh = m.band_shares(D[:, :, keep])  # (s, dirs, amounts, bands)
            mean = sh.reshape(-1, sh.shape[-1]).mean(0)
            res[b] = {"own_share": float(mean[names.index(b)]), "shares": {n: float(x) for n, x in zip(names, mean)}}
            energies[b] = band_energies(m, D[:, :, keep], weights)
            decoded[(label, b)] = (out[p.subject, 0], base[p.subject])
        new = disentanglement_measures(energies, var, names)
        for b in bands:
            res[b].update(new["edits"][b])
            res[b]["own_normalised_share"] = res[b]["normalised_shares"][b]
        res["cross_response"] = new["cross_response"]
    names = list(ref.band_names)
    var = band_variances(ref, train, weights)
    for label in cmp_labels:
        m = env.models[label]
        z0 = np.asarray(m.encode(S))
        base = np.asarray(m.decode(z0))
        Z = edited(z0, slice(0, z0.shape[1]), amounts)
        out = np.asarray(m.decode(Z.reshape(-1, Z.shape[-1]))).reshape(*Z.shape[:3], -1, 3)
        D = out - base[:, None, None]
        sh = ref.band_shares(D[:, :, keep])
        mean = sh.reshape(-1, sh.shape[-1]).mean(0)
        new = disentanglement_measures({"latent": band_energies(ref, D[:, :, keep], weights)}, var, names)
        results["compare"][label] = {"shares": {n: float(x) for n, x in zip(names, mean)}, **new["edits"]["latent"]}
        decoded[(label, None)] = (out[p.subject, 0], base[p.subject])
    return results, decoded, dsm_labels, cmp_labels, bands


def _edit(ctx, env: Env, p: "EditSettings") -> tuple[dict, dict, list]:
    results, decoded, dsm_labels, cmp_labels, bands = measure_edits(env, p)
    ref = env.models[dsm_labels[0]]
    amounts = [float(a) for a in p.amounts]
    nz = [a for a in amounts if a != 0.0]
    figures = {}
    # pictures: per band, rows = each dsm model editing that band, then each comparison model
    for b in bands:
        rows_src = [(f"{l} {b}", decoded[(l, b)]) for l in dsm_labels]
        rows_src += [(f"{l}", decoded[(l, None)]) for l in cmp_labels]
        # each vertex's displacement by the edit, in the dataset's units (the preprocessing's scale undone)
        mags = [np.linalg.norm(out - base[None], axis=-1) / float(env.pre.scale) for _, (out, base) in rows_src]
        clim = colour_limits(mags)  # one far larger change saturates; the others stay readable
        bar = f"displacement by the edit ({env.template.units or 'input units'})"
        rows = []
        for (name, (out, _)), mag in zip(rows_src, mags):
            rows.append([{"V": out[ai], "scalars": mag[ai], "clim": clim, "cmap": "magma", "bar": bar,
                          "show_bar": ai == len(amounts) - 1, "label": f"{name}: {a:+g}" if ai == 0 else f"{a:+g}"}
                         for ai, a in enumerate(amounts)])
        f = _renders(ctx, rows, env.template, ctx.path("figures", f"edit_{b}.png"))
        if f is not None:
            figures[f"edit of the {b} band, entry {p.directions[0]} by {amounts} (rows: dsm models, then the "
                    f"single-band models' latent), coloured by the change"] = f
    names = list(ref.band_names)
    n_s = results["n_subjects"]
    where = (f"averaged over {n_s} test subjects, directions {p.directions} and amounts {nz}")
    # the tables: the M-weighted energy shares (as before), the same normalised by each band's
    # training variance, and the decoders' cross-responses
    cols = ["model", "edited", *[f"share in {n}" for n in names]]
    tab, tab_v = [], []
    for l in dsm_labels:
        g = results[BAND_KEY][l]["gamma"]
        for b in bands:
            r = results[BAND_KEY][l][b]
            tab.append([f"{l} (gamma {g})", b, *[f"{r['shares'][n]:.3f}" for n in names]])
            tab_v.append([f"{l} (gamma {g})", b, *[f"{r['normalised_shares'][n]:.3f} ({r['variance_units'][n]:.3g})"
                                                  for n in names]])
    for l in cmp_labels:
        r = results["compare"][l]
        tab.append([l, "latent", *[f"{r['shares'][n]:.3f}" for n in names]])
        tab_v.append([l, "latent", *[f"{r['normalised_shares'][n]:.3f} ({r['variance_units'][n]:.3g})" for n in names]])
    text = ("Share of the M-weighted energy of the output change that falls in each spectral band "
            f"(the band projectors of {dsm_labels[0]}), {where}. For a dsm edit of band b, the share in b is its "
            "disentanglement (1 = the edit stays in its band). This share is dominated by the bands' "
            "amplitudes (the low band carries most of a face's variance); the two tables below compare like "
            "with like.\n\n" + markdown_table(tab, cols))
    text_v = ("Each band's energy of the output change divided by that band's training variance v_c (the mean "
              "M-weighted energy of the training subjects' band c about their mean), as a share of the sum over "
              f"bands, {where}; in brackets the mean e_c / v_c itself (1: the edit moves band c as far as a typical "
              "training subject differs from the mean in that band).\n\n"
              + markdown_table(tab_v, ["model", "edited", *[f"normalised share in {n} (e/v)" for n in names]]))
    pairs = sorted({k for l in dsm_labels for k in results[BAND_KEY][l]["cross_response"]})
    tab_x = [[f"{l} (gamma {results[BAND_KEY][l]['gamma']})",
              *[f"{results[BAND_KEY][l]['cross_response'].get(k, float('nan')):.3f}" for k in pairs]] for l in dsm_labels]
    text_x = ("Cross-response rho_{c<-j} of decoder D_c: the mean M-norm of its band-c output change for an edit of "
              "band j's code over that for an equal edit of its own code c (same entries, same amounts), "
              f"{where}. 0: D_c ignores Z_j (disentangled); 1: it responds to Z_j as much as to its own code.\n\n"
              + markdown_table(tab_x, ["model", *[f"rho {k.replace('<-', ' <- ')}" for k in pairs]]))
    sections = [("Disentanglement of latent edits", text),
                ("Disentanglement normalised by the bands' training variance", text_v)]
    if pairs:
        sections.append(("Decoders' response to the other bands' codes", text_x))
    return results, figures, sections


# ------------------------------------------------------------------------------------- tasks

class _Study:
    """Shared: where the models come from (``run`` or inline training), running, the report."""

    title = ""

    def run(self, ctx):
        env = self.env(ctx)
        out, figures, notes, sections = self.run_study(ctx, env)
        self._report(ctx, env, f"{self.title}: {ctx.recipe.get('name', 'run')}", out, figures, notes, sections)

    def _init_source(self, run, dataset, models, split, preprocess, shapes, metrics, renders):
        if run and models:
            raise RecipeError("run: give either `run` (a finished reconstruct run) or `models` to train inline, not both")
        self.run_path = run
        self.inline = bool(models)

    def env(self, ctx) -> Env:
        if not self.run_path and not self.inline:
            raise RecipeError("run: give `run` (a finished reconstruct run directory) or `models` to train inline")
        if self.run_path:
            run_dir = _resolve_run(self.run_path, ctx)
        else:
            run_dir = train_inline(ctx, dict(ctx.recipe))
        ctx.log(f"models from {run_dir}")
        return load_models(run_dir, ctx, ctx.registry)

    def _report(self, ctx, env, title, results, figures, notes, sections):
        res = dict(results)
        if env.metrics.get("models"):
            res["models"] = env.metrics["models"]
            res["dataset"] = env.metrics.get("dataset", {})
        notes = [f"models: {env.run_dir}" + (" (trained inline by this run)" if not self.run_path else ""),
                 f"train epochs: {ctx.train.epochs} (recipe `train.epochs`)" if not self.run_path else "", *notes]
        write_report(ctx, title, res, figures, notes=[n for n in notes if n], sections=sections)


@dataclass
class InterpolateSettings:
    """What ``interpolate`` computes: the keys of an ``interpolate`` recipe beyond where the models
    come from, and the ``interpolate: {...}`` chained in an ``edit`` recipe.

    dsm            labels of the band models to interpolate with (default: every band model)
    subjects       two subject indices of ``subjects_from`` (default [0, 1])
    subjects_from  train, val or test (default test)
    alphas, betas  the grid of eq. 4.16 (alpha: the high band, beta: the others; default 0 .. 1 by 0.25)
    write_obj      write every grid mesh as OBJ under ``interpolation/``
    """

    dsm: list[str] | None = None
    subjects: list[int] | None = None
    subjects_from: str = "test"
    alphas: list[float] | None = None
    betas: list[float] | None = None
    write_obj: bool = True

    def __post_init__(self):
        self.subjects = list(self.subjects) if self.subjects is not None else [0, 1]
        if len(self.subjects) != 2:
            raise RecipeError(f"subjects: give two subject indices, got {self.subjects}")
        if self.subjects_from not in ("train", "val", "test"):
            raise RecipeError(f"subjects_from: one of train, val, test, got {self.subjects_from!r}")
        self.alphas = [float(a) for a in (self.alphas if self.alphas is not None else [0, 0.25, 0.5, 0.75, 1])]
        self.betas = [float(b) for b in (self.betas if self.betas is not None else [0, 0.25, 0.5, 0.75, 1])]


@dataclass
class EditSettings:
    """What ``edit`` computes: the keys of an ``edit`` recipe beyond where the models come from,
    and the ``edit: {...}`` chained in an ``interpolate`` recipe.

    dsm, compare   labels of the band models and of the comparison models (default: every band
                   model; every other generative model)
    bands          the bands to edit (default: every band of the first band model)
    directions     latent entries within a band's slice of Z (default [0, 1, 2])
    amounts        moves in units of the prior's standard deviation (default [-3, -1.5, 0, 1.5, 3])
    subject        the test subject pictured; ``max_subjects`` test subjects are measured
    """

    dsm: list[str] | None = None
    compare: list[str] | None = None
    bands: list[str] | None = None
    directions: list[int] | None = None
    amounts: list[float] | None = None
    subject: int = 0
    max_subjects: int = 20

    def __post_init__(self):
        self.directions = [int(d) for d in (self.directions if self.directions is not None else [0, 1, 2])]
        self.amounts = [float(a) for a in (self.amounts if self.amounts is not None else [-3, -1.5, 0, 1.5, 3])]
        if not self.directions or any(d < 0 for d in self.directions):
            raise RecipeError(f"directions: non-negative latent entry indices, got {self.directions}")
        if not any(a != 0 for a in self.amounts):
            raise RecipeError("amounts: give at least one non-zero amount")
        if self.max_subjects < 1:
            raise RecipeError(f"max_subjects: at least 1, got {self.max_subjects}")
        self.subject, self.max_subjects = int(self.subject), int(self.max_subjects)


class Interpolate(_Study):
    """Interpolate low and high frequencies of two subjects separately (eqs. 4.16-4.17)."""

    name = "interpolate"
    title = "Interpolation"

    def __init__(self, run: str | None = None, dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads",
                 models: Annotated[dict[str, Spec], Kind("model")] | None = None, split: SplitConfig | None = None,
                 preprocess: PreprocessConfig | None = None, shapes: list[str] | None = None,
                 metrics: Annotated[list[Spec], Kind("metric")] | None = None, renders: int = 2,
                 dsm: list[str] | None = None, subjects: list[int] | None = None, subjects_from: str = "test",
                 alphas: list[float] | None = None, betas: list[float] | None = None, write_obj: bool = True,
                 edit: EditSettings | None = None):
        self._init_source(run, dataset, models, split, preprocess, shapes, metrics, renders)
        self.settings = InterpolateSettings(dsm, subjects, subjects_from, alphas, betas, write_obj)
        self.edit = edit

    def run_study(self, ctx, env):
        """Interpolate (and edit, when chained) with the models of ``env``."""
        results, figures, notes = _interp(ctx, env, self.settings)
        sections = []
        out = {"interpolation": results}
        if self.edit is not None:
            r2, f2, s2 = _edit(ctx, env, self.edit)
            out["disentanglement"] = r2
            figures.update(f2)
            sections += s2
        return out, figures, notes, sections


class Edit(_Study):
    """Edit one spectral band's latent entries, next to editing a single-band VAE; disentanglement."""

    name = "edit"
    title = "Multi-frequency editing"

    def __init__(self, run: str | None = None, dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads",
                 models: Annotated[dict[str, Spec], Kind("model")] | None = None, split: SplitConfig | None = None,
                 preprocess: PreprocessConfig | None = None, shapes: list[str] | None = None,
                 metrics: Annotated[list[Spec], Kind("metric")] | None = None, renders: int = 2,
                 dsm: list[str] | None = None, compare: list[str] | None = None, bands: list[str] | None = None,
                 directions: list[int] | None = None, amounts: list[float] | None = None, subject: int = 0,
                 max_subjects: int = 20, interpolate: InterpolateSettings | None = None):
        self._init_source(run, dataset, models, split, preprocess, shapes, metrics, renders)
        self.settings = EditSettings(dsm, compare, bands, directions, amounts, subject, max_subjects)
        self.interpolate = interpolate

    def run_study(self, ctx, env):
        """Edit (and interpolate, when chained) with the models of ``env``."""
        r, figures, sections = _edit(ctx, env, self.settings)
        out, notes = {"disentanglement": r}, []
        if self.interpolate is not None:
            r2, f2, n2 = _interp(ctx, env, self.interpolate)
            out["interpolation"] = r2
            figures.update(f2)
            notes += n2
        return out, figures, notes, sections


@hookimpl
def fwk_register_tasks():
    return [Interpolate, Edit]
