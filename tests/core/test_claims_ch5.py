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
            "metrics for 2 of 3 expressions: holds (one seed; every deciding margin 10 % or more).") in out
    assert ("C6, pbs: lower L1 and DAME than every DT source for 2 of 3 expressions: holds (one seed; every deciding "
            "margin 10 % or more). L1 alone 3 of 3: holds; DAME alone 2 of 3: holds.") in out
    assert "| pbs | dt-0 | smile | 500 | 1.000 / 2.000 | +100.0 % | 1.000 / 2.000 | +100.0 % | yes |" in out
    assert "| pbs | dt-1 | frown |  | 1.000 / 1.500 | +50.0 % | 1.000 / 0.500 | -50.0 % | no |" in out
    assert "| pbs/smile | 30/50 | early_stopping | plateau | 2.0 |" in out


# docs/methods/claims.md, "Chapter 5 at the budget's plateau": ch5_plateau-20261201-234509, test means
# (L1 x1e-3, DAME x1e-2, FMPD x1e-2) as the page prints them
CH5 = {
    "face-compression": {"dt-0": (1.947, 0.173, 0.233), "dt-1": (2.178, 0.164, 0.244), "dt-2": (2.053, 0.163, 0.256),
                         "pbs:pb-euclidean-std": (1.042, 0.699, 6.508), "pb-euclidean-std-two-step": (1.185, 0.973, 8.853),
                         "pbs:pb-dr-norm": (1.194, 0.185, 0.456), "pb-dr-norm-two-step": (1.424, 0.186, 0.463),
                         "pbs": (1.059, 0.193, 0.432)},
    "mouth-wide": {"dt-0": (2.677, 0.212, 0.481), "dt-1": (2.971, 0.243, 0.609), "dt-2": (2.965, 0.216, 0.424),
                   "pbs:pb-euclidean-std": (1.298, 0.861, 5.925), "pb-euclidean-std-two-step": (1.426, 1.682, 11.204),
                   "pbs:pb-dr-norm": (1.848, 0.203, 0.394), "pb-dr-norm-two-step": (2.080, 0.211, 0.454),
                   "pbs": (1.319, 0.228, 0.384)},
    "oo-brow-raise-eyes-wide": {"dt-0": (2.014, 0.182, 0.586), "dt-1": (2.835, 0.225, 1.208),
                                "dt-2": (2.179, 0.185, 0.365), "pbs:pb-euclidean-std": (0.997, 0.617, 5.448),
                                "pb-euclidean-std-two-step": (1.204, 0.939, 7.854),
                                "pbs:pb-dr-norm": (1.326, 0.203, 0.406), "pb-dr-norm-two-step": (1.444, 0.203, 0.452),
                                "pbs": (1.021, 0.230, 0.406)},
}


def test_the_chapter_5_run_gives_the_pages_verdicts(tmp_path, capsys):
    """The page's C5, C6, C9, C10 and C14 words are what the rule gives on its numbers. The page prints 3
    digits: oo-brow-raise's DR Norm. DAME is 0.203 for both, a tie by equal means."""
    run = tmp_path / "ch5_plateau-20261201-234509"
    run.mkdir()
    per = {e: {lb: _m(l1 * 1e-3, dame * 1e-2, fmpd * 1e-2) for lb, (l1, dame, fmpd) in r.items()}
           for e, r in CH5.items()}
    (run / "metrics.json").write_text(json.dumps({"blendshapes": per, "pbs": {"pbs": {"k": {e: 1000 for e in CH5}}}}))
    assert _module().main([str(run)]) == 0
    out = capsys.readouterr().out
    assert ("C5, pbs:pb-euclidean-std against pb-euclidean-std-two-step: end-to-end lower on both perceptual metrics "
            "for 3 of 3 expressions: holds (one seed; every deciding margin 10 % or more). End-to-end lower L1 on "
            "3 of 3.") in out
    assert ("C5, pbs:pb-dr-norm against pb-dr-norm-two-step: end-to-end lower on both perceptual metrics for 2 of 3 "
            "expressions: holds (one seed; deciding margins under 10 %: face-compression DAME 0.54 %, face-compression "
            "FMPD 1.5 %, mouth-wide DAME 3.9 %; counting those as ties: 0 of 3, does not hold). End-to-end lower L1 on "
            "3 of 3.") in out  # oo-brow-raise: DAME 0.203 against 0.203 at the page's digits, a tie
    assert ("C6, pbs: lower L1 and DAME than every DT source for 0 of 3 expressions: does not hold (one seed; every "
            "deciding margin 10 % or more). L1 alone 3 of 3: holds; DAME alone 0 of 3: does not hold.") in out
    assert ("C9, pbs: chosen k face-compression 1000, mouth-wide 1000, oo-brow-raise-eyes-wide 1000: does not hold"
            ) in out
    assert "C10, pbs against pbs:pb-euclidean-std on L1: PBS lower for 0 of 3 expressions" in out
    assert ": does not hold (one seed; deciding margins under 10 %: face-compression 1.6 %, mouth-wide 1.6 %, " \
           "oo-brow-raise-eyes-wide 2.4 %; counting those as ties: 0 of 3, does not hold)." in out
    assert ("C14, pb-euclidean-std-two-step against every DT source: lower L1 for 3 of 3 expressions: holds; lower "
            "DAME for 0 of 3: does not hold (one seed).") in out
    assert ("C14, pb-dr-norm-two-step against every DT source: lower L1 for 3 of 3 expressions: holds; lower DAME "
            "for 1 of 3: partly (one seed).") in out


