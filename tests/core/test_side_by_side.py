"""A run's models fitted side by side in forked processes (fwk.sidebyside, issue 28): each model
bit for bit the one a 1-thread run fits (a reconstruct and a blendshapes run), the plan's rule,
a child's error raised by the run's process with its class, a killed child named with its
signal, and a resume after either."""
import json
import os
import signal

import pytest
import yaml

from fwk.engine import threads
from fwk.engine.config import TrainConfig
from fwk.errors import DataError, FwkError, RecipeError
from fwk.plugins import get_registry
from fwk.runs import execute
from fwk.safeio import load_state
from fwk.forked import plan

AE = {"name": "ae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
RECON = {"name": "sbs", "task": "reconstruct", "seed": 0,
         "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 10},
         "split": {"ratios": [0.6, 0.2, 0.2]}, "train": {"epochs": 3, "batch_size": 4},
         "models": {"ae": AE, "ae2": {**AE, "channels": [4]}, "pca": {"name": "pca", "n_components": 3}},
         "metrics": ["l1"], "renders": 0}
BLEND = {"name": "sbs-blend", "task": "blendshapes", "seed": 0,
         "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12,
                     "shapes": ["neutral", "mouth-wide"], "gain_sd": 0},
         "split": {"ratios": [0.6, 0.2, 0.2]}, "train": {"epochs": 2, "batch_size": 4},
         "models": {"dt": {"name": "dt", "sources": 0},
                    "pbs": {"name": "pbs", "spatial": {"name": "euclidean", "scaling": "std"},
                            "differential": {"name": "dr", "scaling": "std"}, "knee_metric": "dame",
                            "network": {"name": "vae", "conv": {"name": "spiral++", "length": 9},
                                        "channels": [4, 8], "latent": 4,
                                        "sampler": {"name": "quadric", "factors": [4, 4]}}}},
         "metrics": ["l1", "dame"], "renders": 0}


@pytest.fixture
def env(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_RUNTIME_DIR", str(tmp_path / "procs"))
    for var in ("OMP_NUM_THREADS", "FWK_ALLOCATED_CPUS"):
        monkeypatch.delenv(var, raising=False)
    import torch

    before = torch.get_num_threads()
    yield monkeypatch
    threads.unpin()
    torch.set_num_threads(before)


def _run(tmp_path, recipe, n, name, monkeypatch, **kw):
    monkeypatch.setenv("FWK_THREADS", str(n))
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / f"cache-{name}"))
    d = tmp_path / name
    d.mkdir()
    (d / "r.yaml").write_text(yaml.safe_dump(recipe))
    return execute(str(d / "r.yaml"), runs_dir=str(d / "runs"), quiet=True, **kw)


def _states(run):
    out = {}
    for p in sorted((run / "models").glob("*.safetensors")):
        state = load_state(p)
        out[p.stem] = state
    return out


def _same(a, b, where=""):
    import numpy as np
    import torch

    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, torch.Tensor):
        if a.layout == torch.sparse_coo:
            a, b = a.coalesce(), b.coalesce()
            assert torch.equal(a.indices(), b.indices()) and torch.equal(a.values(), b.values()), where
        else:
            assert a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, np.ndarray):
        assert np.array_equal(a, b), where
    else:
        assert a == b, where


def _epoch_threads(run):
    return {p.parent.name: [e["threads"] for e in json.loads(p.read_text())["epochs"]]
            for p in (run / "curves").glob("*/*.json")}


