"""``fwk convert RUN --trust``: rewrite a run of an earlier fwk in the safe format.

Earlier versions saved models (``models/<label>.pt``) and Lightning checkpoints (``*.ckpt``) with
``torch.save``: pickles, which run whatever code they name when they are opened. fwk no longer
opens them (``fwk.safeio``); this command does, once, for a run its user trusts: it unpickles
every such file of the run (sub-runs included: an edit's ``reconstruct/``, a grid's members) and
rewrites it in ``fwk.safeio``'s format (``models/<label>.safetensors``; checkpoints in place),
then records the SHA-256 of each ``recipe.yaml`` that has none (``--resume`` checks it). Without
``--trust`` it only lists what it would unpickle. A file that holds anything but tensors and
plain data is refused, naming the file (nothing of the run is changed then).
"""
from __future__ import annotations

import json
from pathlib import Path

from .errors import FwkError

# torch is imported when a run is converted, never at module import (`fwk --help` imports this module)


def add_convert_parser(subparsers):
    """Register ``fwk convert`` on the CLI's subparsers."""
    p = subparsers.add_parser(
        "convert", help="rewrite a run of an earlier fwk (pickled models and checkpoints) in the safe format; "
                        "unpickles: --trust",
        description="Unpickle the pickled model files (models/<label>.pt) and checkpoints (*.ckpt) that earlier "
                    "versions of fwk wrote in RUN_DIR and its sub-runs, and rewrite them in the safe format "
                    "(tensors and plain data, never code). Unpickling runs any code the files hold: convert only "
                    "runs you trust. Without --trust, lists the files.")
    p.add_argument("run_dir", help="a run directory written by an earlier version of fwk")
    p.add_argument("--trust", action="store_true",
                   help="unpickle the files (this runs any code they hold: only for a run you trust)")
    return p


def _model_ids(run: Path) -> dict:
    """label -> the class ``fwk.lifecycle`` records for each model of the run's recipe (empty if
    the recipe does not resolve today)."""
    from .plugins import get_registry
    from .recipes import read_recipe_file, resolve

    try:
        data = read_recipe_file(run / "recipe.yaml", "run recipe")  # every check of a recipe file
        specs = resolve(data, get_registry()).task.params.get("models") or {}
        return {label: (f"{s.cls.__module__}.{s.cls.__qualname__}", s.name) for label, s in specs.items()}
    except Exception:  # an old recipe that no longer validates: the files are converted without the class
        return {}


def convert_run(run_dir, trust: bool, say=print) -> list[Path]:
    """Convert ``run_dir`` (see the module docstring); returns the files rewritten."""
    from .runs import RECIPE_HASH, recipe_hash, run_state, write_json
    from .safeio import pickled_files

    run_dir = Path(run_dir)
    if not run_dir.is_dir() or not (run_dir / "recipe.yaml").is_file():
        raise FwkError(f"{run_dir}: not a run directory (no recipe.yaml)")
    if run_state(run_dir)[0] == "running":
        raise FwkError(f"{run_dir}: still running; convert it when it has finished")
    files = pickled_files(run_dir)
    if not trust:
        if not files:
            say(f"{run_dir}: no pickled files; nothing to convert")
            return []
        names = ", ".join(str(p.relative_to(run_dir)) for p in files[:4]) + (" ..." if len(files) > 4 else "")
        raise FwkError(f"fwk convert {run_dir}: would unpickle {len(files)} file{'s' if len(files) != 1 else ''} "
                       f"({names}), which runs any code they hold; add --trust if you trust who made the run")
    import torch  # deferred: ~1 s of import time

    from .safeio import SUFFIX, UnsafeStateError, dumps_state
    from .cache import atomic_write_bytes

    if files:
        say(f"fwk convert: unpickling {len(files)} file{'s' if len(files) != 1 else ''} of {run_dir} (this runs any "
            f"code they hold) and rewriting {'them' if len(files) != 1 else 'it'} in the safe format")
    ids: dict = {}
    plan = []  # (old path, new path, bytes): every file converted before any is replaced
    for p in files:
        try:
            state = torch.load(p, map_location="cpu", weights_only=False)
        except Exception as exc:
            raise FwkError(f"{p}: cannot be unpickled ({type(exc).__name__}: {str(exc)[:160]}); nothing converted") \
                from None
        meta = None
        if p.parent.name == "models":
            run = p.parent.parent
            if run not in ids:
                ids[run] = _model_ids(run)
            label = p.name[:-len(p.suffix)]
            cls, name = ids[run].get(label, (None, None))
            meta = {"label": label, **({"model": cls, "name": name} if cls else {})}
            target = p.with_name(f"{label}{SUFFIX}")
        else:
            target = p
        try:
            plan.append((p, target, dumps_state(state, meta)))
        except UnsafeStateError as exc:
            raise FwkError(f"{p}: holds what the safe format cannot store ({exc}); nothing converted") from None
    for old, new, data in plan:
        atomic_write_bytes(new, data)
        if old != new:
            old.unlink()
        say(f"  {new.relative_to(run_dir)}")
    for rec in sorted(run_dir.rglob("recipe.yaml")):  # the recipe each run holds, recorded for --resume
        versions = rec.parent / "versions.json"
        if not versions.is_file():
            continue
        try:
            stored = json.loads(versions.read_text())
        except ValueError:
            continue
        if isinstance(stored, dict) and RECIPE_HASH not in stored:
            stored[RECIPE_HASH] = recipe_hash(rec.parent)
            write_json(versions, stored)
    say(f"converted {len(plan)} file{'s' if len(plan) != 1 else ''}: {run_dir} opens with this fwk")
    return [new for _, new, _ in plan]


def run_convert(args) -> int:
    convert_run(Path(args.run_dir), args.trust)
    return 0
