"""The example package has a tested component of every kind, and `docs/writing-a-plugin.md` walks
through each and names every member of every role a contract suite checks (issue 30)."""
import re
import tomllib
from pathlib import Path

import pytest

from fwk import protocols as P
from fwk.hookspecs import KINDS
from fwk.plugins import get_registry

PACKAGE = Path(__file__).resolve().parents[1]
DOC = (PACKAGE.parents[1] / "docs" / "writing-a-plugin.md").read_text()

#: every role a contract suite checks (the kinds' roles, the model roles, the optional ones)
ROLES = [P.Dataset, P.Representation, P.Sampler, P.Conv, P.FusedPoolingConv, P.Model, P.ReconstructionModel,
         P.GenerativeModel, P.BandModel, P.BlendshapeModel, P.NetworkFactory, P.CompositeModel,
         P.CutSelectingModel, P.TrainingModes, P.Described, P.ChecksData, P.Metric, P.Assembler, P.Task]


def _members(role) -> set[str]:
    own = set(getattr(role, "__annotations__", {}))
    own |= {k for k, v in vars(role).items() if callable(v) and not k.startswith("_")}
    return own


@pytest.mark.parametrize("role", ROLES, ids=lambda r: r.__name__)
def test_every_member_of_every_role_has_a_line_in_the_plugin_guide(role):
    missing = [m for m in sorted(_members(role)) if not re.search(rf"`[^`]*\b{re.escape(m)}\b[^`]*`", DOC)]
    assert not missing, f"docs/writing-a-plugin.md does not name {role.__name__}'s {missing}"


def test_the_optional_attributes_the_suites_read_are_documented():
    for attr in ("rigid_invariant", "scale_invariant", "fuses_pooling", "build_args", "strided", "present",
                 "poly_offsets", "shape_names", "run_dir", "write_json", "write_text", "log"):
        assert f"`{attr}" in DOC, attr


def test_every_kind_has_an_example_registered_through_this_package():
    entries = get_registry().entries  # {kind: {name: Entry}}
    mine = [e for kind in KINDS for e in entries.get(kind, {}).values() if e.distribution == "fwk-example-plugin"]
    kinds = {e.kind for e in mine}
    assert kinds == set(KINDS), f"kinds without an example: {sorted(set(KINDS) - kinds)}"
    for e in mine:
        assert f"`{e.name}`" in DOC, f"{e.kind} {e.name} is not walked through in docs/writing-a-plugin.md"


def test_every_module_has_an_entry_point_a_test_file_and_a_line_in_the_guide():
    points = tomllib.loads((PACKAGE / "pyproject.toml").read_text())["project"]["entry-points"]["fwk"]
    modules = {p.stem for p in (PACKAGE / "fwk_example_plugin").glob("*.py") if p.stem != "__init__"}
    declared = {v.rsplit(".", 1)[-1] for v in points.values() if "." in v}
    assert modules == declared, f"modules {sorted(modules ^ declared)}: one entry point per module"
    for m in modules:
        assert (PACKAGE / "tests" / f"test_{m}.py").exists(), f"no tests/test_{m}.py"
        assert f"{m}.py" in DOC, f"{m}.py is not in docs/writing-a-plugin.md"