@pytest.mark.parametrize("recipe", [RECON, BLEND], ids=["reconstruct", "blendshapes"])
def test_side_by_side_fits_the_models_a_one_thread_run_fits_bit_for_bit(tmp_path, env, recipe):
    one = _run(tmp_path, recipe, 1, "one", env)
    two = _run(tmp_path, recipe, 2, "two", env)
    log = (two / "log.txt").read_text()
    n = len(recipe["models"])
    assert f"fitting {n} models side by side, 2 at a time with 1 thread each (the run's 2;" in log
    assert "side by side" not in (one / "log.txt").read_text()  # one thread: one after another
    a, b = _states(one), _states(two)
    assert set(a) == set(b) == set(recipe["models"])
    _same(a, b)
    seen = _epoch_threads(two)
    assert seen and all(set(v) == {1} for v in seen.values()), seen
    m1, m2 = (json.loads((r / "metrics.json").read_text()) for r in (one, two))
    assert m2["threads"] == 2 and set(m1["models"]) == set(m2["models"])
    for label in m1["timing"]:
        assert m2["timing"][label]["fit_s"] > 0


def test_the_plan(monkeypatch):
    class Ctx:
        def __init__(self, **train):
            self.train, self.device = TrainConfig(**train), "cpu"

    for T, m, want in ((2, 5, (2, 1, 2)), (4, 2, (2, 2, 4)), (3, 5, (3, 1, 3)), (4, 3, (3, 1, 4)),
                       (1, 5, None), (2, 1, None)):
        monkeypatch.setenv("FWK_THREADS", str(T))
        assert plan(Ctx(), m) == want, (T, m)
    monkeypatch.setenv("FWK_THREADS", "2")
    assert plan(Ctx(side_by_side=False), 3) is None
    assert plan(Ctx(strategy="ddp"), 3) is None
    assert plan(Ctx(accelerator="gpu"), 3) is None
    c = Ctx()
    c.device = "cuda"
    assert plan(c, 3) is None
    with pytest.raises(RecipeError, match="train.side_by_side: expected true or false"):
        TrainConfig(side_by_side="yes")


def test_seed_rounds(monkeypatch):
    """Rounds of min(T, seeds) seeds, T // k threads for a round of k, and the run's T itself
    (not derived from a round: 3 threads over 2 seeds give 1 each)."""
    from fwk.seeds import seed_rounds

    class Ctx:
        train, device = TrainConfig(), "cpu"

    for T, seeds, want in ((2, [0, 1, 2], ([([0, 1], 1), ([2], 2)], 2)), (3, [0, 1], ([([0, 1], 1)], 3)),
                           (4, [5, 6, 7, 8, 9], ([([5, 6, 7, 8], 1), ([9], 4)], 4)), (1, [0, 1], None),
                           (2, [0], None)):
        monkeypatch.setenv("FWK_THREADS", str(T))
        assert seed_rounds(Ctx(), seeds) == want, (T, seeds)


def _break(monkeypatch, how):
    """The ae model's fit fails for the model with 4 channels (ae2) in the way ``how``."""
    cls = get_registry().get("model", "ae")
    real = cls.fit

    def fit(self, data, ctx):
        if ctx.scope == "ae2":
            if how == "error":
                raise DataError("ae2 refuses these data")
            if how == "bug":
                raise ZeroDivisionError("a bug in a plugin")
            os.kill(os.getpid(), signal.SIGKILL)
        return real(self, data, ctx)

    monkeypatch.setattr(cls, "fit", fit)
    return real


@pytest.mark.parametrize("how", ["error", "bug", "kill"])
def test_a_failing_child_fails_the_run_which_resumes(tmp_path, env, how):
    recipe = {**RECON, "models": {"ae": AE, "ae2": {**AE, "channels": [4]}}}
    real = _break(env, how)
    if how == "error":
        expect, match = DataError, "ae2 refuses these data"
    elif how == "bug":
        expect, match = RuntimeError, r"models.ae2: fitting failed in its side-by-side process:\n(.|\n)*ZeroDivisionError"
    else:
        expect, match = FwkError, r"models.ae2: its side-by-side fitting process was killed by signal 9 \(SIGKILL\)"
    with pytest.raises(expect, match=match):
        _run(tmp_path, recipe, 2, "broken", env)
    runs = list((tmp_path / "broken" / "runs").iterdir())
    assert len(runs) == 1 and (runs[0] / "FAILED").exists()
    env.setattr(get_registry().get("model", "ae"), "fit", real)
    run = execute(None, resume=str(runs[0]), quiet=True)
    assert (run / "metrics.json").exists() and set(_states(run)) == {"ae", "ae2"}
    assert _epoch_threads(run)["ae2"] == [1, 1, 1]


