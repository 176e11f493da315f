"""``fwk apply RUN_DIR NEUTRAL.obj|FOLDER --out DIR [--format obj,gltf,usd] [--naming arkit]``:
personalised blendshapes for your own head, as OBJs and as a rig.

A finished ``blendshapes`` run holds everything a new neutral needs: the fitted preprocessing
(``stats/preprocess.npz``: the mean training neutral and the dataset scale), the topology
(``stats/template.npz``) and the trained model (``models/<label>.safetensors``, reopened by
``fwk.lifecycle``: ``--model LABEL``, else the run's ``apply_model``, else chosen by role). For
each neutral: read it (its own polygons, UVs and material lines kept), check its topology
against the run's, centre it, register it rigidly to the mean neutral and scale it (thesis
5.2.1), predict every expression the model was trained for (``predict_all``), undo the
registration and scale, and write ``<expression>.obj`` with the neutral's polygons, ``vt`` and
material lines, vertex order unchanged. A folder of neutrals gives one sub-folder per neutral.

A run of a recipe with ``seeds:`` holds one trained model per seed, in ``seed-<s>/``: ``fwk apply
RUN`` uses the first seed of ``seeds:`` and says so on stderr; ``--seed-run S`` (or ``RUN/seed-S``)
picks seed S (``fwk.lifecycle.seed_sub_run``).

``--format`` (comma-separated) adds rig files beside the OBJs (``fwk.rig``): ``gltf`` writes
``<neutral>.glb`` (glTF 2.0 binary, one morph target per expression), ``usd`` ``<neutral>.usdc``
(``usda`` for text; a UsdSkel rig, one BlendShape per expression), ``fbx`` ``<neutral>.fbx`` (one
shape key per expression, centimetres; Blender's own exporter through ``bpy``, the extra ``fbx``:
``fwk.rig.fbx``). ``--naming arkit`` renames
ICT-FaceKit's shapes to Apple ARKit's names in every format (``fwk.rig.arkit``); with
``--only-mapped`` every format and the OBJs hold exactly the shapes with an ARKit name (for
ICT-FaceKit 51 of the 52: it has no ``tongueOut``), in Apple's order, and one line on stderr says
what was left out.

The model's topology is the run's ``template.obj`` (with its UVs). A neutral with another vertex
count is refused with both counts and that file named; one exception: a neutral whose first n
vertices and first polygons are the run's n vertices and polygons (the full mesh a region such
as ICT-FaceKit's face-head was cut from, 11,248 of 26,719 vertices) is accepted: the region is
predicted, the rest of the mesh is left as it is, and the full mesh is written back. When the
run has followers for that mesh (``stats/followers.npz``, from the recipe's ``follow:``; same
vertex count), the rest moves instead: each part outside the region (a tooth, the gums and tongue,
an eye's lashes) by the training subjects' mean motion of it for that expression, scaled by the
predicted face's motion next to it (``fwk.rig.follow``); one line on stderr says so.

Every neutral is also checked against the training neutrals' size (``check_scale``): the
median distance of its vertices from its median point, over the same of the run's mean training
neutral, must lie within ``MAX_SCALE_RATIO`` (2x) either way, no vertex may lie farther from the
head's centre than ``MAX_STRAY`` (4) times the mean neutral's farthest vertex (scaled to this
head's size), and no coordinate beyond ``MAX_COORDINATE`` (10^4) times that farthest distance
from the origin. A head in other units than the run's (a metre head given to a millimetre
run: 0.001x) is refused with the measured ratio and a hint: ``--units`` names the neutral's units
(``mm``, ``cm``, ``m``, ``in``, ...; the run's must be stated, ``dataset.units``) or gives a
factor (``--units 0.1``: one of the neutral's units is 0.1 of the run's). The neutral is then
scaled into the run's units, the checks apply to the scaled head, and every output is written
back in the neutral's own units (the rig files record the units named, else none).

Every input is read and checked before anything is written, and ``--out`` is checked before the
run is loaded (a file in the way, a folder that cannot be created or written: one line, exit 2);
results are written into a temporary folder beside ``--out`` and moved into place at the end, so
a wrong topology, NaNs or an unreadable file raise one error naming the file and leave nothing
half-written. Files are created with the process umask (0644 under the usual 022).
"""
from __future__ import annotations

