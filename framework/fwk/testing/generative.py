"""GenerativeModelContract and BandModelContract: the roles ``fwk.protocols.GenerativeModel``
(``fwk sample``, the comparison models of ``edit``) and ``fwk.protocols.BandModel`` (``edit``,
``interpolate``).

Subclass one in a test module and set ``component`` and ``params`` as for
``fwk.testing.model.ModelContract`` (the model is built as a recipe builds it and fitted once per
class on ``tiny_fit_data()``)::

    class TestMyModelSamples(GenerativeModelContract):
        component = MyModel
        params = {"latent": 8}

Checked, generative: the class defines every member of the role and a fitted instance plays it;
``encode`` gives (b, latent_size) and ``decode`` (b, n, 3), finite; a batch decodes as its codes
one at a time; ``sample(n, seed)`` gives (n, n_vertices, 3), the same meshes for the same seed and
others for another seed.

Band models, in addition: ``band_names`` (at least two, distinct); ``latent_slice`` by name and
by index agree and the slices partition Z in band order (an unknown band is a user error);
``split`` gives one band per name, each of the input's shape, and ``assemble(split(P)) == P``;
``decode_bands`` gives one band per name and ``decode`` assembles them; ``band_shares`` of a
displacement sums to 1 over the bands and puts a one-band displacement in its band.
"""
from __future__ import annotations

import numpy as np
import pytest

from fwk.errors import FwkError
from fwk.protocols import BandModel, GenerativeModel, plays

from .model import FittedModel, same


class GenerativeModelContract(FittedModel):
    """Models with a latent space and a prior (``fwk.protocols.GenerativeModel``)."""

    batch_atol: float = 1e-5  # decoding a batch against its codes one at a time (float32 networks)

    @pytest.fixture(scope="class")
    @classmethod
    def fitted(cls, tmp_path_factory):
        """(model, data): one fit per test class (a class-scoped fixture is a classmethod: pytest 10
        refuses one that is an instance method, whose instance no test would share)."""
        return cls()._fit(tmp_path_factory.mktemp("fit"))

    def test_plays_the_generative_role(self, fitted):
        m, _ = fitted
        assert plays(type(m), GenerativeModel), "the class must define every member of GenerativeModel"
        assert isinstance(m, GenerativeModel)
        assert isinstance(m.latent_size, int) and m.latent_size > 0

    def test_encode_and_decode_shapes(self, fitted):
        m, data = fitted
        P = data.stack("val")
        Z = np.asarray(m.encode(P))
        assert Z.shape == (len(P), m.latent_size) and np.all(np.isfinite(Z))
        X = np.asarray(m.decode(Z))
        assert X.shape == P.shape and np.all(np.isfinite(X))

    def test_a_batch_decodes_as_its_codes_one_at_a_time(self, fitted):
        m, data = fitted
        Z = np.asarray(m.encode(data.stack("val")))
        X = np.asarray(m.decode(Z))
        for i in range(len(Z)):
            assert np.allclose(np.asarray(m.decode(Z[i:i + 1]))[0], X[i], atol=self.batch_atol)

    def test_sample_is_deterministic_for_a_seed(self, fitted):
        m, data = fitted
        S = np.asarray(m.sample(3, seed=5))
        assert S.shape == (3, data.template.n_vertices, 3) and np.all(np.isfinite(S))
        assert same(m.sample(3, seed=5), S, self.exact, self.atol)
        assert not np.allclose(m.sample(3, seed=6), S)


class BandModelContract(GenerativeModelContract):
    """Generative models whose latent code is split by frequency band (``fwk.protocols.BandModel``)."""

    def test_plays_the_band_role(self, fitted):
        m, _ = fitted
        assert plays(type(m), BandModel), "the class must define every member of BandModel"
        assert isinstance(m, BandModel)
        names = list(m.band_names)
        assert len(names) >= 2 and len(set(names)) == len(names) and all(isinstance(n, str) for n in names)

    def test_latent_slices_partition_z(self, fitted):
        m, _ = fitted
        start = 0
        for i, name in enumerate(m.band_names):
            sl = m.latent_slice(name)
            assert sl == m.latent_slice(i)
            assert sl.start == start and sl.stop > sl.start and sl.step in (None, 1)
            start = sl.stop
        assert start == m.latent_size
        with pytest.raises(FwkError):
            m.latent_slice("no such band")

    def test_split_and_assemble_round_trip(self, fitted):
        m, data = fitted
        P = data.stack("val")
        bands = m.split(P)
        assert len(bands) == len(m.band_names) and all(np.shape(b) == P.shape for b in bands)
        assert np.allclose(m.assemble(bands), P, atol=1e-8)

    def test_decode_bands_one_per_band_and_decode_assembles_them(self, fitted):
        m, data = fitted
        Z = np.asarray(m.encode(data.stack("val")))
        parts = m.decode_bands(Z)
        assert len(parts) == len(m.band_names)
        assert all(np.shape(p) == (len(Z), data.template.n_vertices, 3) for p in parts)
        assert np.allclose(m.assemble(parts), m.decode(Z), atol=1e-8)

    def test_band_shares(self, fitted):
        m, data = fitted
        P = data.stack("val")
        D = P[1:] - P[:1]
        sh = np.asarray(m.band_shares(D))
        assert sh.shape == (len(D), len(m.band_names))
        assert np.allclose(sh.sum(-1), 1, atol=1e-8) and np.all(sh >= -1e-12)
        a, b = m.split(P[:1]), m.split(P[1:2])
        for j in range(len(m.band_names)):  # the difference of one band of two meshes lies in that band
            assert np.asarray(m.band_shares(a[j] - b[j]))[0, j] == pytest.approx(1, abs=1e-6)
