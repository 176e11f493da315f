"""The blendshapes report's per-expression rows (PBS against DT on L1, DAME and FMPD, the winner):
an exact tie is no win, k = 0 and k = n say that nothing was assembled; the smoke rig recipe
gives one row per expression."""
import json

import pytest

from fwk.plugins import get_registry

Task = get_registry().get("task", "blendshapes")
SHOWN = {m: type("D", (), {"label": m.upper(), "scale": 1.0})() for m in ("l1", "dame", "fmpd")}


def _results(values, ks, n_vertices=100):
    """results as the task builds them: values {expression: {row: (l1, dame, fmpd)}}."""
    return {"dataset": {"n_vertices": n_vertices},
            "blendshapes": {e: {r: {m: {"mean": v[i]} for i, m in enumerate(("l1", "dame", "fmpd"))}
                                for r, v in rows.items()} for e, rows in values.items()},
            "pbs": {"pbs": {"k": ks, "sweep": {}}}}


def test_verdicts_ties_and_k_notes():
    assert Task._verdict(1.0, 2.0) == "win" and Task._verdict(2.0, 1.0) == "loss"
    assert Task._verdict(1.5, 1.5) == "tie" and Task._verdict(None, 1.0) == "n/a"
    assert Task._verdict(float("nan"), 1.0) == "n/a"
    assert "no assembly" in Task._k_note(0, 100) and "dr network alone" in Task._k_note(0, 100)
    assert "euclidean network alone" in Task._k_note(100, 100) and Task._k_note(40, 100) == "k = 40"


def test_versus_table_and_summary():
    t = Task(models={"x": "dt"})
    res = _results({"smile": {"pbs": (1.0, 2.0, 3.0), "dt": (2.0, 2.0, 1.0)},
                    "frown": {"pbs": (1.0, 1.0, 1.0), "dt": (1.0, 3.0, 0.5)}}, {"smile": 0, "frown": 100})
    heads = ["l1", "dame", "fmpd"]
    table = t._versus(res, ["smile", "frown"], ["dt", "pbs"], SHOWN, ["dt"], heads, 100)
    rows = [ln for ln in table.splitlines() if ln.startswith("| smile") or ln.startswith("| frown")]
    assert len(rows) == 2
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    assert cells[:2] == ["smile", "0 (dr alone)"] and cells[4] == "pbs" and cells[7] == "tie" and cells[10] == "dt"
    cells = [c.strip() for c in rows[1].strip("|").split("|")]
    assert cells[1] == "n (euclidean alone)" and cells[4] == "tie" and cells[7] == "pbs" and cells[10] == "dt"
    assert "L1: `pbs` beats `dt` on 1 of 2 (1 exact ties)" in table
    assert "FMPD: `pbs` beats `dt` on 0 of 2" in table
    summary = t._summary(res, ["smile", "frown"], ["dt", "pbs"], SHOWN, ["dt"], heads, 100)
    assert ("- smile, DAME: `pbs` (k = 0 (the dr network alone: no assembly)) ties with dt (equal values) "
            "(one seed).") in summary
    assert all(ln.endswith(" (one seed).") for ln in summary.splitlines())  # a run of one seed says so
    assert "frown, L1: `pbs` (k = n = 100 (the euclidean network alone: no assembly)) ties with dt" in summary
    assert "smile, FMPD" in summary and "beats dt (50% lower)" in summary
    assert not any("tie" in ln and "beats" in ln for ln in summary.splitlines() if "L1" in ln and "frown" in ln)


def test_one_versus_table_for_every_baseline():
    """Several baselines (dt-0, dt-1) share one table: PBS's value, each baseline's and the winner
    among them per metric; the wins counted against each baseline."""
    t = Task(models={"x": "dt"})
    res = _results({"smile": {"pbs": (1.0, 2.0, 3.0), "dt-0": (2.0, 2.0, 1.0), "dt-1": (3.0, 2.0, 0.5)}},
                   {"smile": 40})
    table = t._versus(res, ["smile"], ["dt-0", "dt-1", "pbs"], SHOWN, ["dt-0", "dt-1"], ["l1", "dame", "fmpd"], 100)
    assert table.count("| expression |") == 1 and "`pbs` against `dt-0`, `dt-1`" in table
    head = [c.strip() for c in table.splitlines()[2].strip("|").split("|")]
    assert head[2:6] == ["L1 ×1 pbs", "L1 ×1 dt-0", "L1 ×1 dt-1", "L1 winner"]
    cells = [c.strip() for c in table.splitlines()[4].strip("|").split("|")]
    assert cells[:2] == ["smile", "40"] and cells[5] == "pbs" and cells[9] == "tie" and cells[13] == "dt-1"
    assert "L1: `pbs` beats `dt-0` on 1 of 1, `dt-1` on 1 of 1" in table
    assert "DAME: `pbs` beats `dt-0` on 0 of 1 (1 exact ties), `dt-1` on 0 of 1 (1 exact ties)" in table
    assert Task._winner({"a": 1.0, "b": 1.0, "c": 2.0}) == "tie: a, b" and Task._winner({"a": None}) == "n/a"


def test_bold_marks_every_equal_best():
    body = Task._bold([["e", "m", "1.5", "1.5", "2"], ["e", "m", "n/a", "3", "2"]])
    assert body[0][2:] == ["**1.5**", "**1.5**", "2"] and body[1][2:] == ["n/a", "3", "**2**"]


@pytest.mark.slow
def test_smoke_rig_report_has_one_row_per_expression(smoke_rig_run):
    report = (smoke_rig_run / "report.md").read_text()
    metrics = json.loads((smoke_rig_run / "metrics.json").read_text())
    exprs = metrics["expressions"]
    assert exprs == ["face-compression", "mouth-wide", "oo-brow-raise-eyes-wide"]
    section = report.split("## Per expression: PBS against DT (test)")[1].split("\n## ")[0]
    for e in exprs:
        row = next(ln for ln in section.splitlines() if ln.startswith(f"| {e} |"))
        cells = [c.strip() for c in row.strip("|").split("|")]
        r = metrics["blendshapes"][e]
        for j, m in enumerate(("l1", "dame", "fmpd")):
            v, w = r["pbs"][m]["mean"], r["dt"][m]["mean"]
            assert cells[4 + 3 * j] == ("pbs" if v < w else "dt" if v > w else "tie")
    assert (smoke_rig_run / "template.obj").exists()
    assert metrics["rendered_expressions"] and set(metrics["rendered_expressions"]) <= set(exprs)
