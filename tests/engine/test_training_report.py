"""The training curves in every report: found in the run and its sub-runs, summarised (the
plateau test against a naive reference), drawn, tabled; metrics.json's other keys unchanged."""
import json
import math

import numpy as np
import pytest
from test_early_stopping import RULE, _ctx, _data, _module

from fwk.engine import fit
from fwk.evaluation import write_report
from fwk.evaluation.curves import PLATEAU_RULE, find_curves, plateau, summarise


def _naive_plateau(v):
    """The module docstring's definition, spelled out with loops."""
    E = len(v)
    w = 5
    while w < 0.1 * E:
        w += 1
    if E < w + 1:
        return None
    ref = v[0]
    for x in v[:E - w]:
        ref = x if x < ref else ref
    best = ref
    for x in v[E - w:]:
        best = x if x < best else best
    return (ref - best) / abs(ref)


def test_plateau_against_a_naive_reference():
    rng = np.random.default_rng(1)
    for _ in range(300):
        E = int(rng.integers(1, 120))
        v = list(np.exp(-np.linspace(0, rng.uniform(0.1, 5), E)) * (1 + rng.normal(0, 0.05, E)) + 0.1)
        p = plateau(v)
        ref = _naive_plateau(v)
        if ref is None:
            assert p["improvement"] is None and p["verdict"] == "too few epochs"
        else:
            assert p["improvement"] == pytest.approx(ref, rel=1e-12, abs=1e-15)
            assert p["verdict"] == ("plateau" if ref < 0.01 else "improving")
        assert p["window"] == max(5, math.ceil(0.1 * E))


def test_plateau_cases():
    assert plateau([1.0] * 6)["verdict"] == "plateau"
    assert plateau([1.0] * 5 + [0.5])["improvement"] == 0.5
    assert plateau([1.0, 0.5] + [0.6] * 9)["verdict"] == "plateau"  # best long ago, nothing better since
    assert plateau([1.0] * 100 + [0.995] * 10)["improvement"] == pytest.approx(0.005)  # w = 10
    assert plateau([None] * 10)["verdict"] == "no validation"
    assert plateau([1.0, float("nan")] * 5 + [0.5])["improvement"] == 0.5


def _trained_run(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, early_stopping=RULE)
    fit(_module(), train, val, ctx.scoped("reg"), "reg")
    fit(_module(), train, None, ctx.scoped("b"), "b-step1")  # no validation
    sub = ctx.child("reconstruct")  # a sub-run (edit's inline reconstruct)
    fit(_module(), train, val, sub.scoped("vae"), "vae")
    return ctx


def test_curves_found_in_the_run_and_its_sub_runs(tmp_path):
    ctx = _trained_run(tmp_path)
    (ctx.run_dir / "curves" / "broken.json").write_text("{")  # unreadable: skipped
    recs = find_curves(ctx.run_dir)
    assert list(recs) == ["b/b-step1", "reg", "reconstruct/vae"]
    assert recs["reg"]["stopped_by"] == "early_stopping"
    assert find_curves(tmp_path / "nothing") == {}


def test_report_has_the_training_section_and_metrics_keep_their_keys(tmp_path):
    ctx = _trained_run(tmp_path)
    results = {"models": {"reg": {"test": {"l1": {"mean": 0.5}}}}, "timing": {"reg": {"fit_s": 1.0}}}
    write_report(ctx, "T", results, notes=["n"])
    m = json.loads((ctx.run_dir / "metrics.json").read_text())
    assert list(m) == ["models", "timing", "figures", "notes", "training"]
    assert m["models"] == results["models"] and m["timing"] == results["timing"] and m["figures"] == {}
    t = m["training"]
    assert t["plateau_rule"] == PLATEAU_RULE and list(t["networks"]) == ["b/b-step1", "reg", "reconstruct/vae"]
    reg = t["networks"]["reg"]
    rec = json.loads((ctx.run_dir / "curves" / "reg" / "reg.json").read_text())
    assert reg == summarise(rec)
    assert reg["stopped_by"] == "early_stopping" and reg["epochs_run"] == rec["stopped_epoch"] < 40
    assert reg["best_val_loss"] == min(e["val_loss"] for e in rec["epochs"])
    assert reg["train_s"] == pytest.approx(sum(e["seconds"] for e in rec["epochs"]), abs=1e-3) and reg["train_s"] > 0
    assert t["networks"]["b/b-step1"]["plateau"] == "no validation"
    assert t["figures"] == ["figures/training_curves.png"]
    assert (ctx.run_dir / "figures" / "training_curves.png").stat().st_size > 1000
    md = (ctx.run_dir / "report.md").read_text()
    assert "## Training" in md and "![training curves](figures/training_curves.png)" in md
    lines = md.split("## Training")[1].splitlines()
    row = next(line for line in lines if line.startswith("| reg |"))
    assert f"| {reg['epochs_run']} / 40 | rule, epoch {reg['epochs_run']} |" in row
    assert "| 40 / 40 | max epochs |" in next(line for line in lines if line.startswith("| b/b-step1 |"))
    assert row.rstrip().endswith(" s |")  # the training time, e.g. "| 0 s |"
    assert "plateau when its best validation loss improved by less than 1%" in md
    assert "stop after 2 epochs in a row without a val_loss below the best by more than 0.02" in md


def test_training_time_counts_every_epoch_of_a_resumed_run():
    """train_s sums the epochs the curves hold, those of an earlier attempt included; an epoch
    without a time (an old curves file) gives no total."""
    epochs = [{"epoch": i + 1, "val_loss": 1.0 / (i + 1), "seconds": 2.5} for i in range(6)]
    assert summarise({"epochs": epochs})["train_s"] == 15.0
    epochs[2]["seconds"] = None
    assert summarise({"epochs": epochs})["train_s"] is None


def test_report_without_training_has_no_section(tmp_path):
    ctx = _ctx(tmp_path)
    write_report(ctx, "T", {"models": {"pca": {"test": {"l1": {"mean": 0.5}}}}})
    assert "training" not in json.loads((ctx.run_dir / "metrics.json").read_text())
    assert "## Training" not in (ctx.run_dir / "report.md").read_text()


def test_fwk_report_rebuilds_the_section(tmp_path):
    from fwk.cli import main

    ctx = _trained_run(tmp_path)
    write_report(ctx, "T", {"models": {"reg": {"test": {"l1": {"mean": 0.5}}}}})
    before = json.loads((ctx.run_dir / "metrics.json").read_text())["training"]
    (ctx.run_dir / "report.md").unlink()
    assert main(["report", str(ctx.run_dir)]) == 0
    assert json.loads((ctx.run_dir / "metrics.json").read_text())["training"] == before
    assert "## Training" in (ctx.run_dir / "report.md").read_text()
    # a run directory whose curves are gone keeps the summary it had
    import shutil

    for d in ctx.run_dir.rglob("curves"):
        shutil.rmtree(d)
    assert main(["report", str(ctx.run_dir)]) == 0
    assert json.loads((ctx.run_dir / "metrics.json").read_text())["training"] == before
    assert "## Training" in (ctx.run_dir / "report.md").read_text()


def test_many_networks_make_several_figures(tmp_path):
    ctx = _ctx(tmp_path, epochs=2)
    train, val = _data()
    for i in range(9):
        fit(_module(), train, val, ctx.scoped(f"n{i}"), f"n{i}")
    write_report(ctx, "T", {})
    assert json.loads((ctx.run_dir / "metrics.json").read_text())["training"]["figures"] == [
        "figures/training_curves.png", "figures/training_curves-2.png"]