import argparse
import os
from concurrent.futures import ThreadPoolExecutor
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .cache import file_mode
from .data import Template
from .data.io import ObjWriter, check_topology, line_number, read_obj
from .data.template import METRES_PER_UNIT, template_from_arrays
from .errors import DataError, FwkError, TopologyError, quote
from .lifecycle import choose_model, open_run
from .safeio import load_npz
from .paths import check_dir
from .protocols import BlendshapeModel, CutSelectingModel
from .rig.arkit import NAMINGS, check_only_mapped, mapped_sources, only_mapped_note, rename
from .rig.fbx import import_bpy, write_fbx
from .rig.gltf import write_glb
from .rig.shipped import shipped_or_path
from .rig.usd import write_usd

if TYPE_CHECKING:  # the rig modules import scipy.spatial: loaded where they run, not at fwk's start-up
    from .rig.register import Registration

MESH_SUFFIXES = (".obj",)
#: --format values -> the file suffix written (``obj``: one OBJ per expression)
FORMATS = {"obj": ".obj", "gltf": ".glb", "glb": ".glb", "usd": ".usdc", "usdc": ".usdc", "usda": ".usda",
           "fbx": ".fbx"}
#: --landmarks: how expressions are carried onto a neutral of another topology (the first: default)
CARRIES = ("transfer", "barycentric")
TEMPLATE_OBJ = "template.obj"  # the run directory's topology with UVs (written by the blendshapes task)
#: the most a neutral's size may differ from the training neutrals' (either way), in the run's units
MAX_SCALE_RATIO = 2.0
#: how much farther than the mean training neutral's farthest vertex (scaled to the neutral's size)
#: a vertex may lie from the neutral's centre
MAX_STRAY = 4.0
#: how far from the origin a coordinate may lie, in the mean training neutral's largest extents
MAX_COORDINATE = 1e4


def add_apply_parser(subparsers):
    p = subparsers.add_parser(
        "apply", help="personalised blendshapes for your own neutral head(s) from a blendshapes run",
        description="Predict every expression of a trained blendshapes run for a neutral OBJ (or a folder "
                    "of them) and write one OBJ per expression with the neutral's own polygons and UVs.")
    p.add_argument("run_dir", help="a finished `fwk run` directory of task blendshapes, or a shipped rig model's "
                                   "name (fwk list --kind rig)")
    p.add_argument("neutral", help="a neutral head .obj sharing the run's topology, or a folder of them")
    p.add_argument("--out", required=True, help="output folder (created; existing files of the same name are replaced)")
    p.add_argument("--model", default=None, help="model label of the run (default: the run's apply_model, else "
                   "the first model choosing its spectral cut, else the first)")
    p.add_argument("--seed-run", type=int, default=None, metavar="S",
                   help="of a run with seeds: the seed whose models to use (default: the first of its seeds; "
                        "RUN/seed-S does the same)")
    p.add_argument("--expressions", nargs="*", default=None, help="only these expressions (default: all trained)")
    p.add_argument("--format", default="obj", help="comma-separated: obj (one OBJ per expression), gltf (.glb with "
                   "one morph target per expression), usd (.usdc UsdSkel rig; usda for text), fbx (.fbx, one shape key "
                   "per expression, cm; needs the extra fbx: bpy); default obj")
    p.add_argument("--naming", default="source", choices=NAMINGS, help="shape names: the run's (source) or Apple "
                   "ARKit's for ICT-FaceKit's shapes (arkit; table in docs/rig-quickstart.md)")
    p.add_argument("--only-mapped", action="store_true", help="with --naming arkit: only the shapes with an ARKit "
                   "name, in Apple's order (ICT-FaceKit: 51 of the 52, no tongueOut), in every format and the OBJs")
    p.add_argument("--units", default=None, help="the neutral's units when they are not the run's: a unit (mm, cm, "
                   "m, um, in, ft; the run's must be stated) or a factor (0.1: one of the neutral's units is 0.1 of "
                   "the run's); the neutral is scaled into the run's units and the outputs written back in its own")
    p.add_argument("--landmarks", default=None, metavar="L.json", help="a neutral of another topology: register "
                   "the run's template to it with these landmark pairs (fwk register) and write the rig on its own "
                   "vertices, polygons and UVs (docs/rig-quickstart.md, 'Your own head, any mesh')")
    p.add_argument("--carry", default=CARRIES[0], choices=CARRIES, help="with --landmarks: how each expression is "
                   "carried from the registered template onto the neutral's vertices: transfer (Deformation Transfer onto "
                   "its triangles, fwk.rig.carry; default: measured lower DAME, the same L1) or barycentric (each "
                   "vertex takes the displacement of its closest registered point)")
    # fwk --quiet (moved first by fwk.cli.main) must not be reset by this parser default
    p.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help="no messages")
    return p


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


