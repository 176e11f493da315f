"""synthetic-heads' ``gain_sd``: how strongly each subject performs an expression (log-normal,
drawn independently of the identity). It changes the expressions only, never the neutrals or the
other draws; 0 makes every expression a function of the identity alone."""
import numpy as np
import pytest

from fwk.errors import RecipeError
from fwk.plugins import get_registry

SH = get_registry().get("dataset", "synthetic-heads")
SMALL = {"n_subjects": 5, "n_vertices": 600}


class _UnitGains(SH):
    """The reference: the default draws with every gain replaced by 1."""

    def _draw(self):
        p, extra = SH(**SMALL)._draw()
        extra["gain"] = {e: np.ones_like(g) for e, g in extra["gain"].items()}
        return p, extra


def test_gain_sd_changes_the_expressions_only():
    base = SH(**SMALL).load().positions
    zero = SH(**SMALL, gain_sd=0).load().positions
    assert np.array_equal(base[:, 0], zero[:, 0]), "neutrals do not depend on gain_sd"
    assert np.array_equal(np.asarray(SH(**SMALL, gain_sd=0.25).load().positions), np.asarray(base)), "0.25 is the default"
    for j in range(1, base.shape[1]):
        assert not np.allclose(base[:, j], zero[:, j]), "the default gains move every expression"
    ref = _UnitGains(**SMALL, gain_sd=0).load().positions
    assert np.array_equal(np.asarray(zero), np.asarray(ref)), "gain_sd 0: every gain is exactly 1"


def test_gain_sd_scales_the_log_gains():
    a, b = SH(**SMALL, gain_sd=0.25)._draw()[1]["gain"], SH(**SMALL, gain_sd=0.5)._draw()[1]["gain"]
    for e in a:
        assert np.allclose(np.log(b[e]), 2 * np.log(a[e])), "the same normal draws, scaled by gain_sd"


@pytest.mark.parametrize("bad", [-0.1, "wide", True])
def test_gain_sd_must_be_a_number_at_least_zero(bad):
    with pytest.raises(RecipeError, match="gain_sd"):
        SH(**SMALL, gain_sd=bad)
