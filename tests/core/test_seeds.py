"""Seeds as a recipe feature (issue 31): ``seeds: [0, 1, 2]`` / ``fwk run R --seeds 3`` trains
every model once per seed in one run directory, on one split; a 3-seed run's per-seed metrics
equal three 1-seed runs with those seeds; reports print mean ± sd over seeds; the paired test
behind every "A beats B" verdict against a naive exact Wilcoxon signed-rank test and
hand-computed cases; grids fan seeds out like members (local and Ray)."""
import importlib.util
import itertools
import json
import re

import numpy as np
import pytest
import yaml

from fwk.cli import main
from fwk.evaluation.seeds import (ALPHA, aggregate_summaries, compare, min_pairs, paired_test, sentence,
                                  seeds_results)
from fwk.runs import execute

# a tiny reconstruct recipe: a closed-form model (its numbers cannot depend on the seed) and a
# trained one (they must), a few seconds a seed on one thread
TINY = {"name": "tiny", "task": "reconstruct", "seed": 0,
        "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 20},
        "split": {"ratios": [0.7, 0.1, 0.2]}, "train": {"epochs": 2, "batch_size": 8},
        "models": {"pca": {"name": "pca", "n_components": 4}, "vae": {"name": "mlp-vae", "latent": 4}},
        "metrics": ["l1", "dame"], "renders": 0}


@pytest.fixture(scope="module")
def tmp(tmp_path_factory):
    d = tmp_path_factory.mktemp("seeds")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FWK_THREADS", "1")  # bit-for-bit reruns need one thread count (docs/recipes.md)
        mp.setenv("FWK_CACHE", str(d / "cache"))
        (d / "tiny.yaml").write_text(yaml.safe_dump(TINY))
        yield d


def _only(folder):
    (d,) = [p for p in folder.iterdir() if p.is_dir()]
    return d


def _json(path):
    return json.loads(path.read_text())


@pytest.fixture(scope="module")
def three(tmp):
    """``fwk run tiny.yaml --seeds 3``."""
    assert main(["--quiet", "run", str(tmp / "tiny.yaml"), "--seeds", "3", "--runs-dir", str(tmp / "three")]) == 0
    return _only(tmp / "three")


def test_three_seeds_equal_three_one_seed_runs(tmp, three):
    top = _json(three / "metrics.json")
    assert top["seeds"] == [0, 1, 2] and top["split_seed"] == 0
    split = (three / "split.json").read_text()
    for s in (2, 1, 0):  # the other order than the 3-seed run's: no state carries from one seed to the next
        one = execute(str(tmp / "tiny.yaml"), [f"seeds=[{s}]"], runs_dir=str(tmp / f"one-{s}"), quiet=True)
        a = _json(three / f"seed-{s}" / "metrics.json")
        b = _json(one / f"seed-{s}" / "metrics.json")
        assert a["models"] == b["models"]  # every number of seed s, exactly
        assert (one / "split.json").read_text() == split == (three / f"seed-{s}" / "split.json").read_text()
        assert _json(three / f"seed-{s}" / "scores.json") == _json(one / f"seed-{s}" / "scores.json")
        for label, per in top["models"].items():
            for name, metrics in per.items():
                for m, summ in metrics.items():
                    assert summ["seed_means"][str(s)] == a["models"][label][name][m]["mean"]
                    assert _json(one / "metrics.json")["models"][label][name][m]["mean"] == summ["seed_means"][str(s)]
    # the split is fixed: the closed-form model scores the same on every seed; the member seed
    # moves the trained one
    assert top["models"]["pca"]["test"]["l1"]["seed_sd"] == 0.0
    assert top["models"]["vae"]["test"]["l1"]["seed_sd"] > 0.0
    v = [top["models"]["vae"]["test"]["l1"]["seed_means"][str(s)] for s in range(3)]
    assert top["models"]["vae"]["test"]["l1"]["mean"] == pytest.approx(np.mean(v), rel=1e-12)
    assert top["models"]["vae"]["test"]["l1"]["seed_sd"] == pytest.approx(np.std(v, ddof=1), rel=1e-12)


