"""Metrics over batches and their summaries."""
from __future__ import annotations

import numpy as np


def evaluate(pred, target, template, metrics) -> dict:
    """{metric name: {"scores": (b,), "maps": (b, n)}} for every metric object."""
    out = {}
    for m in metrics:
        scores, maps = m(np.asarray(pred, dtype=np.float64), np.asarray(target, dtype=np.float64), template)
        out[m.name] = {"scores": np.asarray(scores, dtype=np.float64), "maps": np.asarray(maps, dtype=np.float64)}
    return out


def summarise(scores) -> dict:
    s = np.asarray(scores, dtype=np.float64)
    if s.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "max": float("nan"), "std": float("nan"), "n": 0}
    return {"mean": float(s.mean()), "median": float(np.median(s)), "max": float(s.max()), "std": float(s.std()),
            "n": int(s.size)}


def evaluate_summary(pred, target, template, metrics, scale: float = 1.0) -> dict:
    """Summaries per metric in the evaluation space and in input units (positions / scale)."""
    res = evaluate(pred, target, template, metrics)
    out = {}
    for m in metrics:
        summ = summarise(res[m.name]["scores"])
        power = getattr(m, "power", 0)
        summ["units"] = getattr(m, "units", "")
        if power:
            f = 1.0 / scale ** power
            summ["mean_input"] = summ["mean"] * f
            summ["median_input"] = summ["median"] * f
            summ["max_input"] = summ["max"] * f
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
