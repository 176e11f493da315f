"""Shipped rig models: ``fwk pack`` writes one from a finished blendshapes run, ``fwk rig`` uses it.

A *rig model* is a folder laid out as a run directory that holds only what ``fwk apply`` needs
(so ``fwk apply``, ``fwk register`` and ``fwk rig`` open it as they open a run):

    recipe.yaml versions.json split.json     the run's (one seed's) recipe, versions, identities
    metrics.json                             the dataset's units and scale, the model to apply
    stats/preprocess.npz template.npz        the mean training neutral, the dataset scale, topology
    stats/followers.npz                      (when the run had ``follow:``) the parts outside the region
    models/<label>.safetensors               the model's packed state (safetensors + JSON: no code runs
                                             on load, ``fwk.safeio``)
    card.json                                what it is: recipe, commit, identities, epochs, test metrics
    and the files given with ``--include`` (a licence, an attribution)

``fwk pack RUN --out DIR [--model LABEL] [--seed-run S] [--include FILE ...]`` writes it. The
model's state is its ``packed_state()`` when it plays ``fwk.protocols.Packable`` (pbs: the k sweep's
curves and the networks' derived buffers left out, the spectral basis cut at the largest chosen k;
dt from the mean subject: only the vertices each expression moves), else its ``state_dict()``,
stored narrow (``fwk.safeio.narrow``; widened again on load): every float array as float32 and
ids as int32, and with ``--precision mixed`` the float arrays of at least 65,536 values (network
weights, the basis) as float16; the stats npz files likewise (their integers kept). The
packed model is then reopened from DIR and both it and the run's model predict every expression
for the run's mean training neutral: the largest difference, in the run's units and as a share of
the largest displacement, is printed and recorded in card.json, and a difference above
``MAX_PACK_ERROR`` (0.1 %) of the largest displacement is refused (nothing is written).

``card.json`` records: the model's label and description, the recipe (its name and text's SHA-256),
the git commit of the run, the training, validation and test identities (``split.json``), the
epochs each network trained, and the test metrics per expression (mean over the test identities,
in the dataset's units where the metric has them) of the packed model and of every other model
of the run (the baselines, e.g. Deformation Transfer), from the run's ``metrics.json``.

Rig models that ship with fwk live in ``fwk/shipped/<name>/`` (package data); ``fwk list`` shows
them (kind ``rig``, one row each) and ``fwk show rig NAME`` prints their card. ``fwk rig NEUTRAL.obj --out DIR`` writes the rig
of one neutral (or a folder of them) with the shipped model (``--model NAME`` or a folder written by
``fwk pack``): by default OBJ, glb and USD with the ARKit-named shapes only (``fwk apply``'s
``--naming arkit --only-mapped``); ``--all-shapes`` keeps every shape, ``--landmarks`` rigs a head of
another topology (``fwk register``).
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from .apply import CARRIES, FORMATS, apply
from .cache import dir_mode
from .errors import FwkError
from .lifecycle import choose_model, open_run, read_run_recipe
from .paths import check_dir
from .protocols import BLENDSHAPES, BlendshapeModel, CutSelectingModel, Packable
from .runs import RECIPE_HASH, recipe_hash
from .rig.shipped import CARD, shipped, shipped_or_path
from .safeio import NARROWED, PRECISIONS, load_json, load_npz, narrow, save_state

#: the largest difference between a packed model's predictions and the run's model's, as a share
#: of the largest predicted displacement, that ``fwk pack`` accepts
MAX_PACK_ERROR = 1e-3
_STATS = ("preprocess.npz", "template.npz", "followers.npz")
_COPIED = ("recipe.yaml", "split.json")


def _narrow_npz(src: Path, dest: Path, precision: str) -> None:
    """Copy a stats npz with its float arrays narrowed as the model's state (``fwk.safeio.narrow``;
    integer arrays kept: the readers of stats/ take them as they are), zip-compressed."""
    z = load_npz(src)
    np.savez_compressed(dest, **{k: narrow(v, precision) if v.dtype.kind == "f" else v for k, v in z.items()})


def _versions(run_dir: Path) -> dict:
    """The versions.json of the run (a seed's sub-run: its parent's)."""
    for d in (run_dir, run_dir.parent):
        p = d / "versions.json"
        if p.is_file():
            try:
                v = json.loads(p.read_text())
                return v if isinstance(v, dict) else {}
            except (OSError, ValueError):
                return {}
    return {}


def _test_metrics(metrics: dict) -> dict:
    """{expression: {model: {metric: {"mean": .., "units": ..}}}} from a blendshapes run's
    metrics.json (the dataset's units where the metric has them, ``mean_input``)."""
    out = {}
    for e, models in (metrics.get(BLENDSHAPES) or {}).items():
        if not isinstance(models, dict):
            continue
        row = {}
        for label, ms in models.items():
            if not isinstance(ms, dict) or ":" in label:  # a model's own parts (pbs's networks): not kept
                continue
            row[label] = {}
            for m, v in ms.items():
                if isinstance(v, dict) and "mean" in v:
                    inp = "mean_input" in v
                    row[label][m] = {"mean": float(v["mean_input"] if inp else v["mean"]),
                                     "units": str(v.get("units_input") if inp else v.get("units", ""))}
        out[e] = row
    return out


def _epochs(metrics: dict, label: str) -> dict:
    nets = ((metrics.get("training") or {}).get("networks") or {})
    return {k: {f: v.get(f) for f in ("epochs_run", "max_epochs", "stopped_by", "plateau") if f in v}
            for k, v in nets.items() if k.split("/")[0] == label and isinstance(v, dict)}


def pack(run_dir, out, model: str | None = None, seed_run: int | None = None, include=(), precision="float32",
         log=print, say=None) -> Path:
    """Write the rig model of ``run_dir``'s model ``model`` (default: the run's ``apply_model``,
    else chosen by role) into the new folder ``out``; returns ``out``."""
    t0 = time.perf_counter()
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise FwkError(f"--out {out}: exists and is not an empty folder (fwk pack writes a new rig model folder)")
    check_dir(out, "--out", min_free_mb=0)
    files = [Path(f) for f in include]
    taken = {*_COPIED, "versions.json", "metrics.json", CARD, "stats", "models"}
    for f in files:
        if not f.is_file():
            raise FwkError(f"--include {f}: no such file")
        if f.name in taken:
            raise FwkError(f"--include {f}: its name is taken (by the rig model's own {f.name} or another --include)")
        taken.add(f.name)
    run = open_run(run_dir, seed_run=seed_run, say=say or (lambda m: None))
    label = model or run.metrics.get("apply_model") or run.params.get("apply_model")
    label = choose_model(run.specs, BlendshapeModel, label, prefer=CutSelectingModel, source=str(run.run_dir))
    src = run.run_dir
    m = run.model(label)
    if precision not in PRECISIONS:
        raise FwkError(f"--precision {precision}: one of {', '.join(PRECISIONS)}")
    state = narrow(m.packed_state() if isinstance(m, Packable) else m.state_dict(), precision)
    metrics = run.metrics
    out.parent.mkdir(parents=True, exist_ok=True)  # the temporary folder beside out: os.replace stays on one disk
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for name in _COPIED:
            if (src / name).is_file():
                shutil.copyfile(src / name, tmp / name)
        (tmp / "stats").mkdir()
        for name in _STATS:
            if (src / "stats" / name).is_file():
                _narrow_npz(src / "stats" / name, tmp / "stats" / name, precision)
        (tmp / "models").mkdir()
        save_state(tmp / "models" / f"{label}.safetensors", state,
                   {"model": f"{type(m).__module__}.{type(m).__qualname__}", "name": m.name, "label": label,
                    NARROWED: precision})
        versions = _versions(src)
        (tmp / "versions.json").write_text(json.dumps({**versions, RECIPE_HASH: recipe_hash(tmp)}, indent=2))
        slim = {k: metrics[k] for k in ("dataset", "expressions", "apply_model", "legend") if k in metrics}
        slim["apply_model"] = label
        (tmp / "metrics.json").write_text(json.dumps(slim, indent=2))
        for f in files:
            shutil.copyfile(f, tmp / f.name)
        # the packed model reopened from the new folder against the run's, on the mean training neutral
        packed = open_run(tmp).model(label)
        X = np.asarray(load_npz(src / "stats" / "template.npz")["mean_neutral"], dtype=np.float64)[None]
        exprs = list(m.expressions or [])
        want, got = m.predict_all(X, exprs), packed.predict_all(X, exprs)
        scale = float((metrics.get("dataset") or {}).get("scale") or 1.0)  # evaluation space per run unit
        diff = max(float(np.abs(np.asarray(got[e]) - np.asarray(want[e])).max()) for e in exprs) / scale
        disp = max(float(np.abs(np.asarray(want[e]) - X).max()) for e in exprs) / scale
        units = str((metrics.get("dataset") or {}).get("units") or "units")
        share = diff / disp if disp > 0 else 0.0
        if not np.isfinite(diff) or share > MAX_PACK_ERROR:
            raise FwkError(f"fwk pack: the packed model differs from the run's by {diff:.3g} {units} on the mean "
                           f"neutral ({100 * share:.3g} % of the largest displacement, {disp:.3g} {units}; at most "
                           f"{100 * MAX_PACK_ERROR:g} %): not written")
        card = {
            "name": out.name, "model": label,
            "description": (metrics.get("legend") or {}).get(label, ""),
            "recipe": str(read_run_recipe(src).get("name") or ""),
            "recipe_sha256": recipe_hash(tmp),
            "packed_from": "/".join(src.resolve().parts[-2:] if src.name.startswith("seed-") else [src.name]),
            "commit": versions.get("git_commit"), "commit_dirty": versions.get("git_dirty"),
            "torch": versions.get("torch"), "threads": versions.get("threads"),
            "dataset": metrics.get("dataset"),
            "identities": load_json(src / "split.json") if (src / "split.json").is_file() else None,
            "epochs": _epochs(metrics, label),
            "k": dict(m.k) if isinstance(m, CutSelectingModel) else {},
            "test": _test_metrics(metrics),
            "pack": {"precision": precision,
                     "largest_difference": diff, "largest_displacement": disp, "units": units,
                     "bytes": (tmp / "models" / f"{label}.safetensors").stat().st_size},
            "included": [f.name for f in files],
        }
        (tmp / CARD).write_text(json.dumps(card, indent=2))
        if out.exists():
            out.rmdir()
        os.chmod(tmp, dir_mode())  # mkdtemp's 0700 -> the umask's mode, as a folder made by mkdir
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    log(f"fwk pack: {label} of {src} -> {out} ({size / 1e6:.1f} MB; model file "
        f"{card['pack']['bytes'] / 1e6:.1f} MB, {precision}); on the mean neutral the packed model "
        f"predicts within {diff:.3g} {units} of the run's ({100 * share:.3g} % of the largest displacement, "
        f"{disp:.3g} {units}); {time.perf_counter() - t0:.1f} s")
    return out


# ----------------------------------------------------------------------------- shipped models

def read_card(folder: Path) -> dict:
    card = load_json(Path(folder) / CARD)
    if not isinstance(card, dict):
        raise FwkError(f"{Path(folder) / CARD}: not a rig model's card")
    return card


def find_model(name: str | None) -> Path:
    """A shipped model's folder by name (None: the only one, or ``DEFAULT``), or a folder ``fwk
    pack`` wrote (one with a card.json), or a run directory. A path that exists is taken as that
    path, as every command that takes a run does (``fwk.rig.shipped.shipped_or_path``): a folder
    in the working directory called like a shipped model wins, and is refused when it is neither."""
    have = shipped()
    if name is None:
        if DEFAULT in have:
            return have[DEFAULT]
        if len(have) == 1:
            return next(iter(have.values()))
        raise FwkError("fwk rig: no rig model ships with this installation; give --model FOLDER (fwk pack)"
                       if not have else f"fwk rig: give --model (shipped: {', '.join(have)})")
    p = shipped_or_path(name)
    if (p / CARD).is_file():
        return p
    if p.is_dir() and (p / "recipe.yaml").is_file():
        return p  # a run directory: fwk rig applies it as fwk apply would
    if p.exists() and name in have:
        raise FwkError(f"--model {name}: {p} in the working directory is neither a folder written by fwk pack nor "
                       f"a run, and a path is taken before a shipped model's name (the shipped {name}: "
                       f"{have[name]})")
    raise FwkError(f"--model {name}: neither a shipped rig model ({', '.join(have) or 'none'}) nor a folder "
                   f"written by fwk pack or fwk run")


#: the shipped model ``fwk rig`` uses without --model
DEFAULT = "ict-face"
#: the kind ``fwk list`` and ``fwk show`` give the shipped rig models (no plugin kind: package data)
RIG_KIND = "rig"


def card_summary(card: dict) -> str:
    """One line for ``fwk list``."""
    ids = card.get("identities") or {}
    ep = [v.get("epochs_run") for v in (card.get("epochs") or {}).values() if v.get("epochs_run") is not None]
    n = {k: len(v) for k, v in ids.items() if isinstance(v, list)}
    ds = card.get("dataset") or {}
    return (f"{card.get('model')} ({card.get('recipe')}) on {ds.get('name', '?')}, {ds.get('n_vertices', '?')} vertices; "
            f"identities train {n.get('train', '?')} / val {n.get('val', '?')} / test {n.get('test', '?')}; "
            f"epochs {', '.join(map(str, ep)) or '?'}; commit {str(card.get('commit') or '?')[:10]}; {_wins(card)}")


def _others(card: dict) -> list[str]:
    """The card's other models (the baselines of its run), in name order."""
    return sorted({k for row in (card.get("test") or {}).values() for k in row if k != card.get("model")})


def _against_best(row: dict, label: str, others: list[str], metric: str) -> tuple[float, float] | None:
    """(the model's test mean, the lowest of the others') of one expression's row, None when either
    is missing."""
    a = ((row.get(label) or {}).get(metric) or {}).get("mean")
    bs = [b for b in (((row.get(o) or {}).get(metric) or {}).get("mean") for o in others) if b is not None]
    return None if a is None or not bs else (a, min(bs))


def _wins(card: dict, metrics=("l1", "dame", "fmpd")) -> str:
    """'test: lower than dt on L1 57/57, ...': per metric, the expressions where the model's test
    mean is below the best other model's (the baselines of its run)."""
    label, test, others = card.get("model"), card.get("test") or {}, _others(card)
    counts = []
    for mm in metrics:
        pairs = [p for p in (_against_best(row, label, others, mm) for row in test.values()) if p is not None]
        counts.append(f"{mm.upper()} {sum(a < b for a, b in pairs)}/{len(pairs)}")
    return f"test: lower than {', '.join(others) or 'nothing'} on " + ", ".join(counts)


def card_table(card: dict, metrics=("l1", "dame", "fmpd")) -> str:
    """The card's test metrics: per expression the model's mean and every other model's, with the
    ratio to the best other (below 1: the model is better)."""
    label, test, others = card.get("model"), card.get("test") or {}, _others(card)
    lines = []
    units = {}
    for row in test.values():
        for mm in metrics:
            u = ((row.get(label) or {}).get(mm) or {}).get("units")
            if u:
                units[mm] = u
    head = ["expression"] + [f"{mm.upper()} ({units.get(mm, '')})".replace(" ()", "") for mm in metrics]
    lines.append(f"test identities: {label} against {', '.join(others) or 'nothing'}; each cell: {label} / best "
                 f"other (ratio; below 1: {label} lower)")
    lines.append(" | ".join(head))
    for e, row in test.items():
        cells = [e]
        for mm in metrics:
            pair = _against_best(row, label, others, mm)
            if pair is None:
                cells.append("-")
                continue
            a, b = pair
            cells.append(f"{a:.4g} / {b:.4g} ({a / b:.2f})" if b > 0 else f"{a:.4g} / {b:.4g}")
        lines.append(" | ".join(cells))
    lines.append(_wins(card, metrics))
    return "\n".join(lines)


def show_card(name: str) -> str:
    folder = find_model(name)
    card = read_card(folder)
    p = card.get("pack") or {}
    lines = [f"rig model {card.get('name')}  ({folder})", "", str(card.get("description") or ""), "",
             card_summary(card),
             f"recipe sha256 {card.get('recipe_sha256')}; packed from {card.get('packed_from')}",
             f"stored {p.get('precision')}, model file {int(p.get('bytes') or 0) / 1e6:.1f} MB; on the mean neutral it "
             f"predicts within {p.get('largest_difference', float('nan')):.3g} {p.get('units', '')} of the trained model",
             f"files beside it: {', '.join(card.get('included') or []) or 'none'}", "", card_table(card)]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- commands

def add_pack_parser(subparsers):
    p = subparsers.add_parser("pack", help="write a rig model (the files fwk rig needs) from a blendshapes run",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", help="a finished `fwk run` directory of task blendshapes")
    p.add_argument("--out", required=True, help="the new rig model folder")
    p.add_argument("--model", help="the model's label (default: the run's apply_model)")
    p.add_argument("--seed-run", type=int, metavar="S", help="of a run with seeds: the seed whose model to pack")
    p.add_argument("--include", action="append", default=[], metavar="FILE",
                   help="a file to ship beside the model (a licence, an attribution); repeatable")
    p.add_argument("--precision", choices=PRECISIONS, default=PRECISIONS[0],
                   help="float32 (default): every float array as float32; mixed: arrays of 65,536 values or more "
                        "(network weights, a basis) as float16, the rest float32")
    return p


def run_pack(args) -> int:
    pack(args.run_dir, args.out, args.model, args.seed_run, args.include, args.precision)
    return 0


def add_rig_parser(subparsers):
    p = subparsers.add_parser("rig", help="a blendshape rig for your head with a shipped rig model (no training)",
                              description="Write the rig of NEUTRAL.obj (or of each .obj in a folder) with a rig "
                                          "model that ships with fwk (fwk list) or one written by fwk pack.")
    p.add_argument("neutral", help="a neutral head (.obj) in the model's topology, or a folder of them; any "
                                   "topology with --landmarks")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--model", help=f"a shipped rig model's name (default {DEFAULT}) or a folder from fwk pack")
    p.add_argument("--format", default="obj,gltf,usd", help=f"comma-separated: {', '.join(FORMATS)} "
                                                           "(default obj,gltf,usd)")
    p.add_argument("--naming", default="arkit", help="shape names: arkit (default) or source")
    p.add_argument("--all-shapes", action="store_true",
                   help="keep the shapes without an ARKit name (default with --naming arkit: ARKit's only)")
    p.add_argument("--expressions", nargs="*", default=None,
                   help="only these of the model's expressions, by its own names (as fwk apply)")
    p.add_argument("--units", help="the neutral's units (mm, cm, m, in, ...) or a factor into the model's")
    p.add_argument("--landmarks", metavar="L.json", help="landmarks for a head of another topology (fwk register)")
    p.add_argument("--carry", choices=CARRIES, default=CARRIES[0],
                   help="with --landmarks: how expressions reach your vertices")
    return p


def run_rig(args) -> int:
    folder = find_model(args.model)
    exprs = args.expressions or None
    only = args.naming == "arkit" and not args.all_shapes
    apply(folder, args.neutral, args.out, None, exprs, formats=args.format, naming=args.naming, units=args.units,
          only_mapped=only, landmarks=args.landmarks, carry=args.carry, command="fwk rig")
    return 0