def test_seed_0_of_seeds_is_the_plain_run_of_seed_0(tmp, three):
    plain = execute(str(tmp / "tiny.yaml"), [], runs_dir=str(tmp / "plain"), quiet=True)
    assert _json(plain / "metrics.json")["models"] == _json(three / "seed-0" / "metrics.json")["models"]


def test_member_recipes_fix_the_split_and_the_cli_records_seeds(three):
    assert yaml.safe_load((three / "recipe.yaml").read_text())["seeds"] == 3
    for s in range(3):
        r = yaml.safe_load((three / f"seed-{s}" / "recipe.yaml").read_text())
        assert r["seed"] == s and r["split"] == {"ratios": [0.7, 0.1, 0.2], "seed": 0} and "seeds" not in r
        assert (three / f"seed-{s}" / "report.md").exists()


def test_cli_seeds_values(tmp, capsys):
    from fwk.cli import _seeds

    assert (_seeds("3"), _seeds("0,4,7"), _seeds("5,")) == ("3", "[0, 4, 7]", "[5]")
    for bad in ("0", "x", "1,,y", ","):
        with pytest.raises(SystemExit):
            main(["run", str(tmp / "tiny.yaml"), "--seeds", bad])
    assert main(["run", "--resume", str(tmp), "--seeds", "2"]) == 2
    assert "--seeds: a resumed run keeps the seeds it started with" in capsys.readouterr().err
    assert main(["run", str(tmp / "tiny.yaml"), "--seeds", "5000", "--runs-dir", str(tmp / "none")]) == 2
    assert "seeds: 5000 seeds, more than 1000" in capsys.readouterr().err


def test_report_prints_mean_sd(three):
    report = (three / "report.md").read_text()
    assert "3 seeds (0, 1, 2): every model trained once per seed on one split (split seed 0)" in report
    assert "### test: mean over meshes (mean ± sd over seeds), evaluation space" in report
    row = next(ln for ln in report.splitlines() if ln.startswith("| vae |"))
    assert re.fullmatch(r"\| vae \| [\d.e+-]+ ± [\d.e+-]+ \| [\d.e+-]+ ± [\d.e+-]+ \|", row), row
    assert "| pca | test |" in report and "± 0 |" in report  # the closed-form model: sd 0
    # `fwk report RUN` rebuilds the same tables from metrics.json
    before = [ln for ln in report.splitlines() if "±" in ln]
    assert main(["--quiet", "report", str(three)]) == 0
    after = (three / "report.md").read_text()
    assert [ln for ln in after.splitlines() if "±" in ln] == before


def test_one_seed_report_says_so(tmp):
    one = _only(tmp / "one-1") if (tmp / "one-1").exists() else \
        execute(str(tmp / "tiny.yaml"), ["seeds=[1]"], runs_dir=str(tmp / "one-1"), quiet=True)
    report = (one / "report.md").read_text()
    assert "1 seed (1):" in report and "(one seed: no sd)" in report and "| vae |" in report
    assert not any("±" in ln for ln in report.splitlines() if ln.startswith("| vae"))


def test_resume_reruns_only_unfinished_seeds(tmp):
    run = execute(str(tmp / "tiny.yaml"), ["seeds=2"], runs_dir=str(tmp / "resume"), quiet=True)
    want = _json(run / "metrics.json")["models"]
    (run / "seed-1" / "metrics.json").unlink()
    (run / "metrics.json").unlink()
    (run / "FAILED").write_text("killed\n")
    execute(None, resume=str(run), quiet=True)
    log = (run / "log.txt").read_text()
    assert "seed 0: finished before, not run again" in log and "[seed 1: 2/2]" in log.split("resuming")[-1]
    assert _json(run / "metrics.json")["models"] == want


