"""benchmarks/_claims.py: a model's training minutes as the claims scripts read them, from each
source a run may have (train_s, the curves of an older run, fit_s), checked against sums by hand."""
import json

import pytest

from .scripts import load_benchmark


def _net(**extra):
    return {"epochs_run": 3, "max_epochs": 5, "stopped_by": "early_stopping", "plateau": "plateau", **extra}


def test_train_s_summed_over_the_models_networks():
    m = {"training": {"networks": {"dsm/low": _net(train_s=60.0), "dsm/high": _net(train_s=30.0),
                                   "dsm-g04/low": _net(train_s=999.0)}}}
    t = load_benchmark("_claims").training(m, "dsm")
    assert t["minutes"] == pytest.approx(1.5)
    assert t["epochs"] == "3/5, 3/5" and t["verdict"] == "plateau, plateau"


def test_older_run_reads_the_epochs_seconds_from_its_curves(tmp_path):
    # a resumed older run: no train_s, fit_s counts only the last attempt, the curves keep every epoch
    m = {"training": {"networks": {"ae/vae": _net()}}, "timing": {"ae": {"fit_s": 10.0}}}
    curves = tmp_path / "curves" / "ae"
    curves.mkdir(parents=True)
    (curves / "vae.json").write_text(json.dumps({"epochs": [{"seconds": 20.0}, {"seconds": 40.0}, {"epoch": 3}]}))
    assert load_benchmark("_claims").training(m, "ae", tmp_path)["minutes"] == pytest.approx(1.0)


def test_fit_s_when_nothing_else_and_none_when_nothing():
    claims = load_benchmark("_claims")
    m = {"training": {"networks": {"ae": _net()}}, "timing": {"ae": {"fit_s": 90.0}}}
    assert claims.training(m, "ae")["minutes"] == pytest.approx(1.5)
    assert claims.training({"training": {"networks": {"ae": _net()}}}, "ae")["minutes"] is None
    assert claims.training({}, "ae") == {"epochs": "", "ended": "", "verdict": "", "minutes": None}


def test_a_seeds_run_counts_every_seeds_networks():
    # a seeds run's metrics.json keys each seed's networks seed-<s>/<label>[/<network>]; another model's stay out
    m = {"training": {"networks": {"seed-0/ae/vae": _net(train_s=60.0), "seed-1/ae/vae": _net(train_s=30.0),
                                   "seed-10/ae": _net(train_s=30.0), "seed-0/aex": _net(train_s=999.0),
                                   "seed-0/dsm/ae": _net(train_s=999.0)}}}
    t = load_benchmark("_claims").training(m, "ae")
    assert t["minutes"] == pytest.approx(2.0)
    assert t["epochs"] == "3/5, 3/5, 3/5"