def test_a_prefixed_stream_starts_every_line_with_the_prefix():
    import io

    from fwk.forked import _Prefixed

    out = io.StringIO()
    w = _Prefixed(out, "[a] ")
    for piece in ("x\ny", "z\n", "\n", "p\rq\n"):
        w.write(piece)
    assert out.getvalue() == "[a] x\n[a] yz\n[a] \n[a] p\r[a] q\n"


def test_ctrl_c_stops_the_run_and_its_children_and_the_run_resumes(tmp_path):
    """Ctrl-C (SIGINT to the foreground process group) while two models train side by side: the
    run ends with 130 and "interrupted", marked FAILED, no child left; the resume finishes it."""
    import subprocess
    import sys
    import time

    recipe = {**RECON, "train": {"epochs": 250, "batch_size": 4},
              "models": {"ae": AE, "ae2": {**AE, "channels": [4]}}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    env = {**os.environ, "FWK_THREADS": "2", "FWK_CACHE": str(tmp_path / "cache"),
           "FWK_RUNTIME_DIR": str(tmp_path / "procs")}
    env.pop("OMP_NUM_THREADS", None)
    p = subprocess.Popen([sys.executable, "-m", "fwk", "run", str(tmp_path / "r.yaml"), "--runs-dir",
                          str(tmp_path / "runs")], env=env, cwd=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = set()
    deadline = time.monotonic() + 240
    for line in p.stdout:  # both trainings under way
        seen |= {lb for lb in ("[ae] epoch", "[ae2/ae] epoch") if line.startswith(lb)}
        if len(seen) == 2 or time.monotonic() > deadline:
            break
    assert len(seen) == 2, seen
    os.killpg(p.pid, signal.SIGINT)
    out = p.communicate(timeout=120)[0]
    assert p.returncode == 130 and "fwk: interrupted" in out, out[-2000:]
    (run,) = (tmp_path / "runs").iterdir()
    assert (run / "FAILED").read_text().startswith("interrupted (Ctrl-C)")
    left = subprocess.run(["pgrep", "-g", str(p.pid)], capture_output=True, text=True).stdout.split()
    assert not left, left
    resumed = subprocess.run([sys.executable, "-m", "fwk", "--quiet", "run", "--resume", str(run)], env=env,
                             cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert resumed.returncode == 0 and (run / "metrics.json").exists(), resumed.stderr[-2000:]


def test_a_run_started_before_side_by_side_resumes_one_after_another(tmp_path, env):
    """A run whose versions.json lacks the side-by-side mark (started by an earlier fwk, whose
    models trained one after another with the run's threads) resumes the same way."""
    import shutil

    recipe = {**RECON, "models": {"ae": AE, "ae2": {**AE, "channels": [4]}}}
    run = _run(tmp_path, recipe, 2, "old", env)
    v = json.loads((run / "versions.json").read_text())
    assert v.pop("side_by_side") is True
    (run / "versions.json").write_text(json.dumps(v))
    for d in ("curves", "checkpoints", "tb"):  # as if it had stopped before its second model
        shutil.rmtree(run / d / "ae2", ignore_errors=True)
    for p in (run / "models").glob("ae2*"):
        p.unlink()
    execute(None, resume=str(run), quiet=True)
    assert _epoch_threads(run)["ae2"] == [2, 2, 2]
    log = (run / "log.txt").read_text()
    assert "this run started before fwk fitted models side by side (2026-12-03): its models are fitted one " \
           "after another, as when it started" in log
    from fwk.runs import ONE_AFTER_ANOTHER

    assert ONE_AFTER_ANOTHER == [False]  # the rule ends with the run
    again = _run(tmp_path, recipe, 2, "new", env)  # a new run in the same process: side by side
    assert _epoch_threads(again)["ae2"] == [1, 1, 1]


def test_seeds_side_by_side_fit_the_models_of_seeds_one_after_another_bit_for_bit(tmp_path, env):
    """A recipe's seeds side by side (fwk.seeds.seed_rounds): at 2 threads, seeds 0 and 1 in two
    processes with one thread each, then seed 2 alone with the run's two (its models side by side,
    one thread each): every seed's every model is bit for bit the one a 1-thread run fits, and
    the seeds' combined metrics are written."""
    recipe = {**RECON, "seeds": [0, 1, 2], "models": {"ae": AE, "pca": RECON["models"]["pca"]}}
    one = _run(tmp_path, recipe, 1, "one", env)
    two = _run(tmp_path, recipe, 2, "two", env)
    log = (two / "log.txt").read_text()
    assert ("seeds side by side: 2 at a time, each with 1 of the run's 2 threads (the last 1 with 2); "
            "train.side_by_side: false runs them one after another") in log
    assert "[seed 0] " in log and "[seed 1] " in log  # the forked seeds' lines, named
    last = log[log.index("[seed 2: 3/3]"):]  # the lone last seed, in the run's process: its models side by side
    assert last.splitlines()[3].startswith("fitting 2 models side by side, 2 at a time with 1 thread each")
    for s in (0, 1, 2):
        a, b = _states(one / f"seed-{s}"), _states(two / f"seed-{s}")
        assert set(a) == set(b) == {"ae", "pca"}
        _same(a, b, f"seed {s}")
        seen = _epoch_threads(two / f"seed-{s}")
        assert seen and all(set(v) == {1} for v in seen.values()), (s, seen)
    m = json.loads((two / "metrics.json").read_text())
    assert m["seeds"] == [0, 1, 2] and "seed_sd" in m["models"]["ae"]["test"]["l1"]
    v = json.loads((two / "versions.json").read_text())
    assert v["seeds_side_by_side"] is True


def test_a_failing_seed_fails_the_run_which_resumes_and_an_older_run_resumes_its_seeds_in_turn(tmp_path, env):
    """A seed whose model raises in its side-by-side process fails the run with the error's class
    (the other seed finishes); the resume runs what is left. A run started before seeds ran side
    by side (versions.json without the mark) resumes them one after another."""
    recipe = {**RECON, "seeds": [0, 1], "models": {"ae": AE, "ae2": {**AE, "channels": [4]}}}
    cls = get_registry().get("model", "ae")
    real = cls.fit

    def fit(self, data, ctx):
        if ctx.seed == 1 and ctx.scope == "ae2":
            raise DataError("ae2 refuses seed 1")
        return real(self, data, ctx)

    env.setattr(cls, "fit", fit)
    with pytest.raises(DataError, match="ae2 refuses seed 1"):
        _run(tmp_path, recipe, 2, "broken", env)
    (run,) = (tmp_path / "broken" / "runs").iterdir()
    assert (run / "FAILED").exists() and (run / "seed-0" / "metrics.json").exists()
    assert (run / "seed-1" / "FAILED").exists()
    env.setattr(cls, "fit", real)
    v = json.loads((run / "versions.json").read_text())
    assert v.pop("seeds_side_by_side") is True
    (run / "versions.json").write_text(json.dumps(v))
    execute(None, resume=str(run), quiet=True)
    log = (run / "log.txt").read_text()
    assert "seed 0: finished before, not run again" in log
    assert "this run started before fwk ran seeds side by side (2026-12-03): its seeds run one after another" in log
    assert (run / "metrics.json").exists() and set(_states(run / "seed-1")) == {"ae", "ae2"}
    from fwk.runs import SEEDS_ONE_AFTER_ANOTHER

    assert SEEDS_ONE_AFTER_ANOTHER == [False]
