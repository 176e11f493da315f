"""Grids on Ray: the same metrics as the local executor, failures reported while the rest go on,
a killed Ray grid resumed with only the missing members; the executor setting validated.

The Ray tests run ``fwk run`` as a subprocess (the real entry point; Ray's local instance then
lives and dies with it) and are marked slow: about 25 s each on 2 cores, mostly Ray's start
and each worker's imports."""
from __future__ import annotations

import glob
import importlib.util
import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fwk.errors import RecipeError

REPO = Path(__file__).resolve().parents[2]
BASE = REPO / "recipes" / "smoke" / "grid_base.yaml"
TINY = "{dataset: {n_vertices: 200, n_subjects: 12}, train: {epochs: %d}}"


def _env(tmp_path) -> dict:
    return {**os.environ, "FWK_CACHE": str(tmp_path / "cache"), "FWK_THREADS": "1", "OMP_NUM_THREADS": "1",
            "RAY_USAGE_STATS_ENABLED": "0"}


def _fwk(tmp_path, *args, timeout=300, code=0) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "fwk", *args], env=_env(tmp_path), capture_output=True, text=True,
                       timeout=timeout, cwd=tmp_path)
    assert p.returncode == code, p.stdout[-3000:] + p.stderr[-3000:]
    return p


def _grid(tmp_path, configs: dict[str, str], executor: str | None = None) -> Path:
    text = f"task: grid\nbase: {BASE}\n" + (f"executor: {executor}\n" if executor else "") + "configs:\n"
    text += "".join(f"  {name}: {body}\n" for name, body in configs.items())
    path = tmp_path / "g.yaml"
    path.write_text(text)
    return path


def _only_run(runs: Path) -> Path:
    (d,) = list(runs.iterdir())
    return d


def _values(metrics: dict) -> dict:
    """Every number of a member's metrics.json but the wall times, by key path."""
    out = {}

    def walk(v, path):
        if isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{path}/{k}")
        elif isinstance(v, list):
            for i, x in enumerate(v):
                walk(x, f"{path}[{i}]")
        elif "timing" not in path and not path.endswith(("/seconds", "/train_s")):  # wall times
            out[path] = v

    walk(metrics, "")
    return out


# ------------------------------------------------------------------------------ settings

def test_executor_settings_are_validated():
    from fwk_grid.executors import Executor

    assert Executor.from_recipe("ray").name == "ray"
    assert Executor.from_recipe(None).name == "local"
    e = Executor.from_recipe({"name": "ray", "address": "ray://head:10001", "cpus": 2, "gpus": 0.5})
    assert (e.address, e.cpus, e.gpus, e.threads) == ("ray://head:10001", 2, 0.5, 2)
    assert Executor.from_recipe({"name": "ray", "cpus": 0.5}).threads == 1
    with pytest.raises(RecipeError, match="executor: expected one of local, ray, got 'rya'; did you mean ray"):
        Executor.from_recipe("rya")
    with pytest.raises(RecipeError, match="executor.adress: unknown setting; did you mean address"):
        Executor.from_recipe({"name": "ray", "adress": "x"})
    with pytest.raises(RecipeError, match="executor.cpus: expected a number >= 0"):
        Executor.from_recipe({"name": "ray", "cpus": -1})
    with pytest.raises(RecipeError, match="Ray settings"):
        Executor.from_recipe({"name": "local", "address": "auto"})


def test_the_recipe_key_and_its_override_form(tmp_path):
    from fwk.plugins import get_registry
    from fwk.recipes import load_recipe, resolve

    g = _grid(tmp_path, {"a": TINY % 1})
    r = resolve(load_recipe(g, ["executor=ray", "executor.address=ray://h:1", "executor.cpus=2"]), get_registry())
    task = r.task.build()
    assert (task.executor.name, task.executor.address, task.executor.cpus) == ("ray", "ray://h:1", 2)
    with pytest.raises(RecipeError, match="executor"):
        resolve(load_recipe(g, ["executor=slurm"]), get_registry()).task.build()


