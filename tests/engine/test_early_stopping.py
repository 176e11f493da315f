"""train.early_stopping and the training curves: the rule against a naive reference, exact resume
after a crash or a kill (the same stopping epoch, the same weights, the same record), the record
against TensorBoard's scalars, settings validated like a recipe's."""
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from fwk.engine import EarlyStopping, TrainConfig, fit
from fwk.engine.callbacks import stopping_rule
from fwk.errors import RecipeError
from fwk.runs import make_test_context
from fwk.safeio import load_state
from regression import _data, _module

pytestmark = pytest.mark.usefixtures("one_thread_count")  # the tests compare trainings bit for bit


HERE = Path(__file__).resolve().parent
RULE = {"patience": 2, "min_delta": 0.02}  # the data below: the rule ends training at epoch 25 of 40


def _ctx(tmp_path, epochs=40, **kw):
    return make_test_context(tmp_path, seed=0, epochs=epochs, batch_size=8, lr=1e-2, lr_decay=0.9, **kw)


def _params(m):
    return {k: v.detach().clone() for k, v in m.state_dict().items()}


def _same(p, q):
    return p.keys() == q.keys() and all(torch.equal(p[k], q[k]) for k in p)


def _curves(ctx, name="reg"):
    return json.loads((ctx.run_dir / "curves" / f"{name}.json").read_text())


def _losses(record):
    """The record without what may differ between an uninterrupted and a resumed run."""
    return [{k: v for k, v in e.items() if k not in ("seconds", "threads")} for e in record["epochs"]]


# ------------------------------------------------------------------------------- the rule

def _naive_stop(values, patience):
    """min_delta = 0: the first epoch e (1-based) at which the last ``patience`` values are all no
    lower than the minimum before them; a non-finite value stops at once."""
    for e in range(1, len(values) + 1):
        if not math.isfinite(values[e - 1]):
            return e
        if e > patience and min(values[e - patience:e]) >= min(values[:e - patience]):
            return e
    return None


def test_stopping_rule_against_a_naive_reference():
    rng = np.random.default_rng(0)
    for trial in range(300):
        n = int(rng.integers(1, 30))
        patience = int(rng.integers(1, 6))
        # noisy decreasing curves, some with ties (rounded)
        v = np.cumsum(-np.abs(rng.normal(0.05, 0.05, n))) + rng.normal(0, 0.05, n)
        v = np.round(v, 1) if trial % 3 == 0 else v
        d = stopping_rule(list(v), patience, 0.0)
        assert d["epoch"] == _naive_stop(list(v), patience), (list(v), patience)
        assert d["stop"] == (d["epoch"] is not None)


def _naive_relative(values, patience, frac):
    """The relative rule spelled out: the reference is the last value that beat the reference
    before it by more than frac of that reference's magnitude; stop when patience values in a
    row did not."""
    ref, wait = None, 0
    for e, v in enumerate(values, start=1):
        if ref is None or ref - v > frac * abs(ref):
            ref, wait = v, 0
        else:
            wait += 1
        if wait >= patience:
            return e
    return None


def test_relative_min_delta_against_a_naive_reference_and_scale_free():
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(1, 40))
        patience = int(rng.integers(1, 6))
        frac = float(rng.choice([0.0, 0.001, 0.01, 0.05]))
        v = list(np.exp(-np.cumsum(np.abs(rng.normal(0.03, 0.03, n)))) * (1 + rng.normal(0, 0.01, n)))
        d = stopping_rule(v, patience, frac, relative=True)
        assert d["epoch"] == _naive_relative(v, patience, frac)
        # the same curve in other units stops at the same epoch (the absolute rule would not)
        assert stopping_rule([x * 1e-4 for x in v], patience, frac, relative=True)["epoch"] == d["epoch"]
    # 0.1 % of 1e-2 is 1e-5: an improvement of 2e-5 counts, one of 5e-6 does not
    assert stopping_rule([1e-2, 0.998e-2], 1, 1e-3, relative=True)["stop"] is False
    assert stopping_rule([1e-2, 0.9995e-2], 1, 1e-3, relative=True)["stop"] is True


def test_stopping_rule_min_delta_and_non_finite():
    # improvements of 0.01 are not improvements with min_delta 0.02: the reference stays at 1.0
    assert stopping_rule([1.0, 0.99, 0.98], 2, 0.02) == {"stop": True, "reason": "no improvement", "epoch": 3,
                                                          "wait": 2, "best": 1.0}
    # improvement by more than min_delta resets the count, and becomes the new reference
    d = stopping_rule([1.0, 0.99, 0.95, 0.94, 0.93], 2, 0.02)
    assert d["epoch"] == 5 and d["best"] == 0.95
    assert stopping_rule([1.0, 0.5, 0.25], 2, 0.02)["stop"] is False
    assert stopping_rule([1.0, float("nan")], 5, 0.0)["reason"] == "non-finite"
    assert stopping_rule([], 1, 0.0)["stop"] is False


