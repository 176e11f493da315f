"""How reports show metrics: read from the metric classes, never from a list in the core."""
import gc
import types

import numpy as np
import pytest

import fwk_dame
import fwk_fmpd
import fwk_pointwise
from fwk.data import Template
from fwk.evaluation import (TopologyMemo, default_metrics, display, figure_metrics, format_value, scale_suffix,
                            write_report)
from fwk.evaluation.cli_report import _Dir
from fwk.evaluation.report import results_tables
from fwk.hookspecs import hookimpl
from fwk.plugins import get_registry, registry_from
from fwk.testing.metric import small_mesh


class Hausdorff:
    """A third-party metric in the default list (after fwk's own)."""

    name = "hausdorff"
    label = "Hausdorff"
    units = "input"
    display_scale = 1e-1
    power = 1
    default = True
    default_rank = 10


class Curvy:
    """A third-party perceptual metric, not in the default list."""

    name = "curvy"
    label = "Curvature"
    units = "1"
    display_scale = 1.0
    power = 0
    default = False
    default_rank = 0


class Bare:
    """A metric without display attributes (does not play the role)."""

    name = "bare"
    units = "input"


def _registry():
    extra = types.ModuleType("extra_metrics")
    extra.fwk_register_metrics = hookimpl(lambda: [Hausdorff, Curvy, Bare])
    return registry_from(fwk_pointwise, fwk_dame, fwk_fmpd, extra)


def test_default_metrics_in_rank_order():
    assert default_metrics(get_registry())[:5] == ["l1", "l2", "euclidean", "dame", "fmpd"]
    assert default_metrics(_registry()) == ["l1", "l2", "euclidean", "dame", "fmpd", "hausdorff"]


def test_figure_metrics_distance_and_perceptual():
    assert figure_metrics(get_registry()) == ("l1", ["dame", "fmpd"])
    assert figure_metrics(_registry()) == ("l1", ["dame", "fmpd"])  # curvy is not a default metric


def test_display_from_the_class():
    reg = _registry()
    d = display("l2", reg)
    assert (d.scale, d.label, d.units, d.name, d.power) == (1e-5, "L2 norm", "input^2", "l2", 2)
    assert d.suffix == " ×1e-5" and d.format(2.5e-5) == "2.5" and d.header_unit() == "×1e-5"
    assert display("dame", reg).header_unit() == "rad ×1e-2" and display("fmpd", reg).header_unit() == "×1e-2"
    assert display(fwk_dame.DAME(), reg) == display("dame", reg) == display(fwk_dame.DAME)
    assert display("hausdorff", reg).suffix == " ×1e-1"
    for unknown in ("nothing", "bare"):  # shown as they are: scale 1, the name as label
        d = display(unknown, reg)
        assert (d.scale, d.label, d.suffix, d.format(0.5)) == (1.0, unknown, "", "0.5")


def test_format_value_and_scale_suffix():
    assert format_value(None) == format_value(float("nan")) == format_value(np.float32("nan")) == "n/a"
    assert format_value(0.0012345, 1e-3) == "1.234" and format_value(3) == "3"
    assert scale_suffix(1.0) == "" and scale_suffix(1e-3) == " ×1e-3" and scale_suffix(1e-5) == " ×1e-5"


def test_results_tables_pinned():
    """The tables' text as reports have always written it."""
    res = {"models": {"pca": {"test": {
        "l1": {"mean": 0.0012345, "units": "input", "mean_input": 0.0024, "units_input": "cm"},
        "l2": {"mean": 2e-5, "units": "input^2", "mean_input": 8e-5},
        "dame": {"mean": 0.0312, "units": "rad", "mean_input": 0.0312, "units_input": "rad"},
        "hausdorff": {"mean": float("nan"), "units": "input"}}}}}
    assert results_tables(res, "cm", _registry()).splitlines() == [
        "### test: mean over meshes, evaluation space", "",
        "| model | l1 (×1e-3) | l2 (×1e-5) | dame (rad ×1e-2) | hausdorff (×1e-1) |",
        "| --- | --- | --- | --- | --- |",
        "| pca | 1.234 | 2 | 3.12 | n/a |", "",
        "### mean over meshes, in the dataset's units", "",
        "| model | split | l1 (cm) | l2 (cm^2) | dame (rad) |",
        "| --- | --- | --- | --- | --- |",
        "| pca | test | 0.0024 | 8e-05 | 0.0312 |"]


def test_write_report_takes_display_from_the_given_registry(tmp_path):
    res = {"models": {"m": {"test": {"hausdorff": {"mean": 0.25, "units": "input"}}}}}
    write_report(_Dir(tmp_path), "T", res, registry=_registry())
    assert "| m | 2.5 |" in (tmp_path / "report.md").read_text()


def test_topology_memo_builds_once_per_topology():
    built = []
    memo = TopologyMemo(lambda t: built.append(t.n_vertices) or object())
    V, t = small_mesh()
    a = memo(t)
    assert memo(t) is a and memo(Template(V + 1.0, t.triangles.copy())) is a and len(built) == 1
    other = Template(V, t.triangles[:-1])
    assert memo(other) is not a and len(built) == 2
    n = len(memo._by_template)
    del other
    gc.collect()
    assert len(memo._by_template) == n - 1  # templates are held weakly


@pytest.mark.parametrize("module", [fwk_dame, fwk_fmpd])
def test_metric_plugins_share_the_memo(module):
    assert isinstance(module._prep, TopologyMemo)