def test_a_failing_member_is_reported_and_the_rest_go_on(tmp_path, monkeypatch):
    """Local executor, in this process: a member failing at run time (pca with more components
    than training meshes) leaves a FAILED file and a report row; the others finish; the grid
    ends with one line (exit 2), its run kept and marked FAILED."""
    from fwk.cli import main

    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    g = _grid(tmp_path, {"bad": "{models: {ae: {name: pca, n_components: 500}}, dataset: {n_vertices: 200, "
                                "n_subjects: 12}}", "a": TINY % 1})
    assert main(["--quiet", "run", str(g), "--runs-dir", str(tmp_path / "runs")]) == 2
    d = _only_run(tmp_path / "runs")
    assert "grid: 1 of 2 members failed (bad: " in (d / "FAILED").read_text()
    m = json.loads((d / "metrics.json").read_text())
    assert set(m["models"]) == {"a"} and set(m["failed"]) == {"bad"}
    assert "n_components" in m["failed"]["bad"]
    assert "n_components" in (d / "bad" / "FAILED").read_text()
    assert not (d / "a" / "FAILED").exists()
    report = (d / "report.md").read_text()
    assert "Failed members" in report and "| bad |" in report and "| a |" in report
    assert "grid member bad failed" in (d / "log.txt").read_text()


def test_local_members_side_by_side_give_a_one_thread_grids_numbers(tmp_path, monkeypatch):
    """Local executor with 2 threads: the members (one failing) run side by side in forked
    processes, a thread each (fwk.sidebyside): every value of every member's metrics.json (but
    wall times) is bit for bit that of the same grid run with 1 thread, one member after another;
    the failing member is reported and the others finish, as one after another."""
    from fwk.cli import main

    monkeypatch.setenv("FWK_RUNTIME_DIR", str(tmp_path / "procs"))
    configs = {"bad": "{models: {ae: {name: pca, n_components: 500}}, dataset: {n_vertices: 200, n_subjects: 12}}",
               "a": TINY % 2, "b": "{dataset: {n_vertices: 200, n_subjects: 12}, train: {epochs: 2}, "
                                   "models: {ae: {name: ae, channels: [4], latent: 8, sampler: {name: quadric, "
                                   "factors: [4]}}}}"}
    g = _grid(tmp_path, configs)
    runs = {}
    for n in (1, 2):
        monkeypatch.setenv("FWK_THREADS", str(n))
        monkeypatch.setenv("FWK_CACHE", str(tmp_path / f"cache{n}"))
        assert main(["--quiet", "run", str(g), "--runs-dir", str(tmp_path / f"runs{n}")]) == 2
        runs[n] = _only_run(tmp_path / f"runs{n}")
    log = (runs[2] / "log.txt").read_text()
    assert "3 member runs side by side, 2 at a time with 1 thread each (the run's 2;" in log
    assert "side by side" not in (runs[1] / "log.txt").read_text()
    assert "[a] [ae] fitting ae" in log and "[b] [ae] fitting ae" in log  # which member said each line
    assert "grid member bad failed" in log and "n_components" in (runs[2] / "bad" / "FAILED").read_text()
    for name in ("a", "b"):
        one, two = (_values(json.loads((runs[n] / name / "metrics.json").read_text())) for n in (1, 2))
        assert one == two, name
        curves = [json.loads(p.read_text()) for p in (runs[2] / name / "curves").glob("*/*.json")]
        assert curves and all(e["threads"] == 1 for c in curves for e in c["epochs"])
    m = json.loads((runs[2] / "metrics.json").read_text())
    assert set(m["models"]) == {"a", "b"} and set(m["failed"]) == {"bad"}


# ------------------------------------------------------------------------------ Ray

needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                               reason="Ray is an optional extra: pip install 'fwk[ray]'")


@needs_ray
def test_a_local_ray_instance_runs_members_at_the_drivers_priority():
    """fwk's local Ray instance starts its workers at the driver's niceness (Ray's default puts them
    15 levels below it, where other work on the machine starved a grid's members); a cluster's
    address is left to the cluster's settings."""
    import ray
    from fwk_grid.executors import Executor, ray_init_kwargs

    kw = ray_init_kwargs(Executor(name="ray", num_cpus=1), quiet=True)
    assert ray_init_kwargs(Executor(name="ray", address="ray://head:10001"), quiet=True) == {
        "include_dashboard": False, "log_to_driver": False, "logging_level": logging.ERROR,
        "address": "ray://head:10001"}
    ray.init(**kw)
    try:
        assert ray.get(ray.remote(lambda: os.nice(0)).remote()) == os.nice(0)
    finally:
        ray.shutdown()


