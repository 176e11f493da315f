"""benchmarks/claims_ch4.py reads a chapter 4 run (and its k study) and decides C4 per dsm model
and split by the Pareto front of the learned models: checked on fake runs whose answers are known."""
import json

from .scripts import load_benchmark


def _module():
    return load_benchmark("claims_ch4")


def _run(d, models: dict, seconds=30.0):
    """models: {label: {split: (l1, dame)}}; every learned model trained 10 epochs of ``seconds``."""
    d.mkdir(parents=True)
    res = {k: {s: {"l1": {"mean": v[0]}, "dame": {"mean": v[1]}, "fmpd": {"mean": v[1] * 2}} for s, v in r.items()}
           for k, r in models.items()}
    nets = {k: {"epochs_run": 10, "max_epochs": 100, "stopped_by": "early_stopping", "plateau": "plateau",
                "train_s": 10 * seconds} for k in models if k != "mean-shape"}
    (d / "metrics.json").write_text(json.dumps({"models": res, "training": {"networks": nets}}))


def test_c4_readings_per_split(tmp_path, capsys):
    run = tmp_path / "ch4"
    _run(run, {
        "mean-shape": {"train": (10.0, 2.0), "test": (10.0, 2.0)},
        # train: dsm best DAME, on the front (holds); test: on the front by L1 only (partly)
        "dsm": {"train": (3.0, 1.0), "test": (2.0, 3.0)},
        # off the front on both (dominated by spiralnet++)
        "dsm-g04": {"train": (5.0, 4.0), "test": (5.0, 5.0)},
        "spiralnet++": {"train": (2.0, 3.0), "test": (3.0, 2.5)},
        "vae-dr-norm": {"train": (6.0, 1.5), "test": (6.0, 1.0)},
    })
    mod = _module()
    models = mod.load(run)
    front, read = mod.reading(models, "train")
    assert front == ["spiralnet++", "dsm"]  # sorted by L1; vae-dr-norm is dominated by dsm
    assert read["dsm"] == {"front": True, "dame_rank": 1, "l1_rank": 2, "n": 4, "beats_mean": True, "verdict": "holds"}
    assert read["dsm-g04"]["verdict"] == "does not hold"
    front, read = mod.reading(models, "test")
    assert read["dsm"]["verdict"] == "partly" and read["dsm"]["beats_mean"] is False  # DAME 3.0 above the mean's 2.0
    assert models["dsm"]["training"]["minutes"] == 5.0
    assert mod.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "C4, dsm, train: on the front; DAME rank 1 and L1 rank 2 of 4 learned models; beats the mean shape" in out
    assert "| mean-shape | 10000.000 | 200.000 | 400.000 | (baseline) |" in out


def test_k_study_table(tmp_path, capsys):
    run, krun = tmp_path / "ch4", tmp_path / "k"
    _run(run, {"dsm": {"test": (2.0, 1.0)}, "spiralnet++": {"test": (1.0, 2.0)}})
    for k, (l1, dame) in {10: (3.0, 1.0), 500: (2.0, 2.0), 2000: (2.5, 2.5)}.items():
        _run(krun / f"k{k}", {"dsm": {"test": (l1, dame)}})
    (krun / "k50").mkdir()  # unfinished member: skipped
    mod = _module()
    assert [k for k, _ in mod.k_rows(krun)] == [10, 500, 2000]
    assert mod.main([str(run), "--k", str(krun), "--splits", "test"]) == 0
    out = capsys.readouterr().out
    assert "| 10 | 3000.000 | 100.000 | 200.000 | yes |" in out
    assert "| 2000 | 2500.000 | 250.000 | 500.000 | no |" in out