class Applier:
    """A run reopened for applying: ``predict(V_list) -> [{expression: (n, 3)}]`` in input units.

    The model is ``model`` (a label, ``--model``) when given, else the run's recorded
    ``apply_model``, else chosen by role: the first model choosing its spectral cut
    (``fwk.protocols.CutSelectingModel``), else the first blendshape model. A run with ``seeds:``
    is applied with one seed's models: ``seed_run``, else its first seed (named through ``say``)."""

    def __init__(self, run_dir, model: str | None = None, registry=None, seed_run: int | None = None,
                 say=_stderr):
        run = open_run(shipped_or_path(run_dir), registry, seed_run=seed_run, say=say)
        label = model or run.metrics.get("apply_model") or run.params.get("apply_model")
        self.label = choose_model(run.specs, BlendshapeModel, label, prefer=CutSelectingModel,
                                  source=str(run.run_dir))
        tpl = run.run_dir / "stats" / "template.npz"
        if not tpl.exists():
            raise FwkError(f"{tpl}: missing; is {run.run_dir} a finished blendshapes run?")
        self.model = run.model(self.label)
        self.pre = run.preprocessor
        z = load_npz(tpl)  # arrays only, never unpickled; one line naming the file when damaged
        try:
            self.template = template_from_arrays(z)
        except (KeyError, ValueError, TypeError, IndexError) as exc:  # another npz (swapped, edited)
            raise FwkError(f"{tpl}: not the template of a blendshapes run ({type(exc).__name__}: "
                           f"{str(exc)[:120]})") from None
        self.expressions = list(self.model.expressions or [])
        self.units = str((run.metrics.get("dataset") or {}).get("units") or "unit")
        obj = run.run_dir / TEMPLATE_OBJ
        self.template_obj = obj if obj.exists() else tpl  # runs from before template.obj: the npz
        ref = np.asarray(self.pre.mean_centred, dtype=np.float64)  # the mean training neutral, run's units
        if ref.shape != self.template.vertices.shape or not np.all(np.isfinite(ref)):
            raise FwkError(f"{run.run_dir / 'stats' / 'preprocess.npz'}: the mean training neutral has shape "
                           f"{ref.shape} or non-finite values, the model's topology {self.template.vertices.shape}")
        self.ref_size, self.ref_extent = _size(ref)
        fol = run.run_dir / "stats" / "followers.npz"  # a run with follow: moves a full mesh's other parts
        self.followers = None
        if fol.exists():
            from .rig.follow import Followers  # deferred, as every rig module: scipy.spatial off fwk's start-up

            self.followers = Followers.from_state(load_npz(fol), str(fol))

    def factor(self, units: str | float | None) -> float:
        """``--units`` as the factor that takes a neutral into the run's units (1 when None)."""
        if units is None:
            return 1.0
        if isinstance(units, str) and units.strip() in METRES_PER_UNIT:
            if self.units not in METRES_PER_UNIT:
                raise FwkError(f"--units {units.strip()}: the run's units are not stated (its dataset.units is "
                               f"{self.units}); give a factor instead, e.g. --units 0.1")
            return METRES_PER_UNIT[units.strip()] / METRES_PER_UNIT[self.units]
        try:
            f = float(units)
        except ValueError:
            raise FwkError(f"--units {quote(units)}: expected a unit ({', '.join(METRES_PER_UNIT)}) or a factor "
                           f"(a positive number)") from None
        if not (np.isfinite(f) and 1e-9 <= f <= 1e9):
            raise FwkError(f"--units {quote(units)}: a factor must be a finite number from 1e-9 to 1e9")
        return f

    def check_scale(self, path, V: np.ndarray, units=None) -> None:
        """Refuse a neutral V (n, 3), already in the run's units, whose coordinates lie beyond
        ``MAX_COORDINATE``, whose size differs from the training neutrals' by more than
        ``MAX_SCALE_RATIO``, or with a vertex farther than ``MAX_STRAY`` allows (see the module
        docstring); the errors name the file, the measured ratio or the vertex (and its line)."""
        bound = MAX_COORDINATE * self.ref_extent
        far = np.abs(V).max(axis=1)
        if far.max() > bound:
            k = int(np.argmax(far))
            raise DataError(f"{_vertex(path, k)} lies at {_xyz(V[k])}, beyond ±{bound:.3g} {self.units} "
                            f"({MAX_COORDINATE:g} times the training heads' extent): a stray vertex, or other units?")
        size, extent = _size(V)
        ratio = size / self.ref_size if self.ref_size > 0 else 1.0
        if not 1 / MAX_SCALE_RATIO <= ratio <= MAX_SCALE_RATIO:
            given = f" after --units {units}" if units is not None else ""
            raise DataError(f"{path}: {ratio:.3g} times the size of the run's training neutrals{given} (at most "
                            f"{MAX_SCALE_RATIO:g}x either way): {self._hint(ratio)}")
        d = np.linalg.norm(V - np.median(V, axis=0), axis=1)
        limit = MAX_STRAY * ratio * self.ref_extent
        if d.max() > limit:
            k = int(np.argmax(d))
            raise DataError(f"{_vertex(path, k)} lies {d[k]:.4g} {self.units} from the head's centre, "
                            f"{d[k] / (ratio * self.ref_extent):.3g} times the training heads' farthest vertex "
                            f"(at most {MAX_STRAY:g}): a stray vertex?")

    def _hint(self, ratio: float) -> str:
        """The ``--units`` that would fit, or how to give one."""
        need = 1.0 / ratio
        if self.units in METRES_PER_UNIT:
            mine = METRES_PER_UNIT[self.units]
            close = [u for u, m in METRES_PER_UNIT.items() if abs(np.log(m / mine / need)) < np.log(1.3)]
            if close:
                return f"in {close[0]} rather than the run's {self.units}? give --units {close[0]}"
            return (f"give its units with --units (the run's are {self.units}; {', '.join(METRES_PER_UNIT)}) "
                    f"or a factor, e.g. --units {need:.3g}")
        return f"in other units than the run's? give a factor, e.g. --units {need:.3g}"

    def check(self, path, tpl: Template) -> slice | None:
        """None when ``tpl`` (a neutral's topology) is the model's; ``slice(0, n)`` when it is a
        larger mesh whose first n vertices and first triangles are the model's (the full mesh a
        region was cut from); else a TopologyError naming both vertex counts and template.obj."""
        n = self.template.n_vertices
        m = len(self.template.triangles)
        if tpl.n_vertices == n:
            try:
                check_topology(self.template, tpl, path)
            except TopologyError as exc:
                raise TopologyError(f"{exc} (the model's topology with its UVs: {self.template_obj})") from None
            return None
        if (tpl.n_vertices > n and len(tpl.triangles) > m
                and np.array_equal(tpl.triangles[:m], self.template.triangles)):
            return slice(0, n)
        raise TopologyError(f"{path}: {tpl.n_vertices} vertices, the model expects {n}: wrap your head to the "
                            f"model's topology, {self.template_obj} (its polygons and UVs), or give --landmarks "
                            f"L.json to register it (fwk register)")

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


