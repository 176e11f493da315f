"""benchmarks/precision_decision.py: the bf16 decision of issue 28 from two seeds runs, on fake runs
whose answers are known (the rule: a difference within the larger seed sd is within the spread)."""
import json

import pytest
import yaml

from .scripts import load_benchmark


def _summary(mean, sd):
    return {"mean": mean, "seed_sd": sd, "n": 5, "units": "input"}


def _run(path, precision, pbs_dame, name="r", seeds=(0, 1, 2), epochs=3):
    path.mkdir(parents=True)
    recipe = {"name": name, "task": "blendshapes", "train": {"epochs": epochs}}
    if precision:
        recipe["train"]["precision"] = precision
    (path / "recipe.yaml").write_text(yaml.safe_dump(recipe))
    models = {"dt": {"test": {"l1": _summary(2.0, 0.0), "dame": _summary(5.0, 0.0)}},
              "pbs": {"test": {"l1": _summary(1.0, 0.05), "dame": _summary(*pbs_dame)}},
              "pbs:pb-dr-norm": {"test": {"l1": _summary(1.2, 0.05), "dame": _summary(3.0, 0.1)}}}
    blend = {"mouth-wide": {"pbs": {"l1": _summary(1.1, 0.05), "dame": _summary(*pbs_dame)}}}
    nets = {f"seed-{s}/pbs": {"train_s": 60.0 if precision is None else 40.0} for s in seeds}
    (path / "metrics.json").write_text(json.dumps({"models": models, "blendshapes": blend, "seeds": list(seeds),
                                                   "split_seed": 0, "training": {"networks": nets}}))
    return path


def test_within_the_spread_is_adoptable_beyond_is_not(tmp_path, capsys):
    mod = load_benchmark("precision_decision")
    a = _run(tmp_path / "fp32", None, (4.0, 0.1))
    b = _run(tmp_path / "bf16", "bf16-mixed", (4.08, 0.05), name="r-bf16")  # 0.08 apart, larger sd 0.1: a tie
    assert mod.main([str(a), str(b)]) == 0
    out = capsys.readouterr().out
    assert "| pbs | all | dame | 4 ± 0.1 | 4.08 ± 0.05 | +2.00 % | yes |" in out
    assert "- pbs: bf16-mixed **adoptable**: all 4 within the spread; training 60 s against 40 s a seed (1.50x)." in out
    assert "- dt: trains no network, the precision does not apply" in out
    c = _run(tmp_path / "bf16b", "bf16-mixed", (4.2, 0.05))  # 0.2 apart: beyond
    assert mod.main([str(a), str(c)]) == 0
    out = capsys.readouterr().out
    assert ("- pbs: bf16-mixed **not adoptable**: 2 of 4 beyond the spread (all dame +5.0 %, mouth-wide dame "
            "+5.0 %)") in out
    assert "- pbs:pb-dr-norm: bf16-mixed **adoptable**: all 2 within the spread." in out


def test_other_recipes_and_one_seed_are_refused(tmp_path):
    mod = load_benchmark("precision_decision")
    a = _run(tmp_path / "fp32", None, (4.0, 0.1))
    with pytest.raises(SystemExit, match="recipes differ beyond train.precision: train"):
        mod.main([str(a), str(_run(tmp_path / "b", "bf16-mixed", (4.0, 0.1), epochs=5))])
    with pytest.raises(SystemExit, match="not a run of 2 or more seeds"):
        mod.main([str(a), str(_run(tmp_path / "c", "bf16-mixed", (4.0, 0.1), seeds=(0,)))])
    with pytest.raises(SystemExit, match="no metrics.json"):
        mod.main([str(a), str(tmp_path / "missing")])
