"""``fwk sample RUN_DIR --n N --out DIR [--seed S] [--model LABEL]``: new heads from a trained model.

A finished ``reconstruct`` run (or an ``interpolate``/``edit`` run that trained inline: its
``reconstruct/`` sub-run is used) holds the trained models (``models/<label>.pt``) and the
fitted preprocessing (``stats/preprocess.npz``). The model draws Z ~ N(0, I) (``sample(n,
seed)``: deterministic for a seed) and decodes; the meshes are taken back to the dataset's units
(the preprocessing's uniform scale undone; they sit in the registered frame of the mean head)
and written as ``sample_000.obj``, ... with the dataset's own polygons, UVs and material lines,
vertex order unchanged, so they open in any DCC tool. The topology comes from the run's dataset
(rebuilt from its recipe); everything is written into a temporary folder and moved into place.
"""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np

from .errors import FwkError


def add_sample_parser(subparsers):
    p = subparsers.add_parser(
        "sample", help="sample new meshes from a trained model of a run (OBJ, the dataset's polygons and UVs)",
        description="Draw latent codes from N(0, I), decode them with a trained model of a reconstruct run and "
                    "write OBJ files in the dataset's units with its own polygons and UVs.")
    p.add_argument("run_dir", help="a finished `fwk run` directory with trained models (reconstruct, or "
                                   "interpolate/edit with a reconstruct/ sub-run)")
    p.add_argument("--n", type=int, default=8, help="how many meshes (default 8)")
    p.add_argument("--out", required=True, help="output folder (created; files of the same name are replaced)")
    p.add_argument("--seed", type=int, default=0, help="random seed (the same seed gives the same meshes)")
    p.add_argument("--model", default=None, help="model label of the run (default: the first dsm, else the first "
                                                 "model that can sample)")
    return p


def _run_with_models(run_dir: Path) -> Path:
    if (run_dir / "models").is_dir():
        return run_dir
    if (run_dir / "reconstruct" / "models").is_dir():
        return run_dir / "reconstruct"
    raise FwkError(f"{run_dir}: no trained models (no models/ folder); is it a finished reconstruct run?")


def sample_meshes(run_dir, n: int, seed: int = 0, model: str | None = None, registry=None):
    """(label, meshes (n, v, 3) in the dataset's units, template with the user's polygons)."""
    import torch

    from .data.preprocess import Preprocessor
    from .runs import load_run

    if n < 1:
        raise FwkError(f"--n {n}: at least 1")
    run_dir = _run_with_models(Path(run_dir))
    loaded = load_run(run_dir, registry)
    params = loaded.resolved.task.params
    models = params.get("models") or {}
    label = model
    if label is None:
        label = next((k for k, s in models.items() if getattr(s, "name", "") == "dsm"), None)
        if label is None:
            label = next((k for k, s in models.items() if hasattr(s.cls, "sample")), None)
    if label not in models:
        raise FwkError(f"--model {label}: not a model of {run_dir} (models: {', '.join(models) or 'none'})")
    if not hasattr(models[label].cls, "sample"):
        raise FwkError(f"--model {label}: {models[label].name} cannot sample (no latent prior)")
    state = run_dir / "models" / f"{label}.pt"
    pre_path = run_dir / "stats" / "preprocess.npz"
    for p in (state, pre_path):
        if not p.exists():
            raise FwkError(f"{p}: missing; is {run_dir} a finished run?")
    m = models[label].build()
    d = torch.load(state, weights_only=False)
    try:
        m.load_state_dict(d, ctx=loaded.ctx)
    except TypeError:
        m.load_state_dict(d)
    with np.load(pre_path) as z:
        pre = Preprocessor.from_state({k: z[k] for k in z.files})
    X = np.asarray(m.sample(n, seed=seed), dtype=np.float64)
    if not np.all(np.isfinite(X)):
        raise FwkError(f"model {label} of {run_dir} produced non-finite vertices")
    P = X / pre.scale  # the evaluation space's uniform scale undone (centre and rotation: the mean's frame)
    template = params["dataset"].build().load(loaded.ctx.cache).template
    if template.n_vertices != P.shape[1]:
        raise FwkError(f"{run_dir}: the dataset now has {template.n_vertices} vertices, the model {P.shape[1]}")
    return label, P, template


def run_sample(args) -> int:
    from .data.io import write_obj

    label, P, template = sample_meshes(args.run_dir, args.n, args.seed, args.model)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".fwk-sample-", dir=out.parent))
    try:
        for i, V in enumerate(P):
            write_obj(tmp / f"sample_{i:03d}.obj", V, template)
        out.mkdir(parents=True, exist_ok=True)
        for f in sorted(tmp.iterdir()):
            f.replace(out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if not getattr(args, "quiet", False):
        print(f"{len(P)} meshes from model {label} (seed {args.seed}) written to {out}")
    return 0