def test_seeds_trained_elsewhere_join_a_run_by_resume(tmp, three):
    """docs/recipes.md, Seeds: a one-seed run's seed-<s>/ sub-run copied into a run of all the seeds
    (its recipe.yaml the one fwk wrote there) is finished there; --resume trains only the others and
    combines them: the numbers of the run trained in one go."""
    import shutil

    one = execute(str(tmp / "tiny.yaml"), ["seeds=[1]"], runs_dir=str(tmp / "elsewhere"), quiet=True)
    run = execute(str(tmp / "tiny.yaml"), ["seeds=3"], runs_dir=str(tmp / "joined"), quiet=True)
    for s in (1, 2):  # as if the run had been stopped after seed 0: seed 1 comes from elsewhere, seed 2 trains
        shutil.rmtree(run / f"seed-{s}")
    (run / "metrics.json").unlink()
    (run / "FAILED").write_text("killed\n")
    (run / "seed-1").mkdir()
    assert (one / "seed-1" / "recipe.yaml").read_text() == (three / "seed-1" / "recipe.yaml").read_text()
    shutil.copytree(one / "seed-1", run / "seed-1", dirs_exist_ok=True)
    execute(None, resume=str(run), quiet=True)
    log = (run / "log.txt").read_text().split("resuming")[-1]
    assert "seed 1: finished before, not run again" in log and "[seed 2: 3/3]" in log
    assert _json(run / "metrics.json")["models"] == _json(three / "metrics.json")["models"]


# ------------------------------------------------------------------------- the test

def naive_wilcoxon(a, b) -> float:
    """Two-sided exact Wilcoxon signed-rank p-value by enumerating every sign assignment of the
    ranks (no tied |differences|): 2 min(P(W+ <= w), P(W+ >= w)), capped at 1."""
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d = d[d != 0]
    n = len(d)
    if n == 0:
        return 1.0
    ranks = np.empty(n)
    ranks[np.argsort(np.abs(d))] = np.arange(1, n + 1)
    w = ranks[d > 0].sum()
    dist = np.array([sum(r for r, s in zip(range(1, n + 1), signs) if s)
                     for signs in itertools.product((0, 1), repeat=n)])
    return min(1.0, 2 * min(np.mean(dist <= w), np.mean(dist >= w)))


def test_paired_test_against_a_naive_exact_wilcoxon():
    # hand-computed: all n differences of one sign give W+ = 0, p = 2 / 2^n
    assert paired_test(np.zeros(6), np.ones(6))["p"] == pytest.approx(2 / 64)   # 0.031 < 0.05
    assert paired_test(np.zeros(5), np.ones(5))["p"] == pytest.approx(2 / 32)   # 0.0625: 5 subjects never suffice
    assert min_pairs() == 6 and ALPHA == 0.05
    assert paired_test([1.0, 2.0], [1.0, 2.0])["p"] == 1.0  # no differing pair
    # d = 0.1, 0.2, -0.3, -0.4: W+ = 1 + 2 = 3; of the 16 sign sets of ranks 1..4, five sum to
    # at most 3 ({}, {1}, {2}, {3}, {1, 2}): P(W+ <= 3) = 5/16 -> p = 10/16
    assert paired_test([1.1, 2.2, 3.0, 4.0], [1.0, 2.0, 3.3, 4.4])["p"] == pytest.approx(10 / 16)
    rng = np.random.default_rng(7)
    for n in range(4, 12):
        a, b = rng.normal(size=n), rng.normal(size=n) + 0.3
        assert paired_test(a, b)["p"] == pytest.approx(naive_wilcoxon(a, b), rel=1e-12, abs=1e-15)


def _seeds(offsets, shift, noise=0.0, n=8, flip=()):
    """{seed: (A's scores, B's scores)}: B = A + shift on every subject, A moved by each seed's
    offset; seeds in ``flip`` get B = A + alternating +-shift (no consistent winner)."""
    rng = np.random.default_rng(0)
    out = {}
    for s, off in enumerate(offsets):
        a = 1.0 + off + np.linspace(0, 0.5, n) + noise * rng.normal(size=n)
        sign = np.where(np.arange(n) % 2, -1.0, 1.0) if s in flip else 1.0
        out[s] = (a, a + shift * sign + 1e-3 * np.arange(n))
    return {s: v[0] for s, v in out.items()}, {s: v[1] for s, v in out.items()}


