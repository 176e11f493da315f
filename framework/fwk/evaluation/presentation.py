"""How reports show metrics, read from the metric classes (the core names no metric).

Every metric class declares its display attributes (``fwk.protocols.Metric``): ``label``,
``display_scale``, ``units``, ``power``, ``default`` and ``default_rank``. Reports find a
metric's class by the name ``metrics.json`` records; a name no registered metric plays the
role for (a third-party metric since removed, say) is shown as it is, unscaled.

API::

    default_metrics(registry=None) -> ["l1", "l2", ...]     # default=True, in default_rank order
    display(metric, registry=None) -> Display(scale, label, units, name, power)
    figure_metrics(registry=None) -> (distance, [perceptual, ...])   # what the standard figures plot
    format_value(x, scale=1.0) -> "1.234" ("n/a" for None / NaN)
    scale_suffix(scale) -> " ×1e-3" ("" at 1)
"""
from __future__ import annotations

import math
from typing import NamedTuple

from ..plugins import get_registry
from ..protocols import Metric, plays
from ..registry import Registry


def format_value(x, scale: float = 1.0) -> str:
    """A table cell: ``x / scale`` to four significant digits; ``n/a`` for None and non-finite."""
    if x is None or not math.isfinite(x):
        return "n/a"
    return f"{x / scale:.4g}"


def scale_suffix(scale: float) -> str:
    """The display factor as a header appends it to a name: `` ×1e-3`` ("" when ``scale`` is 1)."""
    if scale == 1.0:
        return ""
    return f" ×1e{int(round(math.log10(scale)))}"


def bare_unit(units: str) -> str:
    """A metric's unit in the evaluation space: none for the positions' own units ("input",
    "input^2": the space is scaled into [-1, 1]) and for unitless ("1"), else the unit ("rad")."""
    return "" if (not units or "input" in units or units == "1") else units


def axis_unit(units: str, input_units: bool) -> str:
    """What an axis or colour-bar title says of a metric's unit: in the dataset's units
    (``input_units``) the unit itself (``cm``, ``cm^2``, ``rad``; ``unitless`` for ``1``);
    in the evaluation space ``evaluation space`` for the positions' own units (``input``,
    scaled into [-1, 1]), else the unit."""
    if not units or units == "1":
        return "unitless"
    if "input" in units:
        return "evaluation space" if not input_units else units.replace("input", "input units")
    return units


class Display(NamedTuple):
    """How a metric is shown: tables give ``value / scale`` under ``label``; ``units`` and
    ``power`` as the metric class declares them (``fwk.protocols.Metric``)."""

    scale: float
    label: str
    units: str
    name: str
    power: int

    @property
    def suffix(self) -> str:
        """`` ×1e-3``: the factor a header appends to the metric's name ("" at scale 1)."""
        return scale_suffix(self.scale)

    def format(self, x) -> str:
        """A table cell of this metric: ``format_value(x, scale)``."""
        return format_value(x, self.scale)

    def header_unit(self, units: str | None = None) -> str:
        """The unit a table header shows in the evaluation space: the unit (see ``bare_unit``)
        and the display factor, e.g. ``rad ×1e-2``; ``units`` overrides the class's (a
        metrics.json records them)."""
        return " ".join(x for x in (bare_unit(self.units if units is None else units), self.suffix.strip()) if x)


def _metric_classes(registry: Registry | None) -> dict[str, type]:
    """The registered metric classes that play the metric role (display attributes included)."""
    reg = registry or get_registry()
    classes = {n: reg.get("metric", n) for n in reg.names("metric")}
    return {n: c for n, c in classes.items() if plays(c, Metric)}


def display(metric, registry: Registry | None = None) -> Display:
    """How ``metric`` (a registered name, a metric class or instance) is shown. A name that no
    registered metric plays the role for is shown as it is: scale 1, its name as label."""
    if isinstance(metric, str):
        metric = _metric_classes(registry).get(metric, metric)
    if isinstance(metric, str) or not plays(metric, Metric):
        name = metric if isinstance(metric, str) else metric.name
        return Display(1.0, name, "", name, 0)
    return Display(float(metric.display_scale), metric.label, metric.units, metric.name, int(metric.power))


def default_metrics(registry: Registry | None = None) -> list[str]:
    """The names of the registered metrics with ``default = True``, in ``default_rank`` order
    (ties by name): what evaluating tasks and ``fwk eval`` compute when a recipe names none."""
    classes = [c for c in _metric_classes(registry).values() if c.default]
    return [c.name for c in sorted(classes, key=lambda c: c.default_rank)]


def figure_metrics(registry: Registry | None = None) -> tuple[str | None, list[str]]:
    """What the standard figures plot, from the default metrics: the first point-wise distance
    (``power == 1``: the x axis of the error scatters and the first error maps) and the
    scale-invariant, perceptual ones (``power == 0``: the scatters' y axes, the first of them
    also error maps). For fwk's own metrics: ``("l1", ["dame", "fmpd"])``."""
    classes = _metric_classes(registry)
    names = default_metrics(registry)
    distance = next((n for n in names if classes[n].power == 1), None)
    return distance, [n for n in names if classes[n].power == 0]