def _size(V: np.ndarray) -> tuple[float, float]:
    """(median, largest) distance of V's vertices from their median point: a size that a few
    stray vertices do not move, and the extent."""
    d = np.linalg.norm(V - np.median(V, axis=0), axis=1)
    return float(np.median(d)), float(d.max())


def _xyz(v) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in v) + ")"


def _vertex(path, k: int) -> str:
    """``path, line N: vertex k+1`` (the line found only now, on the way to an error)."""
    try:
        line = line_number(Path(path).read_bytes(), lambda s: s.startswith((b"v ", b"v\t")), k)
    except OSError:
        line = None
    return f"{path}, line {line}: vertex {k + 1}" if line else f"{path}: vertex {k + 1}"


def _inputs(path: Path) -> list[Path]:
    """The neutral OBJs to read: ``path`` itself or the .obj files of folder ``path``."""
    try:
        return _list_inputs(path)
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None


def _list_inputs(path: Path) -> list[Path]:
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


def _read_neutral(f: Path) -> tuple[np.ndarray, Template]:
    """A neutral OBJ's positions and topology; a DataError naming it when a position is not finite."""
    V, tpl = read_obj(f)
    if not np.all(np.isfinite(V)):
        raise DataError(f"{f}: vertex positions contain NaN or infinite values")
    return V, tpl


def parse_formats(text) -> list[str]:
    """``obj,gltf,usd`` -> the distinct formats in order (a one-line error for an unknown one)."""
    items = [f.strip().lower() for f in (text.split(",") if isinstance(text, str) else text) if f.strip()]
    for f in items:
        if f not in FORMATS:
            raise FwkError(f"--format {f}: unknown format (formats: {', '.join(FORMATS)})")
    if not items:
        raise FwkError("--format: give at least one of " + ", ".join(FORMATS))
    out = []
    for f in items:
        if FORMATS[f] not in [FORMATS[x] for x in out]:
            out.append(f)
    return out


