import numpy as np
import pytest

from fwk.plugins import get_registry
from fwk.recipes import make_spec
from fwk.testing.generative import GenerativeModelContract
from fwk.testing.model import ModelContract, tiny_fit_data
from fwk.testing.representation import RepresentationContract, small_batch

REG = get_registry()
# a small graph autoencoder (the ae/vae reconstruction contract lives in tests/autoencoders)
SMALL_AE = {"channels": [8, 16], "latent": 8, "sampler": {"name": "quadric", "factors": [4, 4]}}


@pytest.mark.parametrize("scaling", ["none", "std", "norm"])
class TestEuclidean(RepresentationContract):
    component = REG.get("representation", "euclidean")

    @pytest.fixture(autouse=True)
    def _params(self, scaling):
        self.params = {"scaling": scaling}


def test_euclidean_scalings_match_definitions():
    P, t = small_batch()
    E = REG.get("representation", "euclidean")
    r = E(scaling="norm", a=1.0)
    r.fit(P, None, t)
    F = r.encode(P).astype(np.float64)
    for c in range(3):  # corrected eqs 3.9-3.10: each channel spans exactly [-1, 1] on train
        assert F[..., c].min() == pytest.approx(-1, abs=1e-6) and F[..., c].max() == pytest.approx(1, abs=1e-6)
    r = E(scaling="std")
    r.fit(P, None, t)
    F = r.encode(P).astype(np.float64)
    assert np.allclose(F.mean(0), 0, atol=1e-5)
    sd = P.std(0)
    assert np.allclose(F.std(0)[sd > 1e-6], 1, atol=1e-4)
    # relative: offsets from a per-sample reference
    r = E(scaling="none", relative=True)
    r.fit(P[1:], P[:-1], t)
    assert np.allclose(r.encode(P[1:], P[:-1]), P[1:] - P[:-1], atol=1e-6)
    assert np.allclose(r.decode(r.encode(P[1:], P[:-1]), P[:-1]), P[1:], atol=1e-6)


class TestPCAContract(ModelContract):
    component = REG.get("model", "pca")
    params = {"n_components": 5}


class TestMLPVAEContract(ModelContract):
    component = REG.get("model", "mlp-vae")
    params = {"latent": 8, "hidden": [64]}


class TestVAEContract(ModelContract):
    component = REG.get("model", "vae")
    params = SMALL_AE


# the generative role (fwk sample, edit's comparison models) of every built-in that plays it
# (dsm's, with the band role, in tests/dsm)

class TestPCAGenerative(GenerativeModelContract):
    component = REG.get("model", "pca")
    params = {"n_components": 5}


class TestMLPVAEGenerative(GenerativeModelContract):
    component = REG.get("model", "mlp-vae")
    params = {"latent": 8, "hidden": [64]}


class TestAEGenerative(GenerativeModelContract):
    component = REG.get("model", "ae")
    params = SMALL_AE


class TestVAEGenerative(GenerativeModelContract):
    component = REG.get("model", "vae")
    params = SMALL_AE


class TestVAEDRGenerative(GenerativeModelContract):
    """dr places its decodes onto the mean (no target when sampling)."""

    component = REG.get("model", "vae")
    params = {**SMALL_AE, "representation": {"name": "dr"}}


def test_pca_matches_numpy_svd():
    data = tiny_fit_data()
    P = data.stack("train")
    m = REG.get("model", "pca")(n_components=4)
    m.fit(data)
    X = P.reshape(len(P), -1)
    mu = X.mean(0)
    U, s, Vt = np.linalg.svd(X - mu, full_matrices=False)
    # the representation hands PCA float32 features: agreement to float32 precision
    assert np.allclose(m.singular_values, s[:4], rtol=1e-6)
    assert np.allclose(np.abs(m.components @ Vt[:4].T), np.eye(4), atol=1e-5)
    Q = data.stack("val").reshape(-1, X.shape[1])
    ref = mu + (Q - mu) @ Vt[:4].T @ Vt[:4]
    assert np.allclose(m.reconstruct(data.stack("val")).reshape(len(Q), -1), ref, atol=1e-6)
    # all components reproduce the training set exactly
    full = REG.get("model", "pca")()  # every component the training shapes carry: min(64, m - 1)
    full.fit(data)
    assert np.allclose(full.reconstruct(P), P, atol=1e-6)


@pytest.mark.parametrize("m,d,gram_max", [(12, 40, 4000), (40, 12, 4000), (30, 50, 5)])
def test_top_singular_matches_numpy(m, d, gram_max, monkeypatch):
    """Gram trick (m < d), covariance (m > d) and the truncated svds path (many samples)."""
    import fwk_pca

    monkeypatch.setattr(fwk_pca, "GRAM_MAX", gram_max)
    rng = np.random.default_rng(1)
    X = rng.normal(size=(m, d)) * np.linspace(3, 0.1, d)
    k = 6
    s, W = fwk_pca.top_singular(X, k)
    _, s0, Vt = np.linalg.svd(X, full_matrices=False)
    assert s.shape == (k,) and W.shape == (k, d)
    assert np.allclose(s, s0[:k], rtol=1e-8)
    assert np.allclose(np.abs(W @ Vt[:k].T), np.eye(k), atol=1e-6)


def test_pca_sample_follows_the_training_variance():
    data = tiny_fit_data(n_subjects=24)
    m = REG.get("model", "pca")(n_components=5)
    m.fit(data)
    z = m.encode(m.sample(4000, seed=0))
    assert np.allclose(z.std(0), m.singular_values / np.sqrt(m.n_train - 1), rtol=0.05)
    assert np.allclose(m.encode(m.decode(z[:3])), z[:3], atol=1e-5)


def test_pca_rejects_bad_settings():
    from fwk.errors import RecipeError

    for bad in (-1, 2.5, True, "4"):
        with pytest.raises(RecipeError, match="n_components"):
            REG.get("model", "pca")(n_components=bad)


def test_pca_with_no_components_is_the_training_mean():
    data = tiny_fit_data()
    P = data.stack("train")
    m = REG.get("model", "pca")(n_components=0)
    m.fit(data)
    Q = data.stack("val")
    mean = P.mean(0)
    np.testing.assert_allclose(m.reconstruct(Q), np.broadcast_to(mean, Q.shape), atol=1e-6)
    assert m.encode(Q).shape == (len(Q), 0)
    np.testing.assert_allclose(m.sample(3), np.broadcast_to(mean, (3, *mean.shape)), atol=1e-6)
    m2 = REG.get("model", "pca")(n_components=0)
    m2.load_state_dict(m.state_dict())
    np.testing.assert_allclose(m2.reconstruct(Q), m.reconstruct(Q))


def test_mlp_vae_training_loss_decreases(tmp_path):
    import json

    from fwk.runs import make_test_context

    data = tiny_fit_data(n_subjects=24)
    ctx = make_test_context(tmp_path, epochs=15, batch_size=8, lr=1e-3)
    m = make_spec("model", {"name": "mlp-vae", "latent": 8, "hidden": [128]}, "mlp-vae", REG).build()
    m.fit(data, ctx)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (d,) = {p.parent for p in (ctx.run_dir / "tb").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    loss = [e.value for e in ea.Scalars("train_l1")]
    assert len(loss) == 15 and loss[-1] < 0.5 * loss[0], loss
