"""benchmarks/claims_ch4.py reads a chapter 4 run (and its k study) and decides C4 per dsm model
and split by the Pareto front of the learned models: checked on fake runs whose answers are known."""
import json

import pytest

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
        # train: lowest DAME of table 4.2's (holds); test: lower DAME than spiralnet++ only (partly)
        "dsm": {"train": (3.0, 1.0), "test": (2.0, 3.0)},
        "dsm-g04": {"train": (5.0, 4.0), "test": (5.0, 5.0)},
        "spiralnet++": {"train": (2.0, 3.0), "test": (3.0, 3.5)},
        "vae-euclidean": {"train": (4.0, 0.5), "test": (4.0, 2.0)},  # table 4.2's Mesh Autoencoder row
        "vae-dr-norm": {"train": (6.0, 1.5), "test": (6.0, 1.0)},
    })
    mod = _module()
    models = mod.load(run)
    front, read = mod.reading(models, "train")
    assert front == ["spiralnet++", "dsm", "vae-euclidean"]  # sorted by L1; vae-dr-norm is dominated by dsm
    c = read["dsm"]
    assert (c["front"], c["dame_rank"], c["l1_rank"], c["n"], c["beats_mean"]) == (True, 2, 2, 5, True)
    assert c["c4_vs"] == ["spiralnet++", "vae-euclidean"] and c["c4_lower"] == 1 and c["verdict"] == "partly"
    assert read["dsm-g04"]["verdict"] == "does not hold"
    # table 4.3 on train: dsm lowest L1 (3.0 against 4.0 and 6.0), not lowest DAME (vae-euclidean 0.5)
    assert c["c7"].startswith("lowest L1 of dsm and the VAEs: yes, lowest DAME: no: partly (one seed;")
    front, read = mod.reading(models, "test")
    assert read["dsm"]["verdict"] == "partly" and read["dsm"]["beats_mean"] is False  # DAME 3.0 above the mean's 2.0
    assert read["dsm"]["c7"].startswith("on the front of dsm and the VAEs: yes: holds")
    assert models["dsm"]["training"]["minutes"] == 5.0
    assert mod.main([str(run)]) == 0
    out = capsys.readouterr().out
    assert "C4, dsm, train: lower DAME than 1 of the 2 of table 4.2's 4 methods in the run (spiralnet++, vae-euclidean; not run: Neural 3DMM, FeaStNet); L1 rank 2 of 3: partly" in out
    assert "| mean-shape | 10000.000 | 200.000 | 400.000 | (baseline) |" in out
    assert "Rule: A is lower than B" in out


# docs/methods/claims.md, "Chapter 4 at the budget's plateau": ch4_plateau-20261201-225739 (L1 x1e-3, DAME x1e-2)
CH4 = {"mean-shape": {"train": (11.373, 1.959), "test": (11.963, 1.978)},
       "dsm": {"train": (1.076, 1.620), "test": (3.716, 1.827)},
       "dsm-g04": {"train": (1.446, 1.756), "test": (3.841, 1.928)},
       "vae-euclidean": {"train": (7.223, 14.53), "test": (7.646, 14.94)},
       "vae-euclidean-std": {"train": (1.556, 4.988), "test": (3.644, 4.894)},
       "vae-dr-norm": {"train": (1.384, 1.445), "test": (4.092, 1.631)},
       "spiralnet++": {"train": (2.286, 6.255), "test": (3.692, 6.126)},
       "neural-3dmm": {"train": (2.093, 6.239), "test": (3.410, 6.133)}}
# the k study, k-plateau-20261202-015750, dsm's test L1 and DAME per k
KSTUDY = {10: (3.892, 1.685), 50: (3.538, 1.644), 200: (3.641, 1.673), 500: (3.715, 1.827), 1000: (3.715, 2.114),
          2000: (3.695, 2.680)}


