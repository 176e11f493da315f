"""The report's opening (issue 30): the verdict says which model wins, on which metric and by how
much (with the seeds' spread where there are seeds, "(one seed)" otherwise) in the first lines of
report.md; the legend explains every model label from the model itself (its describe(), else its
class docstring and recipe parameters)."""
from fwk.evaluation.legend import describe, describe_spec, first_line, legend_table, model_legend
from fwk.evaluation.verdict import ordinal, verdict_lines
from fwk.recipes import Spec


def _s(mean, sd=None, units="input", mean_input=None, units_input="cm", n=4, n_seeds=None):
    out = {"mean": mean, "n": n, "units": units}
    if mean_input is not None:
        out.update(mean_input=mean_input, units_input=units_input)
    if sd is not None:
        out.update(seed_sd=sd, n_seeds=n_seeds or 3)
        if mean_input is not None:
            out["seed_sd_input"] = sd * mean_input / mean
    return out


def _results(seeded=False):
    sd = (lambda x: x * 0.05) if seeded else (lambda x: None)
    per = {"smile": {"dt-0": {"l1": _s(2.0, sd(2.0), mean_input=20.0), "dame": _s(0.5, sd(0.5), "rad")},
                     "pbs": {"l1": _s(1.0, sd(1.0), mean_input=10.0), "dame": _s(0.6, sd(0.6), "rad")}},
           "frown": {"dt-0": {"l1": _s(3.0, sd(3.0), mean_input=30.0), "dame": _s(0.4, sd(0.4), "rad")},
                     "pbs": {"l1": _s(1.5, sd(1.5), mean_input=15.0), "dame": _s(0.4, sd(0.4), "rad")}}}
    return {"blendshapes": per, "models": {"pbs": {"test": per["smile"]["pbs"]}, "dt-0": {"test": per["smile"]["dt-0"]}},
            "verdict": {"section": "blendshapes", "noun": "expression", "metrics": ["l1", "dame"],
                        "highlight": ["pbs"], "counted": "subjects"}}


def test_the_verdict_names_the_winner_the_metric_and_the_margin_per_key():
    lines = verdict_lines(_results())
    head, body = lines[0], [ln for ln in lines[1:] if ln]
    assert head.startswith("**Verdict** on the test split (one seed), 4 subjects, lower is better: "
                           "of 4 expression-metric pairs")
    assert "`pbs`'s on 2" in head
    smile = next(ln for ln in body if ln.startswith("- **smile**"))
    # L1 in the dataset's units, 50% below the runner-up; DAME won by dt-0, pbs 2nd by 20%
    assert "L1 norm `pbs` 10 cm, 50% below the runner-up `dt-0`" in smile
    assert "DAME `dt-0` 0.5 rad, 17% below the runner-up `pbs`" in smile
    assert "`pbs`: best on L1 norm, 2nd on DAME (+20%)." in smile
    frown = next(ln for ln in body if ln.startswith("- **frown**"))
    assert "DAME `dt-0` 0.4 rad, tied with `pbs`" in frown or "DAME `pbs` 0.4 rad, tied with `dt-0`" in frown
    assert "spread" not in "\n".join(lines)  # one seed: no spread claimed


def test_over_seeds_the_verdict_gives_mean_and_sd_and_says_whether_the_margin_beats_the_spread():
    res = _results(seeded=True)
    res["blendshapes"]["smile"]["dt-0"]["dame"] = _s(0.5, 0.2, "rad")  # a wide spread on one side
    lines = verdict_lines(res)
    assert "(mean ± sd over 3 seeds)" in lines[0] and "one seed" not in lines[0]
    smile = next(ln for ln in lines if ln.startswith("- **smile**"))
    assert "L1 norm `pbs` 10 ± 0.5 cm, 50% below the runner-up `dt-0`, beyond the seeds' spread" in smile
    assert "DAME `dt-0` 0.5 ± 0.2 rad, 17% below the runner-up `pbs`, within the seeds' spread" in smile


def test_without_a_verdict_spec_the_test_split_of_the_models_is_judged():
    res = _results()
    del res["verdict"], res["blendshapes"]
    lines = verdict_lines(res)
    assert lines[0].startswith("**Verdict** on the test split (one seed), 4 meshes") and "of 2 metrics" in lines[0]
    assert any(ln.startswith("- **test**: L1 norm `pbs`") for ln in lines)
    assert verdict_lines({}) == [] and verdict_lines({"models": {"a": {"test": {"l1": {"mean": "x"}}}}}) == []


def test_small_margins_keep_two_digits_and_ordinals():
    res = {"models": {"a": {"test": {"l1": _s(1.0)}}, "b": {"test": {"l1": _s(1.003)}}}}
    assert "0.3% below the runner-up `b`" in verdict_lines(res)[2]
    assert [ordinal(n) for n in (1, 2, 3, 4, 11, 12, 13, 21, 22, 101)] == \
        ["1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "101st"]


class _Plain:
    """A plain model for the legend.

    More text that is not the first line."""


class _Said:
    """Not this line."""

    def __init__(self, n):
        self.n = n

    def describe(self):
        return f"the model of subject {self.n}"


def test_the_legend_comes_from_the_models_not_from_names():
    spec = Spec("model", "plain", {"k": 3, "network": Spec("model", "vae", {"channels": [8]}),
                                   "anchor": Spec("model", "said", {"n": 0})}, _Plain)
    assert first_line(_Plain) == "A plain model for the legend"
    assert describe(_Said(2)) == "the model of subject 2"  # the Described role wins
    line = describe(_Plain(), spec)
    assert line.startswith("A plain model for the legend (recipe: `plain`, k: 3")
    assert "network: vae (channels: [8])" in line and "anchor: said (n: 0)" in line
    assert describe_spec(Spec("model", "x", {}, _Plain)) == "A plain model for the legend (recipe: `x`)"
    legend = model_legend({"a": spec, "b": Spec("model", "said", {"n": 1}, _Said)}, {"b": _Said(1)})
    assert legend["b"] == "the model of subject 1" and legend["a"].startswith("A plain model")
    table = legend_table({"dt-0": "Deformation Transfer | from subject 0"})
    assert table.splitlines()[0] == "| model | what it is |" and "`dt-0` | Deformation Transfer \\| from" in table


def test_dt_describes_its_source_subjects():
    from fwk.plugins import get_registry
    from fwk.protocols import Described

    dt = get_registry().get("model", "dt")
    assert isinstance(dt(0), Described)
    assert "from training subject 0 as the source" in dt(0).describe()
    assert "from training subjects 0, 1, 2 as the sources" in dt([0, 1, 2]).describe()


def test_only_judged_rows_compete_and_the_others_are_named_with_the_reason():
    """A row scored with help the user does not have (a dr network placed onto the ground truth)
    is left out of the ranking, and the verdict says which rows and why."""
    r = _results()
    per = r["blendshapes"]
    for e in per:  # a better-looking row that used the ground truth's placement
        per[e]["pbs:pb-dr"] = {"l1": _s(0.1, mean_input=1.0), "dame": _s(0.01, units="rad")}
    lines = verdict_lines(r)
    assert "`pbs:pb-dr`'s" in lines[0]  # without `judged` it wins everything
    r["verdict"].update(judged=["dt-0", "pbs"], not_judged_why="`pbs:pb-dr` (placed onto the ground truth)")
    lines = verdict_lines(r)
    assert "pb-dr" not in "\n".join(lines[:-1]) and "`pbs`'s on 2" in lines[0]
    assert lines[-1] == "- not ranked: `pbs:pb-dr` (placed onto the ground truth)"
