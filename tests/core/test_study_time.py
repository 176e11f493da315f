"""benchmarks/study_time.py: a study's quiet wall time from its epochs and a short run's epoch
times, checked against sums by hand on written curves (a plain run and a grid)."""
import json

import pytest

from fwk.evaluation.curves import find_curves

from .scripts import load_benchmark


def _curve(path, seconds, finished=True):
    path.parent.mkdir(parents=True, exist_ok=True)
    # named as fwk names a model's network, <label>/<network>; find_curves prefixes a grid member
    path.write_text(json.dumps({"network": f"{path.parent.name}/{path.stem}", "epochs_run": len(seconds),
                                "finished": finished,
                                "epochs": [{"epoch": i + 1, "seconds": s, "threads": 2} for i, s in enumerate(seconds)]}))


def test_epochs_times_quiet_median_plus_the_fixed_part(tmp_path):
    st = load_benchmark("study_time")
    study, timing = tmp_path / "study", tmp_path / "timing"
    _curve(study / "curves/dsm/dsm.json", [40.0] * 100)             # contended: 40 s an epoch
    _curve(study / "curves/vae/vae.json", [30.0] * 66)
    _curve(timing / "curves/dsm/dsm.json", [35.0, 20.0, 22.0])      # first epoch warm-up, median 21
    _curve(timing / "curves/vae/vae.json", [15.0, 12.0, 12.0])
    rows, fixed, total = st.predict(find_curves(study), find_curves(timing), wall=300.0)
    assert fixed == pytest.approx(300.0 - (77.0 + 39.0))
    by = {r["network"]: r for r in rows}
    assert by["dsm/dsm"]["minutes"] == pytest.approx(100 * 21.0 / 60)
    assert by["vae/vae"]["minutes"] == pytest.approx(66 * 12.0 / 60)
    assert by["dsm/dsm"]["study_s"] == 40.0 and by["dsm/dsm"]["threads"] == [2]
    assert total == pytest.approx(fixed + 100 * 21.0 + 66 * 12.0)


def test_grid_members_are_told_apart_and_a_missing_one_refused(tmp_path):
    st = load_benchmark("study_time")
    study, timing = tmp_path / "study", tmp_path / "timing"
    for m, n in (("k10", 100), ("k50", 80)):
        _curve(study / m / "curves/dsm/dsm.json", [30.0] * n)
        _curve(timing / m / "curves/dsm/dsm.json", [30.0, 18.0])
    assert sorted(find_curves(study)) == ["k10/dsm/dsm", "k50/dsm/dsm"]
    _, _, total = st.predict(find_curves(study), find_curves(timing), wall=100.0)
    assert total == pytest.approx(100.0 - 96.0 + 180 * 18.0)
    (timing / "k50" / "curves/dsm/dsm.json").unlink()
    with pytest.raises(SystemExit, match="k50/dsm/dsm"):
        st.predict(find_curves(study), find_curves(timing), wall=100.0)
