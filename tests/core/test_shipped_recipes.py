"""Every recipe shipped in ``recipes/`` resolves against the installed plugins: each key is a
known parameter of its component, at any depth (a grid's members as the grid task builds them:
its base with each config merged in). A recipe that only fails when a 2-hour study reaches its
last member is found here instead."""
from pathlib import Path

import pytest

from fwk.errors import RecipeError
from fwk.plugins import get_registry
from fwk.recipes import deep_merge, load_recipe, resolve

ROOT = Path(__file__).resolve().parents[2] / "recipes"
RECIPES = sorted(ROOT.rglob("*.yaml"))


def test_recipes_found():
    assert len(RECIPES) > 20 and (ROOT / "thesis" / "ch3" / "plateau.yaml") in RECIPES


@pytest.mark.parametrize("path", RECIPES, ids=lambda p: str(p.relative_to(ROOT)))
def test_recipe_resolves(path):
    registry = get_registry()
    data = load_recipe(path)
    resolve(data, registry)
    if data.get("task") == "grid":
        base = load_recipe(path.parent / data["base"])
        for name, config in data["configs"].items():
            resolve(deep_merge(base, config), registry)


def test_a_wrong_key_deep_in_a_shipped_recipe_is_refused():
    data = load_recipe(ROOT / "thesis" / "ch4" / "plateau.yaml", ["models.dsm.network.conv.radus=2"])
    with pytest.raises(RecipeError, match=r"models\.dsm\.network\.conv\.radus: unknown parameter of vcconv"):
        resolve(data, get_registry())