def apply(run_dir, neutral, out, model: str | None = None, expressions: list[str] | None = None,
          log=print, registry=None, formats="obj", naming: str = "source", units: str | float | None = None,
          seed_run: int | None = None, say=_stderr, only_mapped: bool = False, landmarks=None,
          carry: str = CARRIES[0], command: str = "fwk apply") -> list[Path]:
    """Write the blendshapes of one neutral (``out/<expression>.obj``, ``out/<neutral>.glb``,
    ``out/<neutral>.usdc`` as ``formats`` asks) or of a folder of neutrals (the same in
    ``out/<stem>/``); returns the written files. ``units``: the neutrals' units or a factor into
    the run's (``--units``; the outputs are written back in the neutrals' units). ``seed_run``:
    of a run with ``seeds:``, the seed whose models to use (default its first, named by ``say``:
    one line on stderr; None: silent). ``only_mapped``: only the shapes the naming maps
    (``--only-mapped``; ``say`` names what was left out). ``landmarks``: a landmark file
    (``fwk.rig.register``): ``neutral`` (one OBJ) may have any topology; the run's template is
    registered to it, predicted on, and every expression carried back onto its own vertices by
    ``carry`` (``--carry``: transfer, Deformation Transfer onto its triangles, ``fwk.rig.carry``; or
    barycentric, ``Registration.carry``), and the registration written as ``fwk register`` writes it
    in ``out/registration/`` (``write_registration``). ``command``: the name the summary line starts with."""
    t0 = time.perf_counter()
    if carry not in CARRIES:
        raise FwkError(f"--carry {carry}: unknown carry (carries: {', '.join(CARRIES)})")
    fmts = parse_formats(formats)
    if "fbx" in fmts:
        import_bpy()  # a missing bpy is said before any work
    if naming not in NAMINGS:
        raise FwkError(f"--naming {naming}: unknown naming (namings: {', '.join(NAMINGS)})")
    if only_mapped:
        check_only_mapped(naming)  # before any work
    neutral, out = Path(neutral), Path(out)
    check_dir(out, "--out", min_free_mb=0)  # before any work (fwk.paths)
    app = Applier(run_dir, model, registry, seed_run=seed_run, say=say)
    k = app.factor(units)
    out_units = units.strip() if isinstance(units, str) and units.strip() in METRES_PER_UNIT else (
        app.units if units is None else next((u for u in METRES_PER_UNIT if app.units in METRES_PER_UNIT and
                                              np.isclose(METRES_PER_UNIT[u], k * METRES_PER_UNIT[app.units])), "unit"))
    t_load = time.perf_counter() - t0
    files = _inputs(neutral)
    if landmarks is not None and (neutral.is_dir() or len(files) != 1):
        raise FwkError(f"--landmarks: one neutral OBJ at a time, not the folder {neutral}")
    meshes, reg = [], None
    for f in files:  # read and check everything before writing anything
        V, tpl = _read_neutral(f)
        if landmarks is not None:  # any topology: the template registered to it (fwk.rig.register)
            reg = register_neutral(app, f, V, tpl, landmarks, units, say=say)
            app.check_scale(f, reg.neutral, units)
            if units is None and reg.unit_name:
                out_units = reg.unit_name
            meshes.append((f, V, tpl, None))
            continue
        region = app.check(f, tpl)
        app.check_scale(f, k * (V if region is None else V[region]), units)
        meshes.append((f, V, tpl, region))
    t1 = time.perf_counter()
    wanted = list(expressions or app.expressions)
    if only_mapped:  # only what is written: the shapes the naming maps and the halves of its combined ones
        wanted = mapped_sources(wanted, naming) or wanted  # none: rename says so in one line below
    if reg is not None:
        preds = app.predict([reg.neutral], wanted)
        preds = [carry_expressions(reg, meshes[0][2], preds[0], carry, say)]  # the neutral's vertices and units
        k = 1.0
    else:
        preds = app.predict([k * (V if r is None else V[r]) for _, V, _, r in meshes], wanted)
    t2 = time.perf_counter()
    fol = app.followers
    if fol is not None and say is not None and any(r is not None and len(V) == fol.n_full for _, V, _, r in meshes):
        say(f"fwk apply: the {fol.n_full - fol.n} vertices outside the model's {fol.n} move with the face "
            f"(the run's followers: {len(fol.summary())} of {len(fol.expressions)} expressions move parts of them)")
    for (f, V, _, region), P in zip(meshes, preds):
        if region is not None and fol is not None and len(V) == fol.n_full:  # the outside follows, in run units
            from .rig.follow import follow

            P.update(follow(app.pre, fol, k * V, P))  # P is in run units here
            region = None  # P holds full meshes now
        for e in list(P):
            P[e] = P[e] / k  # back into the neutral's units
            if not np.all(np.isfinite(P[e])):
                raise FwkError(f"{f}: the model produced non-finite positions for {e}")
            if region is not None:  # the full mesh back: the region predicted, the rest unchanged
                full = V.copy()
                full[region] = P[e]
                P[e] = full
    # every neutral's shapes under the naming, before anything is written (--only-mapped may find none)
    renamed = [rename(P, V, naming, only_mapped) for (_, V, _, _), P in zip(meshes, preds)]
    if only_mapped and renamed and say is not None:
        say(f"{command} {only_mapped_note(list(expressions or app.expressions), list(renamed[0]), naming)}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    except OSError as exc:
        raise FwkError(f"--out {out}: cannot write there ({exc.strerror or exc})") from None
    written, mode = [], file_mode()
    try:
        for (f, V, tpl, region), shapes in zip(meshes, renamed):
            sub = tmp if not neutral.is_dir() else tmp / f.stem
            sub.mkdir(parents=True, exist_ok=True)
            if reg is not None:  # the fit beside the rig: what fwk register writes, in out/registration/
                (sub / "registration").mkdir()
                write_registration(app, Path(str(run_dir)).name, f, V, tpl, reg, units, sub / "registration")
            # the OBJs in a second thread while the rig files are built (their writes and NumPy release
            # the GIL: 51 full ICT heads, 1 s less of fwk rig's 9 s); leaving the block waits for it
            with ThreadPoolExecutor(1) as pool:
                writer = ObjWriter(tpl)
                objs = pool.submit(lambda: [writer.write(sub / f"{e}.obj", X) for e, X in shapes.items()]) \
                    if "obj" in fmts else None
                for fmt in fmts:
                    if fmt == "obj":
                        continue
                    elif FORMATS[fmt] == ".glb":
                        write_glb(sub / f"{f.stem}.glb", V, tpl, shapes, units=out_units, name=f.stem)
                    elif FORMATS[fmt] == ".fbx":
                        write_fbx(sub / f"{f.stem}.fbx", V, tpl, shapes, units=out_units, name=f.stem)
                    else:
                        write_usd(sub / f"{f.stem}{FORMATS[fmt]}", V, tpl, shapes, units=out_units, name=f.stem)
            if objs is not None:
                objs.result()  # an error of the OBJ thread raises here
        out.mkdir(parents=True, exist_ok=True)
        for p in sorted(q for q in tmp.rglob("*") if q.is_file()):
            os.chmod(p, mode)  # the umask's mode, not the 0600 of a temporary file
            dest = out / p.relative_to(tmp)
            dest.parent.mkdir(parents=True, exist_ok=True)
            os.replace(p, dest)
            written.append(dest)
    except OSError as exc:
        raise FwkError(f"--out {out}: writing failed ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    n, t3 = len(meshes), time.perf_counter()
    kept = f" ({len(renamed[0])} shapes written)" if renamed and len(renamed[0]) != len(preds[0]) else ""
    if reg is not None and say is not None:
        say(f"{command}: the registration (neutral.obj, correspondence.npz, report.md, residual.png) -> "
            f"{out / 'registration'}: read report.md before the rig")
    log(f"{command}: {n} neutral(s) x {len(preds[0]) if preds else 0} expression(s){kept} with model {app.label} -> {out} "
        f"({', '.join(fmts)}; loading the {'run' if command == 'fwk apply' else 'model'} {t_load:.2f} s; per neutral: reading {(t1 - t0 - t_load) / max(n, 1):.2f} s, "
        f"predicting {(t2 - t1) / max(n, 1):.2f} s, writing {(t3 - t2) / max(n, 1):.2f} s; total {t3 - t0:.2f} s)")
    return written


def carry_expressions(reg: Registration, tpl: Template, expressions: dict, carry: str = CARRIES[0], say=_stderr) -> dict:
    """Expressions of the registered neutral (template frame) on the neutral's own vertices and
    units: ``transfer`` (``fwk.rig.carry.DeformationCarry`` on its triangles) or ``barycentric``."""
    if carry == "barycentric":
        return {e: reg.carry(P) for e, P in expressions.items()}
    from .rig.carry import DeformationCarry

    t0 = time.perf_counter()
    dc = DeformationCarry(reg, tpl.triangles)
    out = {e: dc.carry(P) for e, P in expressions.items()}
    if say:
        say(f"fwk apply: {len(out)} expression(s) carried by Deformation Transfer onto the neutral's "
            f"{len(tpl.triangles)} triangles in {time.perf_counter() - t0:.1f} s (set-up {dc.seconds:.1f} s)")
    return out


def register_neutral(app: Applier, path, V: np.ndarray, tpl: Template, landmarks, units=None,
                     say=_stderr) -> Registration:
    """The run's template registered to a neutral of any topology (``fwk.rig.register``) with the
    landmark file ``landmarks``; ``units``: the neutral's (``--units``), else detected."""
    from .rig.register import read_landmarks, register

    ids, points = read_landmarks(landmarks, app.template.n_vertices, V)
    u = None if units is None else app.factor(units)
    if len(tpl.triangles) == 0:
        raise DataError(f"{path}: no polygons (a point cloud cannot be registered)")
    ref = np.asarray(app.pre.mean_centred, dtype=np.float64)  # the mean training neutral in the run's units
    return register(ref, app.template.triangles, V, tpl.triangles, ids, points, units=u,
                    template_units=app.units, say=say)


def add_register_parser(subparsers):
    p = subparsers.add_parser(
        "register", help="register a run's template to a head of any topology (landmark-guided non-rigid ICP)",
        description="Fit the template of a blendshapes run to SCAN.obj (any vertex count, order, units and "
                    "placement) guided by landmark pairs; write the neutral in the template's topology, the "
                    "correspondence of the scan's vertices and a report.")
    p.add_argument("scan", help="the head, an .obj of any topology")
    p.add_argument("--template", required=True, metavar="RUN|MODEL",
                   help="a finished `fwk run` directory of task blendshapes, or a shipped rig model's name "
                        "(fwk list --kind rig)")
    p.add_argument("--landmarks", required=True, metavar="L.json", help='pairs {"landmarks": [{"template": ID, '
                   '"scan": ID or [x, y, z]}, ...]}, 0-based vertex ids, at least 5 (docs/rig-quickstart.md)')
    p.add_argument("--out", required=True, help="output folder: neutral.obj, correspondence.npz, report.md")
    p.add_argument("--units", default=None, help="the scan's units (mm, cm, m, um, in, ft; or a factor into the "
                   "run's units); default: detected from the landmarks' size against the template's")
    p.add_argument("--seed-run", type=int, default=None, metavar="S", help="of a run with seeds: the seed's template")
    p.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS, help="no messages")
    return p


def write_registration(app: Applier, source: str, f: Path, V: np.ndarray, tpl: Template, reg: Registration,
                       units, out: Path) -> tuple[list[Path], dict, str]:
    """The registration of the neutral ``f`` (vertices V, polygons tpl) in the folder ``out``, which
    exists: ``neutral.obj`` (the run's template topology and UVs, in the scan's frame and units),
    ``correspondence.npz`` (``Registration.arrays``), ``residual.png`` (where the renderer works)
    and ``report.md``; ``source``: the run's or model's name for the report's title. Returns (the
    files written, ``reg.summary()``, the residual's unit); OSError passes through."""
    from .rig.register import FADE, FIT_TOLERANCE, LANDMARK_OFF, render_residual

    obj = Path(app.template_obj)
    tt = read_obj(obj)[1] if obj.suffix == ".obj" else app.template
    sm = reg.summary()
    unit = reg.unit_name or (units if isinstance(units, str) and units.strip() in METRES_PER_UNIT else "scan units")
    lines = [f"# Registration of {f.name} to {source}", "",
             f"- scan: {len(V)} vertices, {len(tpl.triangles)} triangles; template: {app.template.n_vertices} "
             f"vertices ({obj})",
             f"- units: one scan unit = {reg.unit:.4g} {app.units}" + (f" ({reg.unit_name}, detected from the "
             f"landmarks' size)" if units is None and reg.unit_name else " (given)" if units is not None else
             " (no named unit fits: the scan was brought to the template's landmark size)"),
             f"- landmarks: {len(reg.template_landmarks)} pairs; each one's distance from where the others' "
             f"similarity places it: at most {sm['landmark_residual_max']:.4g} {unit}"
             + (f"; **likely misplaced: {', '.join(f'landmark {i + 1} (template vertex {reg.template_landmarks[i]})' for i in sm['landmarks_off'])}** "
                f"(farther than {LANDMARK_OFF:g} of the landmarks' spread): check the landmark file"
                if sm["landmarks_off"] else " (none farther than {:g} of the landmarks' spread)".format(LANDMARK_OFF)),
             f"- residual (scan vertex to the registered template's surface), fitted vertices: mean "
             f"{sm['residual_mean']:.4g}, max {sm['residual_max']:.4g} {unit}; all vertices: mean "
             f"{sm['residual_mean_all']:.4g}, max {sm['residual_max_all']:.4g}",
             f"- not fitted: {sm['not_fitted']} of {sm['scan_vertices']} scan vertices farther than "
             f"{sm['tolerance']:.4g} {unit} ({FIT_TOLERANCE:g} median template edges) from the registered template: "
             f"they move with a weight falling linearly to 0 at {FADE:g}x that distance; {sm['still']} stay still "
             f"(`fitted`, `weight` in correspondence.npz)",
             f"- template vertices with no scan within that distance: {sm['template_missing']} "
             f"(`template_missing`)",
             f"- folded triangles of the registered template (turned over or collapsed against the template's): "
             f"{sm['folded']} (`folded`)" + (": **check the landmarks** (a pair given for the wrong side, a point "
                                             "off the head); the rig bends where they are" if sm["folded"] else ""),
             f"- time: {sm['seconds']:.1f} s", ""]
    written = [ObjWriter(tt).write(out / "neutral.obj", reg.to_scan(reg.neutral))]
    np.savez(out / "correspondence.npz", **reg.arrays())
    written.append(out / "correspondence.npz")
    try:  # the scan coloured by its residual; a machine that cannot draw keeps the numbers
        written.append(render_residual(reg, tpl.triangles, out / "residual.png", unit))
        lines += ["Your vertices coloured by their residual (`distance` in correspondence.npz; in the "
                  "template's frame, front and side; the colour bar ends at the 99th percentile, ≥ where "
                  "larger ones saturate):", "", "![residual](residual.png)", ""]
    except OSError:
        raise
    except Exception as exc:  # any renderer failure (no OpenGL, a broken VTK) is not the registration's
        lines += [f"No residual render ({type(exc).__name__}: {str(exc)[:160]}).", ""]
    (out / "report.md").write_text("\n".join(lines))
    written.append(out / "report.md")
    return written, sm, unit


def register_scan(run_dir, scan, landmarks, out, units=None, seed_run: int | None = None, log=print,
                  say=_stderr) -> list[Path]:
    """``fwk register``: writes ``out/neutral.obj`` (the run's template topology and UVs, in the
    scan's frame and units), ``out/correspondence.npz`` (``Registration.arrays``) and
    ``out/report.md``; returns them."""
    scan, out = Path(scan), Path(out)
    check_dir(out, "--out", min_free_mb=0)
    (f,) = _inputs(scan) if not scan.is_dir() else (None,)
    if f is None:
        raise DataError(f"{scan}: fwk register takes one .obj, not a folder")
    V, tpl = _read_neutral(f)
    app = Applier(run_dir, None, None, seed_run=seed_run, say=say)
    reg = register_neutral(app, f, V, tpl, landmarks, units, say=say)
    app.check_scale(f, reg.neutral, units)
    try:
        out.mkdir(parents=True, exist_ok=True)
        written, sm, unit = write_registration(app, Path(run_dir).name, f, V, tpl, reg, units, out)
    except OSError as exc:
        raise FwkError(f"--out {out}: writing failed ({exc.strerror or exc})") from None
    log(f"fwk register: {f} -> {out} (residual mean {sm['residual_mean']:.4g}, max {sm['residual_max']:.4g} {unit}; "
        f"{sm['not_fitted']} vertices not fitted; {sm['seconds']:.1f} s)")
    return written


def run_register(args) -> int:
    """``fwk register``'s entry (cli.EXTRA_COMMANDS)."""
    quiet = getattr(args, "quiet", False)
    register_scan(args.template, args.scan, args.landmarks, args.out, units=args.units, seed_run=args.seed_run,
                  log=(lambda *_: None) if quiet else print, say=None if quiet else _stderr)
    return 0


def run_apply(args) -> int:
    """``fwk apply``'s entry (cli.EXTRA_COMMANDS)."""
    quiet = getattr(args, "quiet", False)
    apply(args.run_dir, args.neutral, args.out, getattr(args, "model", None), getattr(args, "expressions", None),
          log=(lambda *_: None) if quiet else print, formats=getattr(args, "format", "obj"),
          naming=getattr(args, "naming", "source"), units=getattr(args, "units", None),
          seed_run=getattr(args, "seed_run", None), say=None if quiet else _stderr,
          only_mapped=getattr(args, "only_mapped", False), landmarks=getattr(args, "landmarks", None),
          carry=getattr(args, "carry", CARRIES[0]))
    return 0
