import numpy as np
import torch
import pytest

from fwk.plugins import get_registry
from fwk.testing.model import ModelContract, tiny_fit_data

REG = get_registry()
SMALL = {"channels": [8, 16], "latent": 8, "sampler": {"name": "quadric", "factors": [4, 4]}}


def _spec(name, **kw):
    from fwk.recipes import make_spec

    return make_spec("model", {"name": name, **SMALL, **kw}, "model", REG)


class TestAEContract(ModelContract):
    component = None

    def _fit(self, tmp_path, seed=0):
        from fwk.runs import make_test_context

        data = tiny_fit_data()
        m = _spec("ae").build()
        m.fit(data, make_test_context(tmp_path, seed=seed, **self.train))
        return m, data

    def test_fit_reconstruct_and_reload(self, tmp_path):
        m, data = self._fit(tmp_path)
        P = data.stack("val")
        R = m.reconstruct(P)
        assert R.shape == P.shape and np.all(np.isfinite(R))
        m2 = _spec("ae").build()
        m2.load_state_dict(m.state_dict())
        assert np.allclose(m2.reconstruct(P), R, atol=1e-5)


@pytest.mark.parametrize("name,rep", [("ae", "euclidean"), ("vae", "euclidean"), ("ae", "dr")])
def test_training_loss_decreases(tmp_path, name, rep):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from fwk.runs import make_test_context

    data = tiny_fit_data(n_subjects=24)
    ctx = make_test_context(tmp_path, epochs=12, batch_size=8, lr=1e-3)
    m = _spec(name, representation={"name": rep}).build()
    m.fit(data, ctx)
    (d,) = {p.parent for p in (ctx.run_dir / "tb").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    loss = [e.value for e in ea.Scalars("train_l1")]
    # the zero output's loss: the representation's centre (for dr and euclidean std the training
    # mean's features); 12 epochs on 21 tiny heads must beat it and drop the loss by >= 20 %
    F = torch.as_tensor(m.rep.encode(data.stack("train")))
    zero = float(torch.mean(torch.abs(m.rep.unscale(torch.zeros_like(F)) - m.rep.unscale(F))))
    assert len(loss) == 12 and loss[-1] < zero and loss[-1] < 0.8 * loss[0], (loss, zero)
    if rep == "dr":
        assert m.shape[1] == 9


def test_encoder_and_decoder_compose_across_specs():
    import torch

    data = tiny_fit_data()
    t = data.template
    a = _spec("vae").build()
    b = _spec("ae", channels=[4, 8]).build()
    enc = a.build_encoder(t, 3)
    dec = b.build_decoder(t, 9, latent_in=24)
    x = torch.randn(2, t.n_vertices, 3)
    mu, logvar = enc(x)
    assert mu.shape == (2, 8) and logvar.shape == (2, 8)
    y = dec(torch.cat([mu, mu, mu], dim=1))
    assert y.shape == (2, t.n_vertices, 9)


def test_fully_convolutional_vcconv_vae_learns(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from fwk.runs import make_test_context

    data = tiny_fit_data(n_subjects=24)
    ctx = make_test_context(tmp_path, epochs=30, batch_size=8, lr=1e-3)  # a slower starter than the spirals
    m = _spec("vae", conv={"name": "vcconv", "weight_num": 8}, sampler={"name": "simple", "levels": 3},
              channels=[16, 16, 8], fully_convolutional=True, residual_rate=0.5).build()
    m.fit(data, ctx)
    (d,) = {p.parent for p in (ctx.run_dir / "tb").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    loss = [e.value for e in ea.Scalars("train_l1")]
    assert loss[-1] < 0.7 * loss[0], loss
    R = m.reconstruct(data.stack("val"))
    assert R.shape == data.stack("val").shape and np.isfinite(R).all()
