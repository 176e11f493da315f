"""``fwk eval A B``: metrics between two meshes, or two folders of meshes matched by relative path."""
from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import numpy as np

from ..cache import atomic_write_bytes
from ..data.io import read_mesh
from ..errors import DataError, TopologyError
from ..paths import check_dir
from ..plugins import get_registry
from .core import evaluate, summarise
from .presentation import default_metrics

SUFFIXES = (".obj", ".ply")


def _pairs(a: Path, b: Path) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """Pairs of files, and the files (of either folder) without a partner."""
    for p in (a, b):
        if not p.exists():
            raise DataError(f"{p}: no such file or folder")
    if a.is_file() and b.is_file():
        return [(a, b)], []
    if a.is_dir() and b.is_dir():
        rel_a = {p.relative_to(a) for p in a.rglob("*") if p.suffix.lower() in SUFFIXES}
        rel_b = {p.relative_to(b) for p in b.rglob("*") if p.suffix.lower() in SUFFIXES}
        common = sorted(rel_a & rel_b)
        if not common:
            raise DataError(f"{a} and {b}: no mesh files with the same relative path")
        lonely = [a / r for r in sorted(rel_a - rel_b)] + [b / r for r in sorted(rel_b - rel_a)]
        return [(a / r, b / r) for r in common], lonely
    raise DataError(f"{a} and {b}: give two mesh files or two folders")


def _same_topology(pa, ta, pb, tb) -> None:
    """TopologyError naming both files and what differs."""
    if ta.n_vertices != tb.n_vertices:
        raise TopologyError(f"{pa} ({ta.n_vertices} vertices) and {pb} ({tb.n_vertices} vertices) "
                            "do not share a topology")
    if ta.triangles.shape != tb.triangles.shape:
        raise TopologyError(f"{pa} ({len(ta.triangles)} triangles) and {pb} ({len(tb.triangles)} triangles) "
                            "do not share a topology")
    diff = np.flatnonzero((ta.triangles != tb.triangles).any(1))
    if len(diff):
        raise TopologyError(f"{pa} and {pb} have the same vertex count but different faces "
                            f"(first difference at triangle {int(diff[0])})")


def compare_paths(a, b, metrics: list[str] | None = None, maps_dir=None, registry=None) -> dict:
    """Metrics of ``a`` (prediction) against ``b`` (reference): two mesh files, or two folders
    whose OBJ/PLY files are paired by relative path (all with one topology). Returns
    ``{"metrics": {name: {mean, median, max}}, "units": {name: units}, "pairs": count}``;
    ``maps_dir`` receives one .npz of per-vertex maps per pair. User errors raise FwkError
    subclasses naming the files; ``metrics`` default to ``default_metrics(registry)``."""
    registry = registry or get_registry()
    ms = [registry.get("metric", m, key_path="--metrics")() for m in (metrics or default_metrics(registry))]
    pairs, lonely = _pairs(Path(a), Path(b))
    template = None
    P, T = [], []
    for pa, pb in pairs:
        Va, ta = read_mesh(pa)
        Vb, tb = read_mesh(pb)
        _same_topology(pa, ta, pb, tb)
        if template is None:
            template, first = tb, pb
        else:
            _same_topology(first, template, pb, tb)
        for V, p in ((Va, pa), (Vb, pb)):
            if not np.all(np.isfinite(V)):
                raise DataError(f"{p}: vertex positions contain NaN or infinite values")
        P.append(Va)
        T.append(Vb)
    res = evaluate(np.stack(P), np.stack(T), template, ms)
    out = {m.name: {k: v for k, v in summarise(res[m.name]["scores"]).items() if k in ("mean", "median", "max")}
           for m in ms}
    if maps_dir is not None:
        d = Path(maps_dir)
        for i, (pa, _) in enumerate(pairs):
            name = str(pa.relative_to(a) if Path(a).is_dir() else pa.name).replace("/", "__")
            buf = io.BytesIO()
            np.savez(buf, **{m.name: res[m.name]["maps"][i] for m in ms})
            atomic_write_bytes(d / f"{name}.npz", buf.getvalue())
    return {"metrics": out, "units": {m.name: m.units for m in ms}, "pairs": len(pairs),
            "unmatched": [str(p) for p in lonely]}


def add_eval_parser(sub):
    """The ``fwk eval`` subcommand's parser."""
    p = sub.add_parser("eval", help="metrics between two meshes or two folders (matched by relative path)")
    p.add_argument("a", help="predicted mesh or folder")
    p.add_argument("b", help="reference (ground-truth) mesh or folder")
    p.add_argument("--metrics", nargs="+", default=None, help="default: the metrics marked default (`fwk list`)")
    p.add_argument("--json", action="store_true", help="print one JSON object {metric: {mean, median, max}}")
    p.add_argument("--maps", metavar="DIR", help="write per-vertex maps (.npz per mesh pair)")
    return p


def run_eval(args) -> int:
    """``fwk eval``: print the metrics' table (or JSON); ``--maps`` checked before any work."""
    if args.maps:
        check_dir(args.maps, "--maps")
    r = compare_paths(args.a, args.b, args.metrics, args.maps)
    if r["unmatched"]:
        more = f" and {len(r['unmatched']) - 3} more" if len(r["unmatched"]) > 3 else ""
        print(f"warning: {len(r['unmatched'])} file(s) without a partner in the other folder were skipped: "
              f"{', '.join(r['unmatched'][:3])}{more}", file=sys.stderr)
    if args.json:
        print(json.dumps(r["metrics"]))
        return 0
    print(f"{r['pairs']} mesh pair(s); units: input = the meshes' own units")
    print(f"{'metric':<10} {'units':<8} {'mean':>12} {'median':>12} {'max':>12}")
    for name, s in r["metrics"].items():
        print(f"{name:<10} {r['units'][name]:<8} {s['mean']:>12.6g} {s['median']:>12.6g} {s['max']:>12.6g}")
    return 0
