"""The rig models that ship with fwk: folders ``fwk/shipped/<name>/`` (package data) written by
``fwk pack`` (``fwk.pack``), each a run directory cut down to what ``fwk apply`` reads, with a
``card.json``. ``shipped()`` lists them; ``shipped_or_path`` lets every command that takes a run
directory (``fwk apply RUN``, ``fwk register --template RUN``) take a shipped model's name too.
"""
from __future__ import annotations

from pathlib import Path

#: where the rig models that ship with fwk live (package data)
SHIPPED = Path(__file__).resolve().parents[1] / "shipped"
#: a rig model's card: what it is, what it was trained on, its test metrics
CARD = "card.json"
#: a rig model's own template landmarks, ``{"name": template vertex id, ...}`` in the order to pick
#: them (``fwk view --pick --template MODEL`` then opens your head's window only; ``fwk pack
#: --include`` ships one with a model of your own)
LANDMARKS = "landmarks.json"


def shipped() -> dict[str, Path]:
    """{name: folder} of the rig models that ship with fwk (``fwk/shipped/<name>/card.json``)."""
    if not SHIPPED.is_dir():
        return {}
    return {p.name: p for p in sorted(SHIPPED.iterdir()) if (p / CARD).is_file()}


def shipped_or_path(name) -> Path:
    """``name`` as a path, unless no such path exists and a shipped rig model has that name: then
    that model's folder (a folder in the working directory called like a shipped model wins)."""
    p = Path(name)
    if not p.exists():
        found = shipped().get(str(name))
        if found is not None:
            return found
    return p
