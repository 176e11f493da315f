"""Markdown tables of reports."""
from __future__ import annotations


def markdown_table(rows: list[list], columns: list[str], units=None) -> str:
    """A GitHub markdown table. ``units``: None, a list aligned with ``columns`` or a dict
    column -> unit; a unit is shown in the header as ``name (unit)`` (empty units are skipped)."""
    if units is not None:
        if isinstance(units, dict):
            units = [units.get(c, "") for c in columns]
        if len(units) != len(columns):
            raise ValueError(f"{len(units)} units for {len(columns)} columns")
        columns = [f"{c} ({u})" if u else str(c) for c, u in zip(columns, units)]
    head = "| " + " | ".join(str(c) for c in columns) + " |"
    sep = "| " + " | ".join("---" for _ in columns) + " |"
    body = ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join([head, sep, *body])