@pytest.mark.slow
@needs_ray
def test_ray_grid_writes_the_metrics_of_the_local_executor(tmp_path):
    """Two members and one that fails, run by both executors: every value of every member's
    metrics.json (but wall times) is the same, bit for bit (one thread each: FWK_THREADS=1; with
    other thread counts the sums' order differs, see docs/scaling.md), and the failure is
    reported alike."""
    configs = {"a": TINY % 1,
               "b": "{dataset: {n_vertices: 200, n_subjects: 12}, train: {epochs: 2}, models: {ae: {latent: 8}}}",
               "bad": "{models: {ae: {name: pca, n_components: 500}}, dataset: {n_vertices: 200, n_subjects: 12}}"}
    g = _grid(tmp_path, configs)
    _fwk(tmp_path, "run", str(g), "--runs-dir", str(tmp_path / "local"), code=2)
    out = _fwk(tmp_path, "run", str(g), "executor=ray", "--runs-dir", str(tmp_path / "ray"), code=2).stdout
    assert "ray: 3 members on" in out
    local, onray = _only_run(tmp_path / "local"), _only_run(tmp_path / "ray")
    for name in ("a", "b"):
        a = _values(json.loads((local / name / "metrics.json").read_text()))
        b = _values(json.loads((onray / name / "metrics.json").read_text()))
        assert len(a) > 50 and a == b, name
    ml, mr = (json.loads((d / "metrics.json").read_text()) for d in (local, onray))
    assert ml["failed"] == mr["failed"] and set(mr["failed"]) == {"bad"}
    assert _values(ml["models"]) == _values(mr["models"])
    assert (onray / "bad" / "FAILED").exists() and "Failed members" in (onray / "report.md").read_text()


@pytest.mark.slow
@needs_ray
def test_a_killed_ray_grid_resumes_with_only_the_missing_members(tmp_path):
    """Kill the whole process group of a Ray grid once its short member has finished and while
    the long one trains: nothing writes the run after the kill (the member's Ray worker dies with
    it), and ``fwk run --resume`` runs only the long one, from its checkpoint."""
    g = _grid(tmp_path, {"short": TINY % 1, "long": TINY % 150}, executor="ray")
    runs = tmp_path / "runs"
    p = subprocess.Popen([sys.executable, "-m", "fwk", "--quiet", "run", str(g), "--runs-dir", str(runs)],
                         env=_env(tmp_path), cwd=tmp_path, start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        t0 = time.monotonic()
        while not glob.glob(str(runs / "*" / "short" / "metrics.json")):
            assert p.poll() is None and time.monotonic() - t0 < 240, "the grid ended or hung before its short member"
            time.sleep(0.1)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()
    d = _only_run(runs)
    assert not (d / "long" / "metrics.json").exists(), "the long member finished before the kill"

    def written():
        return sorted((p.name, p.stat().st_mtime_ns) for p in (d / "long").rglob("*") if p.is_file())

    at_kill = written()
    time.sleep(2)  # the member's Ray worker dies with the grid (its raylet); it trained on into the run before
    assert written() == at_kill, "the Ray worker went on writing the killed grid's member"
    stamp = (d / "short" / "metrics.json").stat().st_mtime_ns
    checkpointed = any((d / "long").rglob("last.ckpt"))
    _fwk(tmp_path, "run", "--resume", str(d))
    log = (d / "log.txt").read_text()
    if checkpointed:  # killed after an epoch or more: it continues, and says from where
        assert "ae: resuming from " in log and "continuing with epoch" in log
    assert "short: finished before, not run again" in log
    assert "ray: 1 member on" in log  # only the missing one was submitted
    assert (d / "short" / "metrics.json").stat().st_mtime_ns == stamp
    assert (d / "long" / "metrics.json").exists()
    curves = json.loads((d / "long" / "curves" / "ae" / "ae.json").read_text())
    assert curves["epochs_run"] == 150 and curves["finished"]
    assert {p.name for p in (d / "long" / "checkpoints" / "ae" / "ae").iterdir()} == {"last.ckpt", "epoch149.ckpt"}
    m = json.loads((d / "metrics.json").read_text())
    assert set(m["models"]) == {"short", "long"} and "failed" not in m