def test_the_chapter_4_run_gives_the_pages_verdicts(tmp_path, capsys):
    run, krun = tmp_path / "ch4_plateau-20261201-225739", tmp_path / "k"
    _run(run, {k: {s: (v[0] * 1e-3, v[1] * 1e-2) for s, v in r.items()} for k, r in CH4.items()})
    for k, (l1, dame) in KSTUDY.items():
        _run(krun / f"k{k}", {"dsm": {"test": (l1 * 1e-3, dame * 1e-2), "train": (l1 * 1e-3, dame * 1e-2)}})
    assert _module().main([str(run), "--k", str(krun)]) == 0
    out = capsys.readouterr().out
    for split in ("train", "test"):
        assert (f"C4, dsm, {split}: lower DAME than 3 of the 3 of table 4.2's 4 methods in the run (spiralnet++, "
                f"neural-3dmm, vae-euclidean; not run: FeaStNet); "
                ) in out
    assert "L1 rank 1 of 4: holds (one seed; every deciding margin 10 % or more)." in out  # train
    assert "L1 rank 3 of 4: holds (one seed; every deciding margin 10 % or more)." in out  # test: behind both
    assert ("C7, dsm, train: lowest L1 of dsm and the VAEs: yes, lowest DAME: no: partly (one seed; every deciding "
            "margin 10 % or more).") in out
    # test: dsm's L1 is 10.1 % below the DR Norm. VAE's (of the smaller), which keeps it off that VAE's lower DAME
    assert ("C7, dsm, test: on the front of dsm and the VAEs: yes: holds (one seed; every deciding margin 10 % or "
            "more).") in out
    assert "C16, train: Euclidean Std. VAE lower L1 (yes) and DAME (yes) than the raw Euclidean VAE: holds" in out
    assert ("C8, test: L1 falls on 2 of 5 steps of k, DAME rises on 4 of 5: partly (one seed per k; steps under "
            "10 %: L1 50 -> 200 2.9 %, L1 200 -> 500 2 %, L1 500 -> 1000 0 %, L1 1000 -> 2000 0.54 %, DAME 10 -> 50 "
            "2.5 %, DAME 50 -> 200 1.8 %, DAME 200 -> 500 9.2 %; counting those as ties: does not hold).") in out


def test_c7_test_front_counts_ties_and_lists_close_margins(tmp_path):
    """C7 on test: a VAE dominates dsm when it is lower on one metric and not higher on the other; a
    difference within the seeds' sd is a tie (neither), and on one seed the margins under 10 % that
    keep dsm on the front are listed with the verdict they would give as ties."""
    mod = _module()
    one = {"dsm": {"test": (3.6, 1.645)}, "vae-dr-norm": {"test": (3.8, 1.45)},
           "vae-euclidean-std": {"test": (3.5, 4.9)}}
    models = mod.load(_run_ret(tmp_path / "one", one))
    c7 = mod.reading(models, "test")[1]["dsm"]["c7"]
    assert c7 == ("on the front of dsm and the VAEs: yes: holds (one seed; deciding margins under 10 %: L1 against "
                  "vae-dr-norm 5.6 %; counting those as ties: does not hold)")
    s = lambda m, sd: {"mean": m, "seed_sd": sd}  # noqa: E731
    for dsm_l1, word in ((s(3.6, 0.06), "holds"), (s(3.78, 0.06), "does not hold, dominated by vae-dr-norm")):
        models = {"dsm": {"test": {"l1": dsm_l1, "dame": s(1.645, 0.003)}, "training": {}},
                  "vae-dr-norm": {"test": {"l1": s(3.8, 0.05), "dame": s(1.627, 0.004)}, "training": {}}}
        models = {k: {**v, "_sd": {"test": {m: x["seed_sd"] for m, x in v["test"].items()}},
                      "test": {m: x["mean"] for m, x in v["test"].items()}} for k, v in models.items()}
        c7 = mod.reading(models, "test")[1]["dsm"]["c7"]
        assert c7.startswith("on the front of dsm and the VAEs: " + ("yes: holds" if word == "holds" else
                                                                     "no, dominated by vae-dr-norm: does not hold"))
        assert c7.endswith("(over seeds; differences within the seeds' sd are ties)")


