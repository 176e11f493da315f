"""An example third-party plugin: the symmetric Chamfer distance as an fwk metric (this module,
entry point ``example``) and a Chebyshev graph convolution (``fwk_example_plugin.cheb``, entry
point ``example-cheb``).

For prediction P' and target P (both (n, 3)), the per-vertex value is the distance from each
predicted vertex to its nearest target vertex, d_i = min_j ||P'_i - P_j||, and the score is
the symmetric mean (mean_i d_i + mean_j min_i ||P_j - P'_i||) / 2. Unlike ``euclidean`` it
ignores correspondence, which makes it the usual metric for unregistered scans.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from fwk.hookspecs import hookimpl


class Chamfer:
    """Symmetric Chamfer distance (ignores vertex correspondence)."""

    name = "chamfer"
    label = "Chamfer"       # the column header of report tables
    units = "input"         # the positions' own units
    power = 1               # scaling positions by s scales the score by s**power
    display_scale = 1e-3    # tables show value / display_scale
    default = False         # not in the default metric list: ask for it with `metrics: [..., chamfer]`
    default_rank = 100
    rigid_invariant = False

    def __init__(self, workers: int = 1):
        self.workers = workers

    def __call__(self, pred, target, template):
        pred = np.asarray(pred, dtype=np.float64)
        target = np.asarray(target, dtype=np.float64)
        scores = np.empty(len(pred))
        maps = np.empty(pred.shape[:2])
        for b in range(len(pred)):
            d_pt, _ = cKDTree(target[b]).query(pred[b], workers=self.workers)
            d_tp, _ = cKDTree(pred[b]).query(target[b], workers=self.workers)
            maps[b] = d_pt
            scores[b] = 0.5 * (d_pt.mean() + d_tp.mean())
        return scores, maps


@hookimpl
def fwk_register_metrics():
    return [Chamfer]
