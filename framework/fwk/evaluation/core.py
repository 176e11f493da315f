"""Metrics over batches and their summaries, and the helpers metric plugins share."""
from __future__ import annotations

import weakref

import numpy as np

from ..cache import memo
from ..plugins import get_registry


def as_pair(pred, target) -> tuple[np.ndarray, np.ndarray]:
    """A metric's inputs as two float64 (b, n, 3) arrays of one shape; a single (n, 3) mesh
    becomes a batch of one. A ValueError names both shapes when they differ."""
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.ndim == 2:
        pred, target = pred[None], target[None]
    if pred.shape != target.shape:
        raise ValueError(f"prediction {pred.shape} and target {target.shape} differ in shape")
    return pred, target


def in_chunks(fn, pred, target, size: int) -> tuple[np.ndarray, np.ndarray]:
    """(scores (b,), maps (b, n)) of ``fn(pred_chunk, target_chunk)`` over chunks of ``size``
    meshes: a metric whose intermediates fall out of cache for large batches stays fast."""
    parts = [fn(pred[i:i + size], target[i:i + size]) for i in range(0, len(pred), size)]
    if not parts:
        return np.zeros(0), np.zeros((0, pred.shape[1]))
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


class TopologyMemo:
    """``build(template)`` computed once per topology: ``memo(template)`` returns the structure
    built for the first template of the same topology (``template.topology_hash()``: vertex
    count and triangles), and remembers it per template object (weakly), so a template seen
    before is not hashed again. At most ``size`` topologies are kept (``fwk.cache.memo``, oldest
    dropped first).

    Metric plugins keep their per-topology structures (edge stencils, sparse scatters) in one::

        _prep = TopologyMemo(_build)     # _build(template) -> the structures
        p = _prep(template)
    """

    def __init__(self, build, size: int = 16):
        self.build = build
        self.size = size
        self.namespace = f"{build.__module__}.{build.__qualname__}"
        self._by_template: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

    def __call__(self, template):
        hit = self._by_template.get(template)
        if hit is None:
            hit = memo(self.namespace, template.topology_hash(), lambda: self.build(template), size=self.size)
            self._by_template[template] = hit
        return hit


def evaluate(pred, target, template, metrics) -> dict:
    """{metric name: {"scores": (b,), "maps": (b, n)}} for every metric object (float64).

    ``pred`` and ``target`` are (b, n, 3) (or (n, 3): one mesh) on the template's topology;
    ``metrics`` are metric instances (``ctx.build("metric", name)`` or the registry's classes).
    """
    pred = np.asarray(pred, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if pred.ndim == 2:
        pred, target = pred[None], target[None]
    if pred.shape != target.shape or pred.ndim != 3 or pred.shape[-1] != 3:
        raise ValueError(f"prediction {pred.shape} and target {target.shape}: expected two (b, n, 3) arrays")
    if template is not None and pred.shape[1] != template.n_vertices:
        raise ValueError(f"meshes have {pred.shape[1]} vertices, the template {template.n_vertices}")
    out = {}
    for m in _instances(metrics):
        scores, maps = m(pred, target, template)
        out[m.name] = {"scores": np.asarray(scores, dtype=np.float64), "maps": np.asarray(maps, dtype=np.float64)}
    return out


def _instances(metrics) -> list:
    """Metric instances from instances, classes or registered names."""
    out = []
    for m in metrics:
        if isinstance(m, str):
            m = get_registry().get("metric", m)
        if isinstance(m, type):
            m = m()
        out.append(m)
    return out


def summarise(scores) -> dict:
    """mean, median, max, std (population) and n of per-mesh scores; NaN (n = 0) when empty."""
    s = np.asarray(scores, dtype=np.float64)
    if s.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "max": float("nan"), "std": float("nan"), "n": 0}
    return {"mean": float(s.mean()), "median": float(np.median(s)), "max": float(s.max()), "std": float(s.std()),
            "n": int(s.size)}


def evaluate_summary(pred, target, template, metrics, scale: float = 1.0, scores_out: dict | None = None) -> dict:
    """Summaries per metric in the evaluation space and in input units.

    The evaluation space is ``scale`` x the input (preprocessing's uniform scale), so a metric
    of ``power`` p (1: l1, euclidean; 2: l2; 0: the scale-invariant DAME, FMPD) is divided by
    ``scale**p`` to give ``mean_input``, ``median_input``, ``max_input``, ``std_input``;
    ``units_input`` names them with the template's units (``cm``, ``cm^2``, ``rad``, ``1``).
    With ``scores_out`` (a dict), each metric's per-mesh scores (evaluation space, a list in the
    order of the meshes) are also put there under the metric's name: what a paired test over
    subjects needs (``fwk.evaluation.seeds``).
    """
    metrics = _instances(metrics)
    res = evaluate(pred, target, template, metrics)
    in_units = (template.units if template is not None else "") or "input"
    out = {}
    for m in metrics:
        if scores_out is not None:
            scores_out[m.name] = [float(x) for x in res[m.name]["scores"]]
        summ = summarise(res[m.name]["scores"])
        units = m.units
        summ["units"] = units
        f = 1.0 / float(scale) ** m.power
        for k in ("mean", "median", "max", "std"):
            summ[f"{k}_input"] = summ[k] * f
        summ["units_input"] = units.replace("input", in_units)
        out[m.name] = summ
    return out


def pareto_front(points) -> np.ndarray:
    """Indices of the points (k, 2) not dominated when minimising both coordinates,
    sorted by the first coordinate."""
    P = np.asarray(points, dtype=np.float64)
    if len(P) == 0:
        return np.zeros(0, dtype=np.int64)
    keep = []
    for i, p in enumerate(P):
        if not np.all(np.isfinite(p)):
            continue
        dominated = np.any(np.all(P <= p, axis=1) & np.any(P < p, axis=1))
        if not dominated:
            keep.append(i)
    keep = np.asarray(keep, dtype=np.int64)
    return keep[np.argsort(P[keep, 0], kind="stable")]