def test_c8_over_seeds_counts_steps_within_the_sd_as_ties(tmp_path, capsys):
    """With seeds a step of k whose difference is within the larger sd counts for neither side, the
    ties are counted, and the k table's cells are mean ± sd."""
    krun = tmp_path / "k"
    s = lambda m, sd: {"mean": m, "seed_sd": sd}  # noqa: E731
    # L1: 3.0 -> 2.0 falls, 2.0 -> 1.95 within sd 0.1 (tie), 1.95 -> 1.0 falls: 2 of 3, holds
    # DAME: 1.0 -> 1.5 rises, 1.5 -> 1.52 tie, 1.52 -> 1.4 falls: 1 of 3, not more than half
    for k, (l1, dame) in {10: (3.0, 1.0), 50: (2.0, 1.5), 200: (1.95, 1.52), 500: (1.0, 1.4)}.items():
        d = krun / f"k{k}"
        d.mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps({"models": {"dsm": {"test": {
            "l1": s(l1, 0.1), "dame": s(dame, 0.05), "fmpd": s(1.0, 0.0)}}}, "seeds": [0, 1, 2]}))
    mod = _module()
    rows = mod.k_rows(krun)
    assert mod.c8(rows[:1], "test") == "C8, test: not measured (fewer than two finished k)."
    assert mod.c8(rows, "test") == ("C8, test: L1 falls on 2 of 3 steps of k, DAME rises on 1 of 3; ties: L1 on 1, "
                                    "DAME on 1: partly (over seeds; differences within the seeds' sd are ties).")
    run = tmp_path / "ch4"
    _run(run, {"dsm": {"test": (2.0, 1.0)}})
    assert mod.main([str(run), "--k", str(krun), "--splits", "test"]) == 0
    assert "| 50 | 2000.000 ± 100.000 | 150.000 ± 5.000 | 100.000 ± 0.000 | no |" in capsys.readouterr().out
    # the k study alone (no chapter 4 run): the same table and verdict, no chapter 4 tables
    assert mod.main(["--k", str(krun), "--splits", "test"]) == 0
    out = capsys.readouterr().out
    assert "| 50 | 2000.000 ± 100.000 | 150.000 ± 5.000 | 100.000 ± 0.000 | no |" in out
    assert mod.c8(rows, "test") in out and "C4" not in out and "evaluation space" not in out
    assert "finished k only" not in out  # every member finished
    with pytest.raises(SystemExit) as e:  # nothing to read: argparse's one line, exit 2
        mod.main([])
    assert e.value.code == 2 and "give RUN" in capsys.readouterr().err


def _run_ret(d, models):
    _run(d, models)
    return d


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
    # a verdict over a study still running says which k it leaves out
    assert mod.k_unfinished(krun) == [50]
    assert "(Over the finished k only: 10, 500, 2000; not finished: 50." in out


def test_c7_at_k50_over_seeds_gives_the_pages_verdicts(tmp_path, capsys):
    """docs/methods/claims.md, C7: ch4_k50_dr_seeds-20261204-215409 (dsm at k = 50 and the DR Norm.
    VAE over seeds 0-2), the page's mean ± sd (L1 ×1e-3, DAME ×1e-2): train and test hold."""
    page = {"dsm": {"train": ((1.090, 0.010), (1.4262, 0.0007)), "test": ((3.604, 0.060), (1.6452, 0.0027))},
            "vae-dr-norm": {"train": ((1.381, 0.004), (1.4428, 0.0025)), "test": ((4.038, 0.054), (1.6269, 0.0038))}}
    run = tmp_path / "k50-seeds"
    run.mkdir()
    s = lambda v, f: {"mean": v[0] * f, "seed_sd": v[1] * f}  # noqa: E731
    res = {k: {sp: {"l1": s(l1, 1e-3), "dame": s(d, 1e-2), "fmpd": s(d, 1e-2)} for sp, (l1, d) in r.items()}
           for k, r in page.items()}
    (run / "metrics.json").write_text(json.dumps({"models": res, "seeds": [0, 1, 2]}))
    assert _module().main([str(run)]) == 0
    out = capsys.readouterr().out
    assert ("C7, dsm, train: lowest L1 of dsm and the VAEs: yes, lowest DAME: yes: holds (over seeds; differences "
            "within the seeds' sd are ties).") in out
    assert ("C7, dsm, test: on the front of dsm and the VAEs: yes: holds (over seeds; differences within the "
            "seeds' sd are ties).") in out