def test_early_stopping_settings_validated():
    c = TrainConfig(early_stopping={"patience": 3})
    assert c.early_stopping == EarlyStopping(patience=3, min_delta=0.0, monitor="val_loss")
    assert TrainConfig().early_stopping is None  # off by default
    assert TrainConfig().replace(early_stopping={"min_delta": 1e-3}).early_stopping.patience == 10
    with pytest.raises(RecipeError, match="train.early_stopping.patince.*patience"):
        TrainConfig(early_stopping={"patince": 3})
    with pytest.raises(RecipeError, match="train.early_stopping.patience"):
        EarlyStopping(patience=0)
    with pytest.raises(RecipeError, match="train.early_stopping.min_delta"):
        EarlyStopping(min_delta=-1)
    with pytest.raises(RecipeError, match="train.early_stopping"):
        TrainConfig(early_stopping=3)


def test_recipe_key(tmp_path):
    from fwk.plugins import get_registry
    from fwk.recipes import resolve, to_plain

    data = {"task": "reconstruct", "dataset": "synthetic-heads", "models": {"pca": "pca"},
            "train": {"epochs": 50, "early_stopping": {"patience": 5, "min_delta": 1e-4}}}
    train = resolve(data, get_registry()).train
    assert train.epochs == 50 and train.early_stopping == EarlyStopping(5, 1e-4, "val_loss")
    assert to_plain(train)["early_stopping"] == {"patience": 5, "min_delta": 1e-4, "monitor": "val_loss",
                                                 "relative": False}
    rel = resolve({**data, "train": {"early_stopping": {"patience": 5, "min_delta": 1e-3, "relative": True}}},
                  get_registry()).train.early_stopping
    assert rel.relative is True and rel.min_delta == 1e-3
    with pytest.raises(RecipeError, match="train.early_stopping.relative"):
        resolve({**data, "train": {"early_stopping": {"relative": "yes"}}}, get_registry())
    with pytest.raises(RecipeError, match="train.early_stopping.patience"):
        resolve({**data, "train": {"early_stopping": {"patience": "x"}}}, get_registry())


# ------------------------------------------------------------------------------- training

