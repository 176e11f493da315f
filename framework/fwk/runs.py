"""Run directories and the run context every task and model receives.

``fwk run recipes/x.yaml`` writes ``runs/<name>-<UTC yyyymmdd-HHMMSS>/`` (or under
``--runs-dir`` / ``FWK_RUNS_DIR``), never overwriting; every file is written atomically.
A user's mistake found while validating writes no run directory; one found while running
(a bad mesh file, say) removes the directory this invocation created.
"""
from __future__ import annotations

import copy
import datetime as _dt
import io
import json
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Iterable

import numpy as np
import yaml
from tqdm.auto import tqdm

from . import __version__
from .cache import Cache, atomic_write_bytes
from .engine.config import TrainConfig
from .engine.threads import register
from .errors import FwkError
from .plugins import get_registry
from .recipes import Spec, load_recipe, make_spec, resolve, to_plain
from .registry import Registry

SCOPED = ("checkpoints", "tb", "curves")  # per network, under the model's label


def _default_device() -> str:
    """``cuda`` when available, else ``cpu``."""
    # deferred: torch costs ~1 s of import time (measured with python -X importtime) that
    # `fwk --help` and `fwk report`, which load this module, need not pay
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return to_plain(o)


def write_json(path: Path, obj) -> None:
    """Write ``obj`` as indented JSON (NumPy values, paths, specs and dataclasses converted),
    atomically."""
    atomic_write_bytes(Path(path), (json.dumps(obj, indent=2, default=_json_default, allow_nan=True) + "\n").encode())


class RunContext:
    """Where a run writes, and the shared services it uses (see COMMON contract in docs)."""

    def __init__(self, run_dir: Path, registry: Registry, cache: Cache | None = None, seed: int = 0,
                 recipe: dict | None = None, train=None, device: str | None = None, quiet: bool = False,
                 resume: bool = False, scope: str | None = None, log_file: Path | None = None):
        self.run_dir = Path(run_dir)
        self.registry = registry
        self.cache = cache or Cache()
        self.seed = int(seed)
        self.recipe = recipe or {}
        self.train = train if train is not None else TrainConfig()
        self.device = device if device is not None else _default_device()
        self.quiet = quiet
        self.resume = resume
        self.scope = scope
        self.source: str | None = None  # the recipe file, for paths relative to it
        self.log_file = log_file if log_file is not None else self.run_dir / "log.txt"

    # files -------------------------------------------------------------------------
    def path(self, *parts) -> Path:
        """``run_dir/parts...`` (checkpoints and TensorBoard events under the scope), its folder
        created."""
        parts = [str(p) for p in parts]
        if self.scope and parts and parts[0] in SCOPED:
            parts = [parts[0], self.scope, *parts[1:]]
        p = self.run_dir.joinpath(*parts)
        p.parent.mkdir(parents=True, exist_ok=True)
        return p

    def write_json(self, rel, obj) -> Path:
        """Write ``obj`` as JSON to ``rel`` in the run directory (atomic); returns the path."""
        p = self.path(rel)
        write_json(p, obj)
        return p

    def write_text(self, rel, text: str) -> Path:
        """Write ``text`` to ``rel`` in the run directory (atomic); returns the path."""
        p = self.path(rel)
        atomic_write_bytes(p, text.encode())
        return p

    def save_npz(self, rel, **arrays) -> Path:
        """Save ``arrays`` as an .npz file at ``rel`` in the run directory (atomic); returns the
        path."""
        p = self.path(rel)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write_bytes(p, buf.getvalue())
        return p

    def save_torch(self, rel, obj) -> Path:
        """``torch.save`` of ``obj`` to ``rel`` in the run directory (atomic); returns the path."""
        import torch  # deferred: see _default_device

        p = self.path(rel)
        buf = io.BytesIO()
        torch.save(obj, buf)
        atomic_write_bytes(p, buf.getvalue())
        return p

    # output ------------------------------------------------------------------------
    def log(self, msg: str) -> None:
        """Print ``msg`` (unless quiet) and append it to the run's log file."""
        if not self.quiet:
            print(msg, flush=True)
        try:
            self.log_file.parent.mkdir(parents=True, exist_ok=True)
            with open(self.log_file, "a") as f:
                f.write(msg.rstrip("\n") + "\n")
        except OSError:
            pass

    def progress(self, iterable: Iterable, desc: str = "", total: int | None = None, **kw):
        """A progress bar over ``iterable``, shown on a terminal unless quiet."""
        disable = self.quiet or not sys.stderr.isatty()
        return tqdm(iterable, desc=desc, total=total, disable=disable, leave=False, dynamic_ncols=True, **kw)

    # components --------------------------------------------------------------------
    def build(self, kind: str, spec, *args, **extra):
        """Build a component of ``kind`` from a Spec, a name or a mapping with ``name``; ``args``
        and ``extra`` go to its constructor."""
        if not isinstance(spec, Spec):
            spec = make_spec(kind, spec, kind, self.registry)
        return spec.build(*args, **extra)

    def child(self, name: str) -> "RunContext":
        """A context for a sub-run in ``run_dir/name`` (its own files and scope, the same log)."""
        c = copy.copy(self)
        c.run_dir = self.run_dir / name
        c.log_file = self.log_file  # one log for the whole run
        c.scope = None
        c.run_dir.mkdir(parents=True, exist_ok=True)
        return c

    def scoped(self, label: str) -> "RunContext":
        """The same run; checkpoints and TensorBoard events go under ``<kind>/<label>/``."""
        c = copy.copy(self)
        c.scope = f"{self.scope}/{label}" if self.scope else label
        return c


