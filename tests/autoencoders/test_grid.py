import json
from pathlib import Path

from fwk.cli import main

REPO = Path(__file__).resolve().parents[2]


def _run_grid(tmp_path, monkeypatch, body: str) -> Path:
    """Run a grid over the smoke base recipe (``body``: the grid's keys after ``base``); its run dir."""
    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    grid = tmp_path / "g.yaml"
    grid.write_text(f"task: grid\nbase: {REPO / 'recipes/smoke/grid_base.yaml'}\n{body}")
    runs = tmp_path / "runs"
    assert main(["--quiet", "run", str(grid), "--runs-dir", str(runs)]) == 0
    (d,) = list(runs.iterdir())
    return d


def test_grid_runs_members_once_and_combines(tmp_path, monkeypatch):
    d = _run_grid(tmp_path, monkeypatch, "configs:\n"
                  "  a: {models: {ae: {conv: spiral++}}}\n"
                  "  b: {models: {ae: {conv: lsa, representation: {name: dr, scaling: norm}}}}\n")
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


def test_grid_sweep_plots_every_metric_against_the_swept_value(tmp_path, monkeypatch):
    d = _run_grid(tmp_path, monkeypatch, "sweep: models.ae.latent\n"
                  "configs:\n  z4: {models: {ae: {conv: spiral++, latent: 4}}}\n"
                  "  z8: {models: {ae: {conv: spiral++, latent: 8}}}\n")
    report = (d / "report.md").read_text()
    for m in ("l1", "l2", "dame", "fmpd"):
        assert (d / "figures" / f"sweep_latent_{m}.png").stat().st_size > 1000
        assert f"{m.upper()} against latent" in report


def test_grid_sweep_names_a_member_without_the_key(tmp_path):
    import pytest

    from fwk.errors import RecipeError
    from fwk.plugins import get_registry

    Grid = get_registry().get("task", "grid")
    g = Grid(base="b.yaml", configs={"a": {}}, sweep="models.dsm.k")
    with pytest.raises(RecipeError, match="grid member a has no key 'models.dsm.k'"):
        g.sweep_values({"a": {"models": {"ae": {"latent": 4}}}})
    with pytest.raises(RecipeError, match="not a number"):
        g.sweep_values({"a": {"models": {"dsm": {"k": "big"}}}})
    assert g.sweep_values({"a": {"models": {"dsm": {"k": 50}}}}) == {"a": 50.0}


def test_grid_train_and_seed_apply_to_every_member(tmp_path, monkeypatch):
    # the base trains 2 epochs with seed 0; the grid's train (here from the command line) and
    # seed win in every member, the member's other train keys are kept
    import yaml

    monkeypatch.setenv("FWK_CACHE", str(tmp_path / "cache"))
    grid = tmp_path / "g.yaml"
    grid.write_text(f"task: grid\nbase: {REPO / 'recipes/smoke/grid_base.yaml'}\nseed: 3\n"
                    "configs:\n  a: {models: {ae: {conv: spiral++}}}\n  b: {train: {epochs: 5}}\n")
    runs = tmp_path / "runs"
    assert main(["--quiet", "run", str(grid), "train.epochs=1", "--runs-dir", str(runs)]) == 0
    (d,) = list(runs.iterdir())
    for member in ("a", "b"):
        r = yaml.safe_load((d / member / "recipe.yaml").read_text())
        assert r["seed"] == 3 and r["train"]["epochs"] == 1 and r["train"]["batch_size"] == 8
        (curve,) = (d / member / "curves").glob("*/*.json")
        assert json.loads(curve.read_text())["epochs_run"] == 1