def test_verdicts_hand_computed():
    # A lower by 1 on all 8 subjects of 3 seeds (p = 2/256 each); seeds' means 1, 1.1, 0.9 (sd 0.1)
    # for both: the gap 1 > 0.1 + 0.1 -> A beats B beyond the seeds' spread
    a, b = _seeds([0.0, 0.1, -0.1], 1.0)
    c = compare(a, b)
    assert c["verdict"] == "a" and c["significant"] == 3 and c["apart"]
    assert all(v["p"] == pytest.approx(2 / 256) for v in c["per_seed"].values())
    assert c["sd_a"] == pytest.approx(0.1) and c["mean_b"] - c["mean_a"] == pytest.approx(1 + 3.5e-3)
    assert c["verdict"] == "a" and compare(b, a)["verdict"] == "b"  # symmetric
    # one seed without a consistent winner: not significant there -> no verdict
    a, b = _seeds([0.0, 0.1, -0.1], 1.0, flip=(2,))
    c = compare(a, b)
    assert c["verdict"] is None and c["significant"] == 2 and c["per_seed"]["2"]["p"] > ALPHA
    # significant on every seed, but the seeds move A and B by +-3: the intervals overlap (1 < 3 + 3)
    a, b = _seeds([0.0, 3.0, -3.0], 1.0)
    c = compare(a, b)
    assert c["significant"] == 3 and not c["apart"] and c["verdict"] is None
    # one seed: never a verdict beyond the spread
    c = compare({0: a[0]}, {0: b[0]})
    assert c["one_seed"] and c["verdict"] is None and c["sd_a"] is None
    # equal means: a tie
    assert compare({0: [1.0, 2.0]}, {0: [2.0, 1.0]})["lower"] == "tie"


def test_sentences_state_the_verdict():
    def c(a, b, **kw):
        return {**compare(a, b), "metric": "l1", "a": ["blendshapes", "smile", "pbs"], "b": ["blendshapes", "smile", "dt"],
                "about": "smile", **kw}

    a, b = _seeds([0.0, 0.1, -0.1], 1.0)
    s = sentence(c(a, b))
    assert s.startswith("- smile, ") and "`pbs` beats `dt` beyond the seeds' spread" in s and "3 of 3 seeds" in s
    a2, b2 = _seeds([0.0, 3.0, -3.0], 1.0)
    s = sentence(c(a2, b2))
    assert "`pbs` is lower on average" in s and "not beyond the seeds' spread" in s and "intervals overlap" in s
    s = sentence(c({0: a[0]}, {0: b[0]}))
    assert s.endswith("(one seed).") and "`pbs` beats `dt`" in s
    s = sentence(c({0: a[0][:4], 1: a[1][:4]}, {0: b[0][:4], 1: b[1][:4]}))
    assert "4 test subjects cannot give p < 0.05 (at least 6 needed)" in s


def test_aggregate_summaries_by_hand():
    per = {s: {"mean": m, "median": m, "max": m, "std": 0.5, "n": 4, "units": "input", "mean_input": 10 * m,
               "units_input": "cm"} for s, m in zip((0, 1, 2), (1.0, 2.0, 3.0))}
    out = aggregate_summaries(per)
    assert out["mean"] == 2.0 and out["seed_sd"] == 1.0 and out["seed_means"] == {"0": 1.0, "1": 2.0, "2": 3.0}
    assert out["mean_input"] == 20.0 and out["seed_sd_input"] == 10.0 and out["n_seeds"] == 3 and out["std"] == 0.5


