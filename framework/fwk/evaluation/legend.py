"""The legend of a report: what each model label of a run is, in one line.

The core names no component: each model says what it is through the optional role
``fwk.protocols.Described`` (``describe()``: one line with its own parameters, e.g. dt's source
subject), else its class docstring's first line and the recipe parameters it was given. A task
composes the legend from its recipe's model specs and the built models (``model_legend``),
adds rows of its own (a composite model's parts, say) and stores it as ``legend`` in
metrics.json; ``write_report`` shows it as the "Models" table under the verdict.

API::

    describe(obj, spec=None) -> str        # one line: obj.describe(), else docstring + parameters
    describe_spec(spec) -> str             # a recipe spec not built: docstring + parameters
    model_legend(specs, models=None) -> {label: line}
    legend_table(legend) -> markdown table (model | what it is)
"""
from __future__ import annotations

from ..protocols import Described
from ..recipes import Spec
from .tables import markdown_table

#: the longest recipe value a legend line spells out (longer ones are shortened with "...")
MAX_VALUE = 40


def first_line(cls) -> str:
    """The first line of ``cls``'s docstring, without its final full stop; the class name when
    it has none."""
    doc = (cls.__doc__ or "").strip()
    line = doc.splitlines()[0].strip() if doc else ""
    return line.rstrip(".") if line else cls.__name__


def _value(v, depth: int = 0) -> str:
    """A recipe value in a few words: a nested component by its name with its own plain
    parameters where they are short (``anchor: {name: dt, sources: 0}`` reads ``dt (sources: 0)``,
    a representation ``euclidean (scaling: std)``), lists as ``[a, b]``; long values shortened."""
    if isinstance(v, Spec):
        inner = params_note(v, depth + 1) if depth == 0 else ""
        text = f"{v.name} ({inner})" if inner and len(inner) <= MAX_VALUE else v.name  # a long one: its name
    elif isinstance(v, dict):
        text = str(v["name"]) if "name" in v else "{...}"
    elif isinstance(v, (list, tuple)):
        text = "[" + ", ".join(_value(x, depth + 1) for x in v) + "]"
    else:
        text = str(v)
    return text if len(text) <= MAX_VALUE else text[:MAX_VALUE - 3] + "..."


def params_note(spec: Spec, depth: int = 0) -> str:
    """The parameters a recipe gave ``spec``, as ``key: value`` pairs (``sources: 0``); below the
    top level only plain values (a nested component's own components are left out)."""
    items = (spec.params or {}).items()
    if depth:
        items = [(k, v) for k, v in items if not isinstance(v, (Spec, dict))]
    return ", ".join(f"{k}: {_value(v, depth)}" for k, v in items)


def describe_spec(spec: Spec) -> str:
    """A component of a recipe that is not built: its class docstring's first line and the
    parameters the recipe gave it."""
    head = first_line(spec.cls) if spec.cls is not None else spec.name
    note = params_note(spec)
    return f"{head} (recipe: `{spec.name}`, {note})" if note else f"{head} (recipe: `{spec.name}`)"


def describe(obj, spec: Spec | None = None) -> str:
    """One line on ``obj`` (a built component): its own ``describe()`` where it plays
    ``Described``, else its class docstring's first line with the recipe parameters of ``spec``
    (nested components, such as an ``anchor:`` model, described in turn)."""
    if isinstance(obj, Described):
        return str(obj.describe()).strip()
    if spec is not None:
        return describe_spec(spec)
    return f"{first_line(type(obj))}"


def model_legend(specs: dict, models: dict | None = None) -> dict[str, str]:
    """{label: one line} for a recipe's models: the built model's ``describe`` where given
    (``models``: {label: model}), else the spec's class docstring and parameters."""
    models = models or {}
    out = {}
    for label, spec in specs.items():
        if label in models:
            out[label] = describe(models[label], spec if isinstance(spec, Spec) else None)
        elif isinstance(spec, Spec):
            out[label] = describe_spec(spec)
        else:
            out[label] = str(spec)
    return out


def legend_table(legend: dict[str, str]) -> str:
    """The "Models" table of a report: each label and what it is."""
    rows = [[f"`{label}`", text.replace("|", "\\|")] for label, text in legend.items()]
    return markdown_table(rows, ["model", "what it is"])
