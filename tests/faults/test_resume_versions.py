"""A resumed run records the code it resumed with (versions.json "resumed") and says in its log
when that code differs from the code that ran it last: a run's numbers may then come from more
than one version of fwk (issue 13: a study resumed after an edit)."""
import json

import fwk.runs

from .common import fwk_run, recipe, resume


def test_resume_records_its_code_and_logs_a_change(tmp_path, monkeypatch):
    real = fwk.runs.versions
    code = {"git_commit": "a" * 40, "git_dirty": False}
    monkeypatch.setattr(fwk.runs, "versions", lambda registry: {**real(registry), **code})

    rc, run = fwk_run(recipe(tmp_path), tmp_path / "runs")
    assert rc == 0
    started = json.loads((run / "versions.json").read_text())
    assert started["git_commit"] == "a" * 40 and "resumed" not in started

    code.update(git_commit="f" * 40, git_dirty=True)  # the tree was edited and committed since
    assert resume(run) == 0
    v = json.loads((run / "versions.json").read_text())
    assert v["git_commit"] == "a" * 40  # what the run started with stays
    assert [(e["git_commit"], e["git_dirty"]) for e in v["resumed"]] == [("f" * 40, True)]
    assert v["resumed"][0]["at"] and v["resumed"][0]["fwk"] == started["fwk"]
    log = (run / "log.txt").read_text()
    assert log.count("resuming with other code than the run last ran with") == 1
    assert f"git_commit {'a' * 40} -> {'f' * 40}, git_dirty False -> True" in log

    # the same code again: recorded, no new line (compared with the latest resume, not the start)
    assert resume(run) == 0
    v = json.loads((run / "versions.json").read_text())
    assert [e["git_commit"] for e in v["resumed"]] == ["f" * 40] * 2
    assert (run / "log.txt").read_text().count("resuming with other code") == 1


def test_resume_of_a_run_without_versions_json_starts_the_record(tmp_path):
    rc, run = fwk_run(recipe(tmp_path), tmp_path / "runs")
    (run / "versions.json").unlink()
    assert resume(run) == 0
    v = json.loads((run / "versions.json").read_text())
    assert len(v["resumed"]) == 1 and "fwk" in v["resumed"][0]
    assert "resuming with other code" not in (run / "log.txt").read_text()