def test_c9_over_seeds_counts_the_seeds_whose_k_differ_across_expressions(tmp_path, capsys):
    """In a run with seeds, metrics.json gives a k every seed chose as one number and different
    choices as {"by_seed": ...}: C9 lists the k per seed and counts the seeds on which they differ
    across expressions (the rule's holds / partly / does not hold over those seeds)."""
    run = tmp_path / "ch5-seeds"
    run.mkdir()
    row = {"pbs": _m(1e-3, 1e-2, 1e-2), "dt-0": _m(2e-3, 2e-2, 1e-2)}
    per = {"smile": row, "frown": row}
    cases = {"differ-on-one": ({"smile": 1000, "frown": {"by_seed": {"0": 1000, "1": 300, "2": 1000}}},
                               "smile 1000 / 1000 / 1000, frown 1000 / 300 / 1000 (seeds 0, 1, 2): the k differ "
                               "across expressions on 1 of 3 seeds: partly."),
                 "never": ({"smile": 1000, "frown": 1000},
                           "smile 1000 / 1000 / 1000, frown 1000 / 1000 / 1000 (seeds 0, 1, 2): the k differ "
                           "across expressions on 0 of 3 seeds: does not hold."),
                 "always": ({"smile": {"by_seed": {"0": 20, "1": 40, "2": 20}}, "frown": 1000},
                            "smile 20 / 40 / 20, frown 1000 / 1000 / 1000 (seeds 0, 1, 2): the k differ across "
                            "expressions on 3 of 3 seeds: holds.")}
    for name, (k, words) in cases.items():
        (run / "metrics.json").write_text(json.dumps({"blendshapes": per, "pbs": {"pbs": {"k": k}}, "seeds": [0, 1, 2]}))
        assert _module().main([str(run)]) == 0
        out = capsys.readouterr().out
        assert f"C9, pbs: chosen k {words}" in out, (name, out)
        if name == "differ-on-one":  # the table's k column: one k per seed where they differ
            assert "| pbs | dt-0 | frown | 1000 / 300 / 1000 |" in out and "| pbs | dt-0 | smile | 1000 |" in out


def test_tables_carry_the_seeds_sd(tmp_path, capsys):
    """A seeds run's table cells are mean ± sd (the page quotes them); a one-seed run's stay means."""
    run = tmp_path / "ch5-sd"
    run.mkdir()
    s = lambda m, sd: {"mean": m, "seed_sd": sd}  # noqa: E731
    row = {"pbs": {"l1": s(1e-3, 0.02e-3), "dame": s(1e-2, 0.001e-2), "fmpd": s(1e-2, 0.0)},
           "dt-0": {"l1": s(2e-3, 0.0), "dame": s(2e-2, 0.0), "fmpd": s(1e-2, 0.0)},
           "pbs:pb-x": {"l1": s(1.1e-3, 0.03e-3), "dame": s(1.5e-2, 0.01e-2), "fmpd": s(2e-2, 0.1e-2)},
           "pb-x-two-step": {"l1": s(1.2e-3, 0.01e-3), "dame": s(1.4e-2, 0.02e-2), "fmpd": s(3e-2, 0.2e-2)}}
    (run / "metrics.json").write_text(json.dumps({"blendshapes": {"smile": row}, "pbs": {"pbs": {"k": {"smile": 50}}},
                                                  "seeds": [0, 1, 2]}))
    assert _module().main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "| pbs | dt-0 | smile | 50 | 1.000 ± 0.020 / 2.000 ± 0.000 | +100.0 % | 1.000 ± 0.001 / 2.000 ± 0.000 |" in out
    assert "| expression | metric | pbs | dt-0 | pbs:pb-x | pb-x-two-step |" in out  # the page's overview table
    assert "| smile | L1 ×1e-3 | **1.000 ± 0.020** | 2.000 ± 0.000 | 1.100 ± 0.030 | 1.200 ± 0.010 |" in out
    assert "| smile | DAME ×1e-2 | **1.000 ± 0.001** | 2.000 ± 0.000 | 1.500 ± 0.010 | 1.400 ± 0.020 |" in out
    assert ("| pbs:pb-x | pb-x-two-step | smile | 1.100 ± 0.030 / 1.200 ± 0.010 | 1.500 ± 0.010 / 1.400 ± 0.020 | "
            "2.000 ± 0.100 / 3.000 ± 0.200 | no |") in out
