"""Shared by the claims scripts (``claims_ch3.py``, ``claims_ch4.py``): how a model of a finished
run trained, read from its ``metrics.json`` (the report's Training section)."""
from __future__ import annotations

import json
from pathlib import Path


def training(m: dict, label: str, run: Path | None = None) -> dict:
    """Epochs, what ended them, the plateau rule's verdicts and the training minutes of model
    ``label``'s networks in ``m`` (the metrics.json of ``run``): the networks named ``label`` or
    ``label/<network>`` (a model that trains a network of another kind, e.g. vcconv's AE an
    ``ae/vae``).

    Minutes are the sum of the epochs' own seconds, which a resumed run keeps from before its
    kill: the networks' ``train_s``; for a run older than that record, the epochs' seconds in
    ``run/curves/<label>/``; failing both, the model's ``timing.fit_s`` (which counts only the
    last attempt of a resumed run); None when nothing says."""
    nets = {k: v for k, v in m.get("training", {}).get("networks", {}).items()
            if k == label or k.startswith(label + "/")}
    if not nets:
        return {"epochs": "", "ended": "", "verdict": "", "minutes": None}
    secs = [v.get("train_s") for v in nets.values()]
    if any(s is None for s in secs) and run is not None:
        curve = sum(e.get("seconds", 0.0) for c in sorted((run / "curves" / label).glob("*.json"))
                    for e in json.loads(c.read_text())["epochs"])
        secs = [curve or None]
    if any(s is None for s in secs):
        fit = m.get("timing", {}).get(label, {}).get("fit_s")
        secs = None if fit is None else [fit]
    return {"epochs": ", ".join(f"{v['epochs_run']}/{v['max_epochs']}" for v in nets.values()),
            "ended": ", ".join(str(v["stopped_by"]) for v in nets.values()),
            "verdict": ", ".join(v["plateau"] for v in nets.values()),
            "minutes": None if secs is None else sum(secs) / 60}