def make_test_context(tmp_path, seed: int = 0, registry: Registry | None = None, **train_overrides) -> RunContext:
    """A real RunContext for tests: quiet, CPU, its own cache under tmp_path."""
    train = TrainConfig(**train_overrides) if train_overrides else TrainConfig(epochs=2, batch_size=8)
    tmp_path = Path(tmp_path)
    return RunContext(tmp_path / "run", registry or get_registry(), Cache(tmp_path / "cache"), seed=seed,
                      train=train, device="cpu", quiet=True)


# ----------------------------------------------------------------------------- run dirs

def runs_root(runs_dir: str | None = None) -> Path:
    """Where run directories go: ``runs_dir``, else ``$FWK_RUNS_DIR``, else ``./runs``."""
    return Path(runs_dir or os.environ.get("FWK_RUNS_DIR") or "runs")


def new_run_dir(root: Path, name: str) -> Path:
    """A new directory ``root/<name>-<UTC yyyymmdd-HHMMSS>`` (suffixed -2, -3... if taken), never an
    existing one."""
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%d-%H%M%S")
    root.mkdir(parents=True, exist_ok=True)
    base = root / f"{name}-{stamp}"
    p, i = base, 1
    while True:
        try:
            p.mkdir(parents=False, exist_ok=False)
            return p
        except FileExistsError:
            i += 1
            p = Path(f"{base}-{i}")


def versions(registry: Registry) -> dict:
    """Python, platform, library and plugin versions and the git commit, for ``versions.json``."""
    out = {"python": sys.version.split()[0], "platform": platform.platform(), "fwk": __version__}
    for mod in ("numpy", "scipy", "torch", "lightning", "torch_geometric", "trimesh", "pyvista", "open3d"):
        try:
            m = __import__(mod)
            out[mod] = getattr(m, "__version__", "")
        except Exception:
            pass
    out["plugins"] = {}
    for e in registry:
        out["plugins"].setdefault(e.plugin, e.version)
    try:
        here = Path(__file__).resolve().parent
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=5)
        if commit.returncode == 0:
            out["git_commit"] = commit.stdout.strip()
    except Exception:
        pass
    return out


def run_task(resolved, ctx: RunContext) -> None:
    """Build the recipe's task and run it in ``ctx``."""
    task = resolved.task.build()
    task.run(ctx)


def execute(recipe_path: str, overrides: list[str] | None = None, runs_dir: str | None = None,
            resume: str | None = None, quiet: bool = False, registry: Registry | None = None,
            cache: Cache | None = None, device: str | None = None) -> Path:
    """``fwk run``: validate everything first, then create the run directory and run. The process
    registers among those that share the cores (``fwk.engine.threads``)."""
    registry = registry or get_registry()
    register()
    if resume:
        run_dir = Path(resume)
        if not (run_dir / "recipe.yaml").exists():
            raise FwkError(f"--resume {resume}: not a run directory (no recipe.yaml)")
        data = yaml.safe_load((run_dir / "recipe.yaml").read_text())
        if recipe_path:
            fresh = load_recipe(recipe_path, overrides)
            fresh["source"] = fresh.pop("_source", None)
            if to_plain(fresh) != {k: v for k, v in data.items()}:
                raise FwkError(f"--resume {resume}: the recipe differs from the one the run was started with")
        resolved = resolve(data, registry)
        created = False
    else:
        data = load_recipe(recipe_path, overrides)
        resolved = resolve(data, registry)
        run_dir = new_run_dir(runs_root(runs_dir), resolved.name)
        created = True
    try:
        ctx = RunContext(run_dir, registry, cache, resolved.seed, recipe=resolved.data, train=resolved.train,
                         device=device, quiet=quiet, resume=bool(resume))
        ctx.source = resolved.source
        if created:
            plain = {k: v for k, v in resolved.data.items() if k != "_source"}
            if resolved.source:
                plain["source"] = resolved.source  # the recipe file: relative paths resolve from it
            ctx.write_text("recipe.yaml", yaml.safe_dump(plain, sort_keys=False))
            ctx.write_json("versions.json", versions(registry))
        ctx.log(f"fwk run {resolved.name}: task {resolved.task.name}, run directory {run_dir}")
        run_task(resolved, ctx)
        ctx.log(f"done: {run_dir}")
    except FwkError:
        if created:
            shutil.rmtree(run_dir, ignore_errors=True)
        raise
    return run_dir
