"""Hostile plugins (issue 25, item 5): a third-party entry point may not take a built-in's name
(unless ``FWK_PLUGIN_OVERRIDES`` says so), and a plugin that raises anything at import, SystemExit
and KeyboardInterrupt included, is reported broken while the rest works.

Each plugin is a real installed distribution: a ``*.dist-info`` folder with ``entry_points.txt``
and a module, on ``PYTHONPATH`` of a ``python -m fwk.cli`` subprocess (entry points are found
when fwk starts). Each refusal: exit 2, at most 3 lines on stderr, no traceback, within 20 s,
nothing written outside the runs folder (``tests/faults/hostile.py``)."""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from tests.faults.common import PCA_RECIPE, recipe, run_dirs
from tests.faults.hostile import LIMIT_S, refused

METRIC = '''
from fwk.hookspecs import hookimpl


class Metric:
    """{doc}"""

    name = "{name}"
    label = "{name}"
    display_scale = 1.0
    units = ""
    power = 1
    default = False

    def __call__(self, pred, target):
        import numpy as np
        return np.zeros(len(pred)), np.zeros(pred.shape[:2])


@hookimpl
def fwk_register_metrics():
    return [Metric]
'''


def _dist(site, dist: str, entries: dict[str, str], modules: dict[str, str]) -> None:
    """Install distribution ``dist`` 1.0 into ``site``: entry points {name: module} in group fwk
    and the modules' sources."""
    info = site / f"{dist.replace('-', '_')}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[fwk]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()))
    for mod, src in modules.items():
        (site / f"{mod}.py").write_text(textwrap.dedent(src))


@pytest.fixture
def site(tmp_path, env):
    """(site folder, the subprocess environment with it on PYTHONPATH)."""
    s = tmp_path / "site"
    s.mkdir()
    e = {**env, "PYTHONPATH": str(s), "PYTHONDONTWRITEBYTECODE": "1"}
    e.pop("FWK_NO_ENTRYPOINTS", None)
    e.pop("FWK_PLUGIN_OVERRIDES", None)
    return s, e


def _fwk(argv, env, cwd):
    return subprocess.run([sys.executable, "-m", "fwk.cli", *argv], env=env, cwd=cwd, capture_output=True, text=True,
                          timeout=LIMIT_S + 30)


def _run_refused(tmp_path, env, text, *expect):
    runs = tmp_path / "runs"
    err = refused(["--quiet", "run", str(recipe(tmp_path, text)), "--runs-dir", str(runs)], tmp_path, *expect,
                  runs=runs, subprocess=True, env=env)
    assert run_dirs(runs) == []
    return err


def test_an_entry_point_taking_a_builtins_name_is_refused(tmp_path, site):
    """Reproduction: an entry point called `dame` of another distribution replaced fwk's DAME
    (which then read 0) without a word."""
    s, env = site
    _dist(s, "evil-dame", {"dame": "evil_dame"}, {"evil_dame": METRIC.format(name="dame", doc="a fake DAME")})
    expect = ("plugin 'dame' of distribution evil-dame 1.0 takes the name of fwk's built-in plugin 'dame' "
              "(distribution fwk ", "FWK_PLUGIN_OVERRIDES=dame")
    refused(["list"], tmp_path, *expect, subprocess=True, env=env)
    _run_refused(tmp_path, env, PCA_RECIPE.replace("[l1, l2]", "[l1, dame]"), *expect)


def test_a_component_taking_a_builtins_name_is_refused(tmp_path, site):
    s, env = site
    _dist(s, "shadow-metrics", {"shadow": "shadow_metrics"},
          {"shadow_metrics": METRIC.format(name="dame", doc="a fake DAME")})
    refused(["list"], tmp_path, "metric 'dame' of plugin shadow (distribution shadow-metrics 1.0) takes the name of "
            "fwk's built-in metric of plugin dame (distribution fwk ", "FWK_PLUGIN_OVERRIDES=dame",
            subprocess=True, env=env)


def test_the_override_switch_lets_a_plugin_replace_a_builtin(tmp_path, site):
    s, env = site
    _dist(s, "evil-dame", {"dame": "evil_dame"}, {"evil_dame": METRIC.format(name="dame", doc="my own DAME")})
    p = _fwk(["list", "--kind", "metric"], {**env, "FWK_PLUGIN_OVERRIDES": "spiral, dame"}, tmp_path)
    assert p.returncode == 0, p.stderr
    row = next(line for line in p.stdout.splitlines() if line.startswith("dame "))
    assert "1.0" in row and "my own DAME" in row, row
    assert any(line.startswith("l1 ") for line in p.stdout.splitlines())


def test_two_distributions_with_one_entry_point_name(tmp_path, site):
    s, env = site
    _dist(s, "one-dist", {"mine": "one_mod"}, {"one_mod": METRIC.format(name="one", doc="one")})
    _dist(s, "two-dist", {"mine": "two_mod"}, {"two_mod": METRIC.format(name="two", doc="two")})
    err = refused(["list"], tmp_path, "plugin 'mine' is declared by several distributions", "one-dist 1.0",
                  "two-dist 1.0", subprocess=True, env=env)
    assert "FWK_PLUGIN_OVERRIDES" not in err  # only a built-in may be replaced, never another third party


BROKEN = {
    "exiter": "raise SystemExit(3)\n",
    "interrupter": "raise KeyboardInterrupt\n",
    "closer": "raise GeneratorExit('closed')\n",
    "failer": "raise RuntimeError('x' * 100000)\n",
    "baser": "class Weird(BaseException):\n    pass\n\nraise Weird('weird')\n",
    "hooker": "from fwk.hookspecs import hookimpl\n\n\n@hookimpl\ndef fwk_register_metrics():\n    raise SystemExit(4)\n",
}


def test_plugins_raising_anything_at_import_are_broken_the_rest_works(tmp_path, site):
    """Reproduction: a plugin raising SystemExit or KeyboardInterrupt at import stopped `fwk list`
    with no message."""
    s, env = site
    _dist(s, "broken-plugins", {name: f"broken_{name}" for name in BROKEN},
          {f"broken_{name}": src for name, src in BROKEN.items()})
    p = _fwk(["list"], env, tmp_path)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr, p.stderr
    for name, what in [("exiter", "SystemExit: 3"), ("interrupter", "KeyboardInterrupt"),
                       ("closer", "GeneratorExit: closed"), ("failer", "RuntimeError: xxx"), ("baser", "Weird: weird"),
                       ("hooker", "SystemExit: 4")]:
        line = next((x for x in p.stderr.splitlines() if x.startswith(f"broken plugin {name}: ")), None)
        assert line is not None and what in line, p.stderr
        assert len(line) < 300, line  # a huge message is cut
    names = {line.split()[0] for line in p.stdout.splitlines()[1:]}
    assert {"pca", "l1", "dame", "reconstruct", "synthetic-heads"} <= names
    p = _fwk(["show", "metric", "l1"], env, tmp_path)
    assert p.returncode == 0, p.stderr


def test_a_recipe_naming_a_broken_plugins_component(tmp_path, site):
    s, env = site
    _dist(s, "broken-metric", {"exiter": "broken_exiter"}, {"broken_exiter": BROKEN["exiter"]})
    _run_refused(tmp_path, env, PCA_RECIPE.replace("[l1, l2]", "[l1, exits]"), "metrics[1]: unknown metric 'exits'",
                 "plugins that failed to load (fwk list): exiter")
