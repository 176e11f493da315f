"""benchmarks/claims_ch5.py reads a chapter 5 run and decides C5 (end-to-end against two-step)
and C6 (PBS against DT) per expression by the sign of differences of means: checked on a fake
run whose answers are known."""
import json

from .scripts import load_benchmark


def _module():
    return load_benchmark("claims_ch5")


def _m(l1, dame, fmpd):
    return {"l1": {"mean": l1}, "dame": {"mean": dame}, "fmpd": {"mean": fmpd}}


def test_pairs_by_label():
    labels = ["dt-0", "pbs", "pbs:pb-euclidean-std", "pbs:pb-dr-norm", "pb-euclidean-std-two-step",
              "pb-dr-norm-two-step", "pb-dr-std-two-step"]  # the last has no partner
    assert _module().pairs(labels) == [("pbs:pb-euclidean-std", "pb-euclidean-std-two-step"),
                                       ("pbs:pb-dr-norm", "pb-dr-norm-two-step")]


def test_c5_and_c6_verdicts(tmp_path, capsys):
    run = tmp_path / "ch5"
    run.mkdir()
    per = {
        # e2e better perceptually; PBS beats both DTs on L1 and DAME
        "smile": {"pbs": _m(1e-3, 1e-2, 1e-2), "dt-0": _m(2e-3, 2e-2, 1e-2), "dt-1": _m(1.5e-3, 1.2e-2, 1e-2),
                  "pbs:pb-euclidean-std": _m(1e-3, 1e-2, 1e-2), "pb-euclidean-std-two-step": _m(1e-3, 2e-2, 2e-2)},
        # two-step better on FMPD; PBS loses DAME to dt-1
        "frown": {"pbs": _m(1e-3, 1e-2, 1e-2), "dt-0": _m(2e-3, 2e-2, 1e-2), "dt-1": _m(1.5e-3, 0.5e-2, 1e-2),
                  "pbs:pb-euclidean-std": _m(1e-3, 1e-2, 1e-2), "pb-euclidean-std-two-step": _m(1e-3, 2e-2, 0.5e-2)},
        "pucker": {"pbs": _m(1e-3, 1e-2, 1e-2), "dt-0": _m(2e-3, 2e-2, 1e-2), "dt-1": _m(1.5e-3, 1.2e-2, 1e-2),
                   "pbs:pb-euclidean-std": _m(1e-3, 1e-2, 1e-2), "pb-euclidean-std-two-step": _m(1e-3, 2e-2, 2e-2)},
    }
    nets = {"pbs/smile": {"epochs_run": 30, "max_epochs": 50, "stopped_by": "early_stopping", "plateau": "plateau",
                          "train_s": 120.0}}
    (run / "metrics.json").write_text(json.dumps({"blendshapes": per, "pbs": {"pbs": {"k": {"smile": 500}}},
                                                  "training": {"networks": nets}}))
    assert _module().main([str(run)]) == 0
    out = capsys.readouterr().out
    assert ("C5, pbs:pb-euclidean-std against pb-euclidean-std-two-step: end-to-end lower on both perceptual "
            "metrics for 2 of 3 expressions: holds.") in out
    assert "C6, pbs: lower L1 and DAME than every DT source for 2 of 3 expressions: holds." in out
    assert "| pbs | dt-0 | smile | 500 | 1.000 / 2.000 | +100.0 % | 1.000 / 2.000 | +100.0 % | yes |" in out
    assert "| pbs | dt-1 | frown |  | 1.000 / 1.500 | +50.0 % | 1.000 / 0.500 | -50.0 % | no |" in out
    assert "| pbs/smile | 30/50 | early_stopping | plateau | 2.0 |" in out
