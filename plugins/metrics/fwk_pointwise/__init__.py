"""Point-wise metrics ``l1``, ``l2``, ``euclidean`` (DESIGN.md "Definitions").

For prediction P' and target P of shape (n, 3):

* ``l1``        = mean over vertices and coordinates of |P' - P|       (thesis "L1 norm", shown x1e-3)
* ``l2``        = mean over vertices and coordinates of (P' - P)^2     (thesis "L2 norm", shown x1e-5)
* ``euclidean`` = mean over vertices of ||P'_i - P_i||_2               (CoMA's mean Euclidean error)

Per-vertex maps are the same quantities before the mean over vertices. Units are those of
the positions ("input"; squared for l2): tasks report them in the evaluation space (the
thesis's) and in the dataset's own units.
"""
from __future__ import annotations

import numpy as np

from fwk.evaluation.core import as_pair
from fwk.hookspecs import hookimpl


class _Pointwise:
    """Shared shape of the point-wise metrics: a per-vertex value, averaged over vertices."""

    units = "input"         # the positions' own units (squared for l2)
    power = 1               # in input units: value / scale**power (positions were multiplied by scale)
    display_scale = 1e-3    # tables show the value divided by this (thesis: L1 x1e-3)
    default = True          # in the default metric list of evaluating tasks
    rigid_invariant = False
    scale_invariant = False

    @staticmethod
    def per_vertex(diff: np.ndarray) -> np.ndarray:  # (b, n, 3) -> (b, n)
        raise NotImplementedError

    def __call__(self, pred, target, template=None):
        pred, target = as_pair(pred, target)
        m = self.per_vertex(pred - target)
        return m.mean(axis=-1), m


class L1(_Pointwise):
    """Mean absolute coordinate error (thesis L1 norm)."""

    name = "l1"
    label = "L1 norm"
    default_rank = 0

    @staticmethod
    def per_vertex(diff):
        return np.abs(diff).mean(axis=-1)


class L2(_Pointwise):
    """Mean squared coordinate error (thesis L2 norm)."""

    name = "l2"
    label = "L2 norm"
    units = "input^2"
    power = 2
    display_scale = 1e-5
    default_rank = 1

    @staticmethod
    def per_vertex(diff):
        return (diff**2).mean(axis=-1)


class EuclideanError(_Pointwise):
    """Mean per-vertex Euclidean distance (CoMA's error)."""

    name = "euclidean"
    label = "Euclidean"
    default_rank = 2

    @staticmethod
    def per_vertex(diff):
        return np.linalg.norm(diff, axis=-1)


@hookimpl
def fwk_register_metrics():
    return [L1, L2, EuclideanError]