def test_blendshapes_comparisons_over_seeds(tmp):
    """A blendshapes run of two seeds restates its summary's "A beats B" sentences with the test."""
    net = {"name": "vae", "channels": [8], "latent": 4, "sampler": {"name": "quadric", "factors": [4]}}
    recipe = {"name": "bs", "task": "blendshapes", "seeds": [0, 1], "train": {"epochs": 1, "batch_size": 4},
              "dataset": {"name": "synthetic-heads", "n_vertices": 300, "n_subjects": 12,
                          "shapes": ["neutral", "mouth-wide"]},
              "split": {"ratios": [0.6, 0.2, 0.2]}, "metrics": ["l1", "dame"], "renders": 0, "pbs_ends": False,
              "models": {"dt": {"name": "dt"}, "pbs": {"name": "pbs", "network": net, "ks": [0, 40, 10000]}}}
    (tmp / "bs.yaml").write_text(yaml.safe_dump(recipe))
    run = execute(str(tmp / "bs.yaml"), runs_dir=str(tmp / "bs"), quiet=True)
    m = _json(run / "metrics.json")
    assert [(c["a_name"], c["b_name"], c["metric"]) for c in m["seed_comparisons"]] == [
        ("pbs", "dt", "l1"), ("pbs", "dt", "dame")]
    assert m["blendshapes"]["mouth-wide"]["dt"]["l1"]["seed_sd"] == 0.0  # DT cannot depend on the seed
    one = (run / "seed-0" / "report.md").read_text()
    assert "(one seed)." in one and "one seed." in one
    report = (run / "report.md").read_text()
    assert "## Comparisons over seeds (test)" in report and "two-sided Wilcoxon signed-rank" in report
    lines = [ln for ln in report.splitlines() if ln.startswith("- mouth-wide, ")]
    assert len(lines) == 2 and all("±" in ln and "(p = " in ln for ln in lines)
    assert "2 test subjects cannot give p < 0.05" in report  # the tiny split: the test cannot decide
    assert "| mouth-wide | L1 norm ×1e-3 | " in report  # the per-expression table, mean ± sd
    # the comparison recomputed from the seeds' files equals the stored one
    assert seeds_results(run, [0, 1], 0)["seed_comparisons"] == m["seed_comparisons"]


def _grid(tmp, executor="local"):
    g = {"task": "grid", "name": "g", "base": "tiny.yaml", "seeds": 2, "executor": executor, "columns": ["l1"],
         "configs": {"a": {"models": {"pca": {"name": "pca", "n_components": 3}}},
                     "b": {"models": {"pca": {"name": "pca", "n_components": 6}}}}}
    base = {**TINY, "models": {}}
    (tmp / "tiny-pca.yaml").write_text(yaml.safe_dump(base))
    (tmp / f"grid-{executor}.yaml").write_text(yaml.safe_dump({**g, "base": "tiny-pca.yaml"}))
    return tmp / f"grid-{executor}.yaml"


def test_grid_fans_seeds_out_like_members(tmp):
    run = execute(str(_grid(tmp)), runs_dir=str(tmp / "grid"), quiet=True)
    log = (run / "log.txt").read_text()
    for name in ("a", "b"):
        assert all(f"{name}/seed-{s}" in log for s in (0, 1))  # one job per member and seed
        m = _json(run / name / "metrics.json")
        assert m["seeds"] == [0, 1] and m["models"]["pca"]["test"]["l1"]["seed_sd"] == 0.0
    report = (run / "report.md").read_text()
    assert re.search(r"\| a \| [\d.]+ ± 0 \| [\d.]+ ± 0 \|", report), report


needs_ray = pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="Ray is an optional extra")


@pytest.mark.slow
@needs_ray
def test_ray_grid_fans_seeds_out_with_the_local_numbers(tmp):
    local = _only(tmp / "grid") if (tmp / "grid").exists() else execute(str(_grid(tmp)), runs_dir=str(tmp / "grid"),
                                                                         quiet=True)
    ray = execute(str(_grid(tmp, "ray")), runs_dir=str(tmp / "ray"), quiet=True)
    assert "ray: 4 members on" in (ray / "log.txt").read_text()
    for name in ("a", "b"):
        for s in (0, 1):
            assert _json(ray / name / f"seed-{s}" / "metrics.json")["models"] == \
                _json(local / name / f"seed-{s}" / "metrics.json")["models"]
        assert _json(ray / name / "metrics.json")["models"] == _json(local / name / "metrics.json")["models"]
