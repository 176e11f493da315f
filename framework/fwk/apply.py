"""``fwk apply RUN_DIR NEUTRAL.obj|FOLDER --out DIR``: personalised blendshapes for your own head.

A finished ``blendshapes`` run holds everything a new neutral needs: the fitted preprocessing
(``stats/preprocess.npz``: the mean training neutral and the dataset scale), the topology
(``stats/template.npz``) and the trained model (``models/<label>.pt``, reopened by
``fwk.lifecycle``: ``--model LABEL``, else the run's ``apply_model``, else chosen by role). For
each neutral: read it (its own polygons, UVs and material lines kept), check its topology
against the run's, centre it, register it rigidly to the mean neutral and scale it (thesis
5.2.1), predict every expression the model was trained for (``predict_all``), undo the
registration and scale, and write ``<expression>.obj`` with the neutral's polygons, ``vt`` and
material lines, vertex order unchanged. A folder of neutrals gives one sub-folder per neutral.

Every input is read and checked before anything is written; results are written into a
temporary folder beside ``--out`` and moved into place at the end, so a wrong topology, NaNs or
an unreadable file raise one error naming the file and leave nothing half-written.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .data import Template
from .data.io import check_topology, read_obj, write_obj
from .errors import DataError, FwkError
from .lifecycle import choose_model, open_run
from .protocols import BlendshapeModel, CutSelectingModel

MESH_SUFFIXES = (".obj",)


def add_apply_parser(subparsers):
    p = subparsers.add_parser(
        "apply", help="personalised blendshapes for your own neutral head(s) from a blendshapes run",
        description="Predict every expression of a trained blendshapes run for a neutral OBJ (or a folder "
                    "of them) and write one OBJ per expression with the neutral's own polygons and UVs.")
    p.add_argument("run_dir", help="a finished `fwk run` directory of task blendshapes")
    p.add_argument("neutral", help="a neutral head .obj sharing the run's topology, or a folder of them")
    p.add_argument("--out", required=True, help="output folder (created; existing files of the same name are replaced)")
    p.add_argument("--model", default=None, help="model label of the run (default: the run's apply_model, else "
                   "the first model choosing its spectral cut, else the first)")
    p.add_argument("--expressions", nargs="*", default=None, help="only these expressions (default: all trained)")
    p.add_argument("--quiet", action="store_true")
    return p


class Applier:
    """A run reopened for applying: ``predict(V_list) -> [{expression: (n, 3)}]`` in input units.

    The model is ``model`` (a label, ``--model``) when given, else the run's recorded
    ``apply_model``, else chosen by role: the first model choosing its spectral cut
    (``fwk.protocols.CutSelectingModel``), else the first blendshape model."""

    def __init__(self, run_dir, model: str | None = None, registry=None):
        run = open_run(run_dir, registry)
        label = model or run.metrics.get("apply_model") or run.params.get("apply_model")
        self.label = choose_model(run.specs, BlendshapeModel, label, prefer=CutSelectingModel,
                                  source=str(run.run_dir))
        tpl = run.run_dir / "stats" / "template.npz"
        if not tpl.exists():
            raise FwkError(f"{tpl}: missing; is {run.run_dir} a finished blendshapes run?")
        self.model = run.model(self.label)
        self.pre = run.preprocessor
        with np.load(tpl) as z:
            self.template = Template(z["mean_neutral"], z["triangles"])
        self.expressions = list(self.model.expressions or [])

    def predict(self, neutrals: list[np.ndarray], expressions: list[str] | None = None, batch: int = 16) -> list[dict]:
        """For each neutral (n, 3) in its own units and place: {expression: (n, 3)} likewise."""
        exprs = expressions or self.expressions
        bad = [e for e in exprs if e not in self.expressions]
        if bad:
            raise FwkError(f"--expressions {bad[0]}: not trained (trained: {', '.join(self.expressions)})")
        out = [dict() for _ in neutrals]
        for s in range(0, len(neutrals), batch):
            V = np.stack(neutrals[s:s + batch])
            X, T = self.pre.transform_neutrals(V)
            for e, P in self.model.predict_all(X, list(exprs)).items():
                P = self.pre.inverse(np.asarray(P, dtype=np.float64), T)
                for i in range(len(V)):
                    out[s + i][e] = P[i]
        return out


def _inputs(path: Path) -> list[Path]:
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
        if not files:
            raise DataError(f"{path}: no .obj files in this folder")
        return files
    if not path.exists():
        raise DataError(f"{path}: no such file or folder")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path}: not an .obj file (fwk apply writes OBJ with the neutral's own polygons and UVs)")
    return [path]


def apply(run_dir, neutral, out, model: str | None = None, expressions: list[str] | None = None,
          log=print, registry=None) -> list[Path]:
    """Write the blendshapes of one neutral (``out/<expression>.obj``) or of a folder of neutrals
    (``out/<stem>/<expression>.obj``); returns the written files."""
    t0 = time.perf_counter()
    app = Applier(run_dir, model, registry)
    t_load = time.perf_counter() - t0
    neutral, out = Path(neutral), Path(out)
    files = _inputs(neutral)
    meshes = []
    for f in files:  # read and check everything before writing anything
        V, tpl = read_obj(f)
        check_topology(app.template, tpl, f)
        if not np.all(np.isfinite(V)):
            raise DataError(f"{f}: vertex positions contain NaN or infinite values")
        meshes.append((f, V, tpl))
    t1 = time.perf_counter()
    preds = app.predict([V for _, V, _ in meshes], expressions)
    t2 = time.perf_counter()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    written = []
    try:
        for (f, _, tpl), P in zip(meshes, preds):
            sub = tmp if not neutral.is_dir() else tmp / f.stem
            for e, V in P.items():
                if not np.all(np.isfinite(V)):
                    raise FwkError(f"{f}: the model produced non-finite positions for {e}")
                write_obj(sub / f"{e}.obj", V, tpl)
        out.mkdir(parents=True, exist_ok=True)
        for p in sorted(tmp.rglob("*.obj")):
            dest = out / p.relative_to(tmp)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(p, dest)
            written.append(dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    n = len(meshes)
    log(f"fwk apply: {n} neutral(s) x {len(preds[0]) if preds else 0} expression(s) with model {app.label} -> {out} "
        f"(loading the run {t_load:.2f} s, predicting {(t2 - t1) / max(n, 1):.2f} s per neutral, "
        f"total {time.perf_counter() - t0:.2f} s)")
    return written


def run_apply(args) -> int:
    quiet = getattr(args, "quiet", False)
    apply(args.run_dir, args.neutral, args.out, getattr(args, "model", None), getattr(args, "expressions", None),
          log=(lambda *_: None) if quiet else print)
    return 0
