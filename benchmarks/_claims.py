"""Shared by the claims scripts (``claims_ch3.py``, ``claims_ch4.py``, ``claims_ch5.py``): how a model of a finished
run trained, read from its ``metrics.json`` (the report's Training section), and the rule by which a
comparison and a verdict are made (``RULE``)."""
from __future__ import annotations

import json
import re
from pathlib import Path


def networks(m: dict, label: str) -> dict:
    """{key: record} of model ``label``'s networks in metrics.json's training section: keyed
    ``label`` or ``label/<network>``, in a seeds run each seed's ``seed-<s>/label[/<network>]``."""
    def own(k):
        k = re.sub(r"^seed-\d+/", "", k)
        return k == label or k.startswith(label + "/")

    return {k: v for k, v in m.get("training", {}).get("networks", {}).items() if own(k)}


def training(m: dict, label: str, run: Path | None = None) -> dict:
    """Epochs, what ended them, the plateau rule's verdicts and the training minutes of model
    ``label``'s networks in ``m`` (the metrics.json of ``run``): the networks named ``label`` or
    ``label/<network>`` (a model that trains a network of another kind, e.g. vcconv's AE an
    ``ae/vae``), in a seeds run every seed's (``seed-<s>/label...``: one entry per seed, the
    minutes summed over the seeds).

    Minutes are the sum of the epochs' own seconds, which a resumed run keeps from before its
    kill: the networks' ``train_s``; for a run older than that record, the epochs' seconds in
    ``run/curves/<label>/``; failing both, the model's ``timing.fit_s`` (which counts only the
    last attempt of a resumed run); None when nothing says."""
    nets = networks(m, label)
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


# ------------------------------------------------------------------ comparisons and verdicts (issue 26)
#: The rule every claims script states and applies (docs/methods/claims.md, "How a verdict is computed").
RULE = ("Rule: A is lower than B when A's mean over the split's subjects is below B's. With seeds (metrics.json "
        "seed_sd), a difference within the larger of the two seeds' sd is a tie and counts for neither. One seed "
        "cannot show a tie: a verdict on one seed says '(one seed)' and lists its deciding margins under 10 % "
        "with the verdict they would give as ties. A claim 'holds' when its comparison goes its way on more than "
        "half of the cases, 'partly' on some, 'does not hold' on none.")
#: a one-seed margin below this is listed as not settled (issue 26: re-measure those with 3 seeds)
CLOSE = 0.10


def stat(x) -> tuple[float, float | None]:
    """(mean, seed sd or None) of a metrics.json summary ({"mean", "seed_sd"}), a (mean, sd) pair or a number."""
    if isinstance(x, dict):
        return float(x["mean"]), x.get("seed_sd")
    if isinstance(x, tuple):
        return float(x[0]), x[1]
    return float(x), None


def fmt(x, factor: float = 1.0) -> str:
    """A value for a table, scaled by ``factor`` to 3 decimals, with ' ± sd' when it carries a seeds' sd."""
    m, sd = stat(x)
    return f"{m * factor:.3f}" + ("" if sd is None else f" ± {sd * factor:.3f}")


def margin(a, b) -> float:
    """|a - b| over the smaller of the two means: the higher one's excess over the lower."""
    (ma, _), (mb, _) = stat(a), stat(b)
    lo = min(abs(ma), abs(mb))
    return float("inf") if lo == 0 else abs(ma - mb) / lo


def lower(a, b, close: float | None = None) -> bool | None:
    """True when a is lower than b, False when higher, None for a tie: equal means; a difference
    within the larger seed sd (both with seeds); with ``close``, a margin below it."""
    (ma, sa), (mb, sb) = stat(a), stat(b)
    if ma == mb or (sa is not None and sb is not None and abs(ma - mb) <= max(sa, sb)):
        return None
    if close is not None and margin(a, b) < close:
        return None
    return ma < mb


def verdict(n_yes: int, n: int) -> str:
    """'holds' on more than half of n cases, 'partly' on some, 'does not hold' on none."""
    return "holds" if 2 * n_yes > n else ("does not hold" if n_yes == 0 else "partly")


def yes(b: bool | None) -> str:
    return "tie" if b is None else ("yes" if b else "no")


def pct(m: float) -> str:
    return f"{m * 100:.2g} %"


def seeded(*summaries) -> bool:
    """Whether the values carry a seeds' sd (a run with ``seeds:``)."""
    return any(stat(s)[1] is not None for s in summaries)


def qualify(word: str, close_margins: list[str], word_as_ties: str, seeds: bool) -> str:
    """The verdict with its seed note: '(mean over seeds; ties within their sd)' or '(one seed)' with the
    deciding margins under 10 % and the verdict those would give as ties."""
    if seeds:
        return f"{word} (over seeds; differences within the seeds' sd are ties)"
    if not close_margins:
        return f"{word} (one seed; every deciding margin 10 % or more)"
    return (f"{word} (one seed; deciding margins under 10 %: {', '.join(close_margins)}; "
            f"counting those as ties: {word_as_ties})")


def qualify_cases(word: str, close_margins: list[str], word_as_ties: str, on_seeds: list[str], n: int) -> str:
    """``qualify`` for a verdict over n cases of which ``on_seeds`` carry seeds (a seeds run of some
    cases read after a one-seed run of all): over seeds when all do, else the one-seed wording (its
    close margins from the one-seed cases) naming the cases decided over seeds."""
    words = qualify(word, close_margins, word_as_ties, len(on_seeds) == n)
    if on_seeds and len(on_seeds) < n:
        words = f"{words[:-1]}; over seeds: {', '.join(on_seeds)})"
    return words