def test_the_rule_ends_training_and_the_record_says_why(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train, val = _data()
    ctx = _ctx(tmp_path, early_stopping=RULE)
    m = fit(_module(), train, val, ctx, "reg")
    r = _curves(ctx)
    assert r["stopped_by"] == "early_stopping" and r["stop_reason"] == "no improvement"
    assert r["finished"] and r["max_epochs"] == 40 and r["early_stopping"] == {**RULE, "monitor": "val_loss", "relative": False}
    e = r["stopped_epoch"]
    assert 2 < e < 40 and r["epochs_run"] == e and m.steps == 4 * e  # 32 samples, batch 8
    val_losses = [x["val_loss"] for x in r["epochs"]]
    assert [x["epoch"] for x in r["epochs"]] == list(range(1, e + 1))
    assert stopping_rule(val_losses, 2, 0.02)["epoch"] == e
    assert stopping_rule(val_losses[:-1], 2, 0.02)["stop"] is False
    assert r["best_val_loss"] == min(val_losses) and val_losses[r["best_epoch"] - 1] == min(val_losses)
    # the record holds the epoch means TensorBoard holds
    (d,) = {p.parent for p in (ctx.run_dir / "tb" / "reg").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    for key in ("train_loss", "val_loss"):
        tb = [s.value for s in ea.Scalars(key)]
        assert np.allclose(tb, [x[key] for x in r["epochs"]], rtol=1e-6), key
    # the last checkpoint is the last epoch trained, and it knows the rule fired
    ck = load_state(ctx.run_dir / "checkpoints" / "reg" / "last.ckpt")
    assert ck["epoch"] == e - 1 and ck["fwk_curves"]["stop"] == {"epoch": e, "reason": "no improvement"}


def test_without_the_rule_training_runs_every_epoch(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, epochs=3)
    m = fit(_module(), train, val, ctx, "reg")
    r = _curves(ctx)
    assert m.steps == 12 and r["epochs_run"] == 3 and r["stopped_by"] == "max_epochs" and r["stopped_epoch"] == 3
    assert r["early_stopping"] is None and r["finished"]
    assert all(set(x) >= {"epoch", "train_loss", "val_loss", "seconds", "threads"} for x in r["epochs"])


def test_without_validation_the_rule_is_not_applied(tmp_path):
    train, _ = _data()
    ctx = _ctx(tmp_path, epochs=3, early_stopping=RULE)
    m = fit(_module(), train, None, ctx, "reg")
    r = _curves(ctx)
    assert m.steps == 12 and r["stopped_by"] == "max_epochs" and r["early_stopping"] is None
    assert "not applied" in r["note"] and r["best_epoch"] is None
    assert all("val_loss" not in x for x in r["epochs"])


def test_a_monitor_the_module_does_not_log_is_named(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, epochs=3, early_stopping={"monitor": "val_l2"})
    with pytest.raises(RecipeError, match="val_l2.*logged: train_loss, val_loss"):
        fit(_module(), train, val, ctx, "reg")


def test_crashed_and_resumed_stops_at_the_same_epoch_with_the_same_weights(tmp_path):
    train, val = _data()
    a = _ctx(tmp_path / "a", early_stopping=RULE)
    straight = _params(fit(_module(), train, val, a, "reg"))
    ra = _curves(a)
    b = _ctx(tmp_path / "b", early_stopping=RULE)
    with pytest.raises(RuntimeError, match="killed"):
        fit(_module(crash_at_step=4 * 9 + 2), train, val, b, "reg")  # in epoch 10
    assert _curves(b)["epochs_run"] == 9 and not _curves(b)["finished"]
    b.resume = True
    torch.manual_seed(77)  # whatever the process did in between
    m = fit(_module(), train, val, b, "reg")
    assert m.steps == 4 * (ra["stopped_epoch"] - 9)  # epochs 10.. only
    assert _same(_params(m), straight)
    rb = _curves(b)
    assert _losses(rb) == _losses(ra)
    assert {k: v for k, v in rb.items() if k != "epochs"} == {k: v for k, v in ra.items() if k != "epochs"}
    # resumed after the rule fired: loaded, not trained further, record unchanged
    (b.run_dir / "curves" / "reg.json").unlink()
    m = fit(_module(), train, val, b, "reg")
    assert m.steps == 0 and _same(_params(m), straight) and _losses(_curves(b)) == _losses(ra)


@pytest.mark.slow
def test_killed_process_resumed_stops_at_the_same_epoch_with_the_same_weights(tmp_path):
    script = tmp_path / "train.py"
    script.write_text(textwrap.dedent(f"""
        import sys, torch
        sys.path.insert(0, {str(HERE)!r})
        from test_early_stopping import _data, _module, _ctx
        from fwk.engine import fit
        from pathlib import Path
        out, resume = Path(sys.argv[1]), sys.argv[2] == "resume"
        train, val = _data()
        ctx = _ctx(out, early_stopping={RULE!r})
        ctx.resume = resume
        m = fit(_module(sleep=float(sys.argv[3])), train, val, ctx, "reg")
        torch.save({{k: v for k, v in m.state_dict().items()}}, out / "weights.pt")
    """))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    subprocess.run([sys.executable, str(script), str(tmp_path / "a"), "fresh", "0"], check=True, env=env)
    p = subprocess.Popen([sys.executable, str(script), str(tmp_path / "b"), "fresh", "0.05"], env=env)
    ck = tmp_path / "b" / "run" / "checkpoints" / "reg"
    deadline, killed = time.time() + 120, False
    while time.time() < deadline and p.poll() is None:
        if any(ck.glob("epoch00[4-9].ckpt")):
            p.send_signal(signal.SIGKILL)
            killed = True
            break
        time.sleep(0.02)
    p.wait()
    assert killed, "the training ended before it could be killed"
    done = json.loads((tmp_path / "b" / "run" / "curves" / "reg.json").read_text())
    assert not done["finished"] and done["epochs_run"] < 20
    subprocess.run([sys.executable, str(script), str(tmp_path / "b"), "resume", "0"], check=True, env=env)
    wa = torch.load(tmp_path / "a" / "weights.pt")
    wb = torch.load(tmp_path / "b" / "weights.pt")
    assert _same(wa, wb)
    ra = json.loads((tmp_path / "a" / "run" / "curves" / "reg.json").read_text())
    rb = json.loads((tmp_path / "b" / "run" / "curves" / "reg.json").read_text())
    assert rb["stopped_by"] == "early_stopping" and rb["stopped_epoch"] == ra["stopped_epoch"]
    assert _losses(rb) == _losses(ra)


def test_curves_are_named_by_scope(tmp_path):
    from fwk.engine.trainer import network_name

    train, val = _data()
    ctx = _ctx(tmp_path, epochs=1).scoped("pb")
    fit(_module(), train, val, ctx, "pb-step2")
    r = json.loads((ctx.run_dir / "curves" / "pb" / "pb-step2.json").read_text())
    assert r["network"] == "pb/pb-step2"
    assert network_name(_ctx(tmp_path, 1).scoped("vae"), "vae") == "vae"
    assert network_name(_ctx(tmp_path, 1), "vae") == "vae"
