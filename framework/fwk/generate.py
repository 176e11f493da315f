"""``fwk sample RUN_DIR --n N --out DIR [--seed S] [--model LABEL] [--seed-run S]``: new heads from a trained model.

A finished ``reconstruct`` run (or an ``interpolate``/``edit`` run that trained inline: its
``reconstruct/`` sub-run is used) holds the trained models (``models/<label>.safetensors``) and the
fitted preprocessing (``stats/preprocess.npz``); it is reopened with ``fwk.lifecycle.open_run``.
The model is chosen by role: ``--model LABEL``, else the first model playing
``fwk.protocols.BandModel``, else the first playing ``GenerativeModel``. It draws Z ~ N(0, I)
(``sample(n, seed)``: deterministic for a seed) and decodes; the meshes are taken back to the dataset's units
(the preprocessing's uniform scale undone; they sit in the registered frame of the mean head)
and written as ``sample_000.obj``, ... with the dataset's own polygons, UVs and material lines,
vertex order unchanged, so they open in any DCC tool. A run of a recipe with ``seeds:`` holds one
trained model per seed (``seed-<s>/``): the first seed of ``seeds:`` is used, said on stderr, unless
``--seed-run S`` (or ``RUN/seed-S``) picks another (``fwk.lifecycle.seed_sub_run``). The topology comes from the run's dataset
(rebuilt from its recipe); everything is written into a temporary folder and moved into place.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from .data.io import write_obj
from .errors import FwkError
from .lifecycle import choose_model, open_run, seed_sub_run
from .paths import check_dir
from .protocols import RECONSTRUCT, BandModel, GenerativeModel
from .recipes import MAX_SEED

#: the most meshes one ``fwk sample`` writes (10,000 heads of 11,248 vertices: 2.7 GB in memory)
MAX_SAMPLES = 10_000


def add_sample_parser(subparsers):
    """Register ``fwk sample`` on the CLI's subparsers."""
    p = subparsers.add_parser(
        "sample", help="sample new meshes from a trained model of a run (OBJ, the dataset's polygons and UVs)",
        description="Draw latent codes from N(0, I), decode them with a trained model of a reconstruct run and "
                    "write OBJ files in the dataset's units with its own polygons and UVs.")
    p.add_argument("run_dir", help="a finished `fwk run` directory with trained models (reconstruct, or "
                                   "interpolate/edit with a reconstruct/ sub-run)")
    p.add_argument("--n", type=int, default=8, help=f"how many meshes (default 8, at most {MAX_SAMPLES:,})")
    p.add_argument("--out", required=True, help="output folder (created; files of the same name are replaced)")
    p.add_argument("--seed", type=int, default=0, help=f"random seed, 0 to {MAX_SEED} (the same seed gives the same "
                                                        "meshes)")
    p.add_argument("--model", default=None, help="model label of the run (default: the first band model, e.g. dsm, "
                                                 "else the first generative model)")
    p.add_argument("--seed-run", type=int, default=None, metavar="S",
                   help="of a run with seeds: the seed whose models to use (default: the first of its seeds; "
                        "RUN/seed-S does the same)")
    return p


def _run_with_models(run_dir: Path) -> Path:
    """The run directory itself, or its inline reconstruct sub-run, whichever holds ``models/``."""
    if (run_dir / "models").is_dir():
        return run_dir
    inline = run_dir / RECONSTRUCT  # the reconstruct sub-run of an interpolate/edit run that trained inline
    if (inline / "models").is_dir():
        return inline
    raise FwkError(f"{run_dir}: no trained models (no models/ folder); is it a finished reconstruct run?")


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def sample_meshes(run_dir, n: int, seed: int = 0, model: str | None = None, registry=None,
                  seed_run: int | None = None, say=_stderr):
    """(label, meshes (n, v, 3) in the dataset's units, template with the user's polygons).
    ``seed_run``: of a run with ``seeds:``, the seed whose models to use (default its first,
    named by ``say``: one line on stderr; None: silent)."""
    if not 1 <= n <= MAX_SAMPLES:
        raise FwkError(f"--n {n}: from 1 to {MAX_SAMPLES:,}")
    if not 0 <= seed <= MAX_SEED:
        raise FwkError(f"--seed {seed}: out of range (0 to {MAX_SEED})")
    run_dir = seed_sub_run(run_dir, seed_run, registry, say=say)  # a run with seeds: one seed's sub-run
    run = open_run(_run_with_models(run_dir), registry)
    label = choose_model(run.specs, GenerativeModel, model, prefer=BandModel, source=str(run.run_dir))
    m = run.model(label)
    pre = run.preprocessor
    X = np.asarray(m.sample(n, seed=seed), dtype=np.float64)
    if not np.all(np.isfinite(X)):
        raise FwkError(f"model {label} of {run.run_dir} produced non-finite vertices")
    P = X / pre.scale  # the evaluation space's uniform scale undone (centre and rotation: the mean's frame)
    template = run.params["dataset"].build().load(run.ctx.cache).template
    if template.n_vertices != P.shape[1]:
        raise FwkError(f"{run.run_dir}: the dataset now has {template.n_vertices} vertices, the model {P.shape[1]}")
    return label, P, template


def run_sample(args) -> int:
    """``fwk sample``: write the sampled meshes as OBJ files into ``--out`` (replaced atomically per file)."""
    check_dir(args.out, "--out")  # before the run is loaded: a bad destination fails in one line, at once
    label, P, template = sample_meshes(args.run_dir, args.n, args.seed, args.model,
                                       seed_run=getattr(args, "seed_run", None),
                                       say=None if getattr(args, "quiet", False) else _stderr)
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
