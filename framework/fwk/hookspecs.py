"""Every hook a plugin may implement: one ``fwk_register_<kind>s()`` per kind of component.

Each hook takes no arguments and returns a list of component classes. Every class has a
class attribute ``name`` (the name a recipe uses, unique within its kind) and a docstring
whose first line is the one-line summary ``fwk list`` shows. ``fwk show KIND NAME`` prints
the constructor's parameters, so the constructor signature *is* the recipe schema of the
component.
"""
from __future__ import annotations

import pluggy

PROJECT = "fwk"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

#: The kinds of component, in the order ``fwk list`` shows them.
KINDS = (
    "dataset",
    "representation",
    "sampler",
    "conv",
    "model",
    "metric",
    "assembler",
    "task",
)


@hookspec
def fwk_register_datasets() -> list[type]:
    """Dataset classes: ``load(cache) -> fwk.data.MeshCollection``."""


@hookspec
def fwk_register_representations() -> list[type]:
    """Representation classes (fwk.protocols.Representation): positions <-> per-vertex features."""


@hookspec
def fwk_register_samplers() -> list[type]:
    """Sampler classes (fwk.protocols.Sampler): build a template's down/up hierarchy."""


@hookspec
def fwk_register_convs() -> list[type]:
    """Graph convolution classes (fwk.protocols.Conv): torch modules (b, n, c_in) -> (b, n, c_out)."""


@hookspec
def fwk_register_models() -> list[type]:
    """Model classes (fwk.protocols.Model): learn from a collection, reconstruct or predict meshes."""


@hookspec
def fwk_register_metrics() -> list[type]:
    """Metric classes (fwk.protocols.Metric): per-mesh score and per-vertex map."""


@hookspec
def fwk_register_assemblers() -> list[type]:
    """Assembler classes (fwk.protocols.Assembler): split a mesh into frequency bands and back."""


@hookspec
def fwk_register_tasks() -> list[type]:
    """Task classes (fwk.protocols.Task): what ``fwk run`` does with a recipe."""


HOOKS = {kind: f"fwk_register_{kind}s" for kind in KINDS}
