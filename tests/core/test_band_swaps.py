"""benchmarks/dsm_band_errors.py and pbs_band_errors.py: the swaps that attribute an assembled
output's error to its bands, checked with the real spectral assembler and band predictions whose
errors are known by construction."""
import numpy as np
import trimesh

from fwk.data import Template
from fwk.plugins import get_registry

from .scripts import load_benchmark

Spectral = get_registry().get("assembler", "spectral")


class _Bands:
    """A stand-in dsm: its band predictions are the truth's bands plus given offsets."""

    n_bands = 2

    def __init__(self, assembler, offsets):
        self.a, self.offsets = assembler, offsets

    def split(self, P):
        return self.a.split(P)

    def assemble(self, bands):
        return self.a.assemble(bands)

    def encode(self, P):
        return P

    def decode_bands(self, P):
        return [b + d for b, d in zip(self.split(P), self.offsets)]


def _setup():
    m = trimesh.creation.icosphere(subdivisions=3)
    V = np.asarray(m.vertices)
    a = Spectral(k=30)
    a.fit(Template(V, np.asarray(m.faces)), V)
    rng = np.random.default_rng(0)
    G = V + 0.05 * rng.normal(size=(4, *V.shape))
    U = a.proj.U
    low_err = U[:, :30] @ rng.normal(size=(30, 3)) * 0.01      # lies in the low band only
    high_err = 0.01 * rng.normal(size=V.shape)
    high_err -= U[:, :30] @ (U[:, :30].T @ (a.proj.m[:, None] * high_err))  # its part above k only
    return a, G, low_err, high_err


def test_each_swap_keeps_exactly_the_other_bands_error():
    a, G, low_err, high_err = _setup()
    rows = dict(load_benchmark("dsm_band_errors").attribute(_Bands(a, [low_err, high_err]), G, {}))
    np.testing.assert_allclose(rows["both bands predicted"], G + low_err + high_err, atol=1e-10)
    np.testing.assert_allclose(rows["low predicted, high true"], G + low_err, atol=1e-10)
    np.testing.assert_allclose(rows["low true, high predicted"], G + high_err, atol=1e-10)


def test_an_other_models_bands_replace_dsms_one_at_a_time():
    a, G, low_err, high_err = _setup()
    R = G + 2 * low_err - high_err                       # another network's output, errors in both bands
    rows = dict(load_benchmark("dsm_band_errors").attribute(_Bands(a, [low_err, high_err]), G, {"vae": R}))
    np.testing.assert_allclose(rows["vae"], R)
    np.testing.assert_allclose(rows["vae's low band + dsm's high"], G + 2 * low_err + high_err, atol=1e-10)
    np.testing.assert_allclose(rows["dsm's low + vae's high band"], G + low_err - high_err, atol=1e-10)


class _Pbs:
    """A stand-in PBS: eq. 5.10 as the spectral assembler's two-band assembly at its one k."""

    def __init__(self, assembler):
        self.a = assembler

    def assemble(self, Ps, Pd, ks):
        return [self.a.assemble([Ps, Pd]) for _ in ks]


def test_pbs_swaps_keep_one_networks_error_in_its_own_band():
    # benchmarks/pbs_band_errors.py's swaps: the truth below k keeps only the differential
    # network's error above k, the truth above k only the spatial network's below k
    a, G, low_err, high_err = _setup()
    Es = low_err + high_err                               # the spatial network errs in both bands
    Ed = 2 * low_err - high_err
    rows = dict(load_benchmark("pbs_band_errors").swaps(_Pbs(a), G + Es, G + Ed, G, 30))
    np.testing.assert_allclose(rows["PBS (k = 30)"], G + low_err - high_err, atol=1e-10)
    np.testing.assert_allclose(rows["truth below k, differential above"], G - high_err, atol=1e-10)
    np.testing.assert_allclose(rows["spatial below k, truth above"], G + low_err, atol=1e-10)
    np.testing.assert_allclose(rows["differential network alone"], G + Ed)
    np.testing.assert_allclose(rows["spatial network alone"], G + Es)