def test_c17_from_the_pages_edit_run(tmp_path, capsys):
    """docs/methods/claims.md, C17: edit-20261202-033014's cross-responses as the page prints them
    (gamma 1: high <- low 0.754, low <- high 0.493; gamma 0.4: 0.418, 0.324): lower gamma, more
    control holds (margins 80 % and 52 %); "barely influence each other" partly (largest rho 0.418,
    below 0.5, above 0.1). And the readings' edges: every rho at most 0.1 holds, one at 0.5 or more
    does not; a pair with a higher rho at the lower gamma counts against."""
    mod = _module()

    def edit_run(d, r1, r04):
        d.mkdir()
        dsm = {"dsm": {"gamma": 1.0, "cross_response": r1}, "dsm-g04": {"gamma": 0.4, "cross_response": r04}}
        (d / "metrics.json").write_text(json.dumps({"disentanglement": {"dsm": dsm, "compare": {}}}))
        return d

    page = edit_run(tmp_path / "edit", {"high<-low": 0.754, "low<-high": 0.493}, {"high<-low": 0.418, "low<-high": 0.324})
    run = tmp_path / "ch4"
    _run(run, {"dsm": {"test": (2.0, 1.0)}})
    assert mod.main([str(run), "--edit", str(page), "--splits", "test"]) == 0
    out = capsys.readouterr().out
    assert ("C17, lower gamma more control: dsm-g04 (gamma 0.4) against dsm (gamma 1): rho high<-low 0.418 against "
            "0.754, rho low<-high 0.324 against 0.493; lower for 2 of 2 pairs: holds (one seed; every deciding margin "
            "10 % or more).") in out
    assert ("C17, bands barely influence each other at gamma 0.4 (dsm-g04): rho high<-low 0.418, low<-high 0.324; "
            "largest 0.418 against 0.1 (holds) and 0.5 (partly): partly (one seed).") in out
    lines = mod.c17(edit_run(tmp_path / "e2", {"a<-b": 0.3, "b<-a": 0.2}, {"a<-b": 0.05, "b<-a": 0.25}))
    assert lines[0].endswith("lower for 1 of 2 pairs: partly (one seed; every deciding margin 10 % or more).")
    assert lines[1].endswith("largest 0.250 against 0.1 (holds) and 0.5 (partly): partly (one seed).")
    assert mod.c17(edit_run(tmp_path / "e3", {"a<-b": 0.3}, {"a<-b": 0.08}))[1].endswith(": holds (one seed).")
    assert mod.c17(edit_run(tmp_path / "e4", {"a<-b": 0.9}, {"a<-b": 0.5}))[1].endswith(": does not hold (one seed).")


# docs/methods/claims.md, C8 over seeds: dsm's mean ± sd per k over seeds 0-2 (L1 ×1e-3, DAME ×1e-2),
# k-plateau-seeds-20261205-073353's finished members and k = 50 from ch4_k50_dr_seeds-20261204-215409
# (the same member recipe)
KSEEDS = {10: {"train": ((1.266, 0.013), (1.454, 0.003)), "test": ((3.886, 0.032), (1.684, 0.003))},
          50: {"train": ((1.090, 0.010), (1.4262, 0.0007)), "test": ((3.604, 0.060), (1.6452, 0.0027))},
          200: {"train": ((1.055, 0.007), (1.456, 0.001)), "test": ((3.658, 0.015), (1.673, 0.003))},
          500: {"train": ((1.073, 0.006), (1.620, 0.001)), "test": ((3.686, 0.026), (1.820, 0.007))},
          1000: {"train": ((1.107, 0.008), (1.937, 0.004)), "test": ((3.694, 0.019), (2.091, 0.019))},
          2000: {"train": ((1.154, 0.005), (2.567, 0.004)), "test": ((3.704, 0.015), (2.647, 0.030))}}
KSEEDS_C8 = {"train": "C8, train: L1 falls on 2 of 5 steps of k, DAME rises on 4 of 5; ties: L1 on 0, DAME on 0: "
                      "partly (over seeds; differences within the seeds' sd are ties).",
             "test": "C8, test: L1 falls on 1 of 5 steps of k, DAME rises on 4 of 5; ties: L1 on 3, DAME on 0: "
                     "partly (over seeds; differences within the seeds' sd are ties)."}


def test_c8_over_seeds_gives_the_pages_verdicts(tmp_path, capsys):
    """The page's C8 words over seeds come from its k table's mean ± sd."""
    krun = tmp_path / "k-plateau-seeds"
    s = lambda v, f: {"mean": v[0] * f, "seed_sd": v[1] * f}  # noqa: E731
    for k, r in KSEEDS.items():
        d = krun / f"k{k}"
        d.mkdir(parents=True)
        res = {sp: {"l1": s(l1, 1e-3), "dame": s(dame, 1e-2)} for sp, (l1, dame) in r.items()}
        (d / "metrics.json").write_text(json.dumps({"models": {"dsm": res}, "seeds": [0, 1, 2]}))
    assert _module().main(["--k", str(krun)]) == 0
    out = capsys.readouterr().out
    for line in KSEEDS_C8.values():
        assert line in out
