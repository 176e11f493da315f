import json
from pathlib import Path

from fwk.cli import main

REPO = Path(__file__).resolve().parents[2]


def test_grid_runs_members_once_and_combines(tmp_path, monkeypatch):
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    grid = tmp_path / "g.yaml"
    grid.write_text(f"task: grid\nbase: {REPO / 'recipes/smoke/grid_base.yaml'}\nconfigs:\n"
                    "  a: {models: {ae: {conv: spiral++}}}\n"
                    "  b: {models: {ae: {conv: lsa, representation: {name: dr, scaling: norm}}}}\n")
    runs = tmp_path / "runs"
    assert main(["--quiet", "run", str(grid), "--runs-dir", str(runs)]) == 0
    (d,) = list(runs.iterdir())
    m = json.loads((d / "metrics.json").read_text())
    assert set(m["models"]) == {"a", "b"}
    for k in ("l1", "l2", "dame", "fmpd"):
        assert m["models"]["b"]["test"][k]["mean"] >= 0
    report = (d / "report.md").read_text()
    assert "| a |" in report and "| b |" in report and "scatter" in report
    # resumable: a finished member is not run again
    stamp = (d / "a" / "metrics.json").stat().st_mtime_ns
    (d / "b" / "metrics.json").unlink()
    assert main(["--quiet", "run", "--resume", str(d)]) == 0
    assert (d / "a" / "metrics.json").stat().st_mtime_ns == stamp
    assert (d / "b" / "metrics.json").exists()


def test_smoke_grid_recipe_validates():
    from fwk.plugins import get_registry
    from fwk.recipes import load_recipe, resolve

    r = resolve(load_recipe(REPO / "recipes/smoke/grid.yaml"), get_registry())
    assert len(r.task.params["configs"]) == 20
