"""fwk.engine: seeding, exact resume, finished runs, checkpoints, TensorBoard, two optimisers."""
import numpy as np
import pytest
import torch

from fwk.engine import EpochSampler, TrainConfig, fit, make_optimizer, predict_batches
from fwk.errors import RecipeError
from fwk.runs import make_test_context
from fwk.safeio import load_state
from regression import _data, _module

pytestmark = pytest.mark.usefixtures("one_thread_count")  # the tests compare trainings bit for bit


def _two_opt_module():
    import lightning.pytorch as pl

    class Two(pl.LightningModule):
        """Two networks, one Adam each (as Deep Spectral Meshes: one per band), manual optimisation."""

        def __init__(self):
            super().__init__()
            self.automatic_optimization = False
            self.a = torch.nn.Linear(6, 1)
            self.b = torch.nn.Linear(6, 1)

        def training_step(self, batch, _):
            x, y = batch
            for net, opt, col in zip((self.a, self.b), self.optimizers(), (0, 1)):
                loss = torch.mean(torch.abs(net(x + 0.01 * torch.randn_like(x))[:, 0] - y[:, col]))
                opt.zero_grad()
                self.manual_backward(loss)
                opt.step()
            self.log("train_loss", loss, batch_size=len(x))

        def configure_optimizers(self):
            return [make_optimizer(self.a.parameters(), self.train_config),
                    make_optimizer(self.b.parameters(), self.train_config)]

    torch.manual_seed(0)
    return Two()


def _params(m):
    return {k: v.detach().clone() for k, v in m.state_dict().items()}


def _same(p, q):
    return p.keys() == q.keys() and all(torch.equal(p[k], q[k]) for k in p)


def _ctx(tmp_path, epochs, seed=0, **kw):
    return make_test_context(tmp_path, seed=seed, epochs=epochs, batch_size=8, lr=1e-2, lr_decay=0.9, **kw)


def test_train_config_replace():
    c = TrainConfig()
    assert c.kl_weight == 1e-6 and c.lr_decay == 0.99 and c.batch_size == 16  # thesis 4.5 / 5.2.4
    d = c.replace(epochs=3)
    assert d.epochs == 3 and c.epochs == 10
    with pytest.raises(RecipeError, match="train.epoch.*epochs"):
        c.replace(epoch=3)
    with pytest.raises(RecipeError, match="train.lr_decay"):
        c.replace(lr_decay=1.5)


def test_epoch_sampler_is_a_function_of_seed_and_epoch():
    s = EpochSampler(10, seed=5)
    s.set_epoch(3)
    a = list(s)
    assert sorted(a) == list(range(10))
    t = EpochSampler(10, seed=5)
    t.set_epoch(3)
    assert list(t) == a
    t.set_epoch(4)
    assert list(t) != a
    assert list(EpochSampler(10, seed=5, shuffle=False)) == list(range(10))
    # several processes (DDP): disjoint shards of equal length covering every sample
    shards = [EpochSampler(10, seed=5, num_replicas=3, rank=r) for r in range(3)]
    for sh in shards:
        sh.set_epoch(3)
    lists = [list(sh) for sh in shards]
    assert all(len(x) == len(sh) == 4 for x, sh in zip(lists, shards))
    assert set(sum(lists, [])) == set(range(10))


def test_deterministic_for_a_seed(tmp_path):
    train, val = _data()
    runs = []
    for i, seed in enumerate((1, 1, 2)):
        m = _module()
        torch.manual_seed(100 + i)  # whatever the RNG state then, the seed decides shuffling and noise
        runs.append(_params(fit(m, train, val, _ctx(tmp_path / str(i), 2, seed=seed), "reg")))
    assert _same(runs[0], runs[1])
    assert not _same(runs[0], runs[2])


def test_resume_ends_with_the_same_weights(tmp_path):
    train, val = _data()
    straight = _params(fit(_module(), train, val, _ctx(tmp_path / "a", 4), "reg"))
    ctx = _ctx(tmp_path / "b", 2)
    fit(_module(), train, val, ctx, "reg")
    ctx.resume = True
    m = fit(_module(), train, val, ctx, "reg", ctx.train.replace(epochs=4))
    assert m.steps == 2 * 4  # only epochs 3 and 4 were trained (32 samples, batch 8)
    assert _same(_params(m), straight)


def test_corrupt_last_checkpoint_falls_back_to_the_previous_one(tmp_path):
    train, val = _data()
    straight = _params(fit(_module(), train, val, _ctx(tmp_path / "a", 3), "reg"))
    ctx = _ctx(tmp_path / "b", 2)
    fit(_module(), train, val, ctx, "reg")
    last = ctx.run_dir / "checkpoints" / "reg" / "last.ckpt"
    last.write_bytes(last.read_bytes()[:100])  # killed while writing
    ctx.resume = True
    assert _same(_params(fit(_module(), train, val, ctx, "reg", ctx.train.replace(epochs=3))), straight)


def test_finished_run_is_loaded_not_retrained(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, 2)
    done = _params(fit(_module(), train, val, ctx, "reg"))
    ctx.resume = True
    torch.manual_seed(123)
    m = fit(_module(), train, val, ctx, "reg")
    assert m.steps == 0 and _same(_params(m), done) and not m.training


def test_without_resume_old_checkpoints_are_not_used(tmp_path):
    train, val = _data()
    ctx = _ctx(tmp_path, 2)
    a = _params(fit(_module(), train, val, ctx, "reg"))
    m = fit(_module(), train, val, ctx, "reg")  # ctx.resume is False: train again from scratch
    assert m.steps == 8 and _same(_params(m), a)


def test_checkpoints_and_tensorboard(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    train, val = _data()
    ctx = _ctx(tmp_path, 5, keep_checkpoints=2)
    fit(_module(), train, val, ctx, "reg")
    names = sorted(p.name for p in (ctx.run_dir / "checkpoints" / "reg").iterdir())
    assert names == ["epoch003.ckpt", "epoch004.ckpt", "last.ckpt"]
    ck = load_state(ctx.run_dir / "checkpoints" / "reg" / "last.ckpt")
    assert ck["epoch"] == 4 and "fwk_rng" in ck
    (d,) = {p.parent for p in (ctx.run_dir / "tb" / "reg").rglob("events.*")}
    ea = EventAccumulator(str(d))
    ea.Reload()
    assert len(ea.Scalars("train_loss")) == 5 and len(ea.Scalars("val_loss")) == 5
    assert ea.Scalars("train_loss")[-1].value < ea.Scalars("train_loss")[0].value
    lr = [e.value for e in ea.Scalars("lr-Adam")]  # the learning rate of each epoch
    assert np.allclose(lr, [1e-2 * 0.9**e for e in range(5)], rtol=1e-5)


def test_lightning_stays_quiet(tmp_path, capfd):
    train, val = _data()
    fit(_module(), train, val, _ctx(tmp_path, 1), "reg")
    out, err = capfd.readouterr()
    assert out == "" and err == "", (out, err)


def test_two_optimisers_with_per_epoch_decay_and_resume(tmp_path):
    train, val = _data()
    m = fit(_two_opt_module(), train, None, _ctx(tmp_path / "a", 3), "two")
    opts = m.optimizers()
    assert len(opts) == 2
    for o in opts:  # decayed once per epoch: lr * 0.9^3
        assert o.param_groups[0]["lr"] == pytest.approx(1e-2 * 0.9**3)
    torch.manual_seed(1)
    fresh = _two_opt_module()
    assert not torch.equal(fresh.a.weight, m.a.weight) and not torch.equal(fresh.b.weight, m.b.weight)
    ctx = _ctx(tmp_path / "b", 1)
    fit(_two_opt_module(), train, None, ctx, "two")
    ctx.resume = True
    r = fit(_two_opt_module(), train, None, ctx, "two", ctx.train.replace(epochs=3))
    assert _same(_params(r), _params(m))


def test_dataset_and_plain_tensor_inputs(tmp_path):
    import lightning.pytorch as pl

    class AE(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.lin = torch.nn.Linear(4, 4)

        def training_step(self, batch, _):
            (x,) = batch
            return torch.mean((self.lin(x) - x) ** 2)

        def configure_optimizers(self):
            return make_optimizer(self.parameters(), self.train_config)

    X = np.random.default_rng(0).normal(size=(12, 4)).astype(np.float32)
    torch.manual_seed(0)
    a = _params(fit(AE(), X, None, _ctx(tmp_path / "a", 1), "ae"))
    torch.manual_seed(0)
    b = _params(fit(AE(), torch.utils.data.TensorDataset(torch.as_tensor(X)), None, _ctx(tmp_path / "b", 1), "ae"))
    assert _same(a, b)


def test_predict_batches():
    W = torch.randn(5, 3)
    X = np.random.default_rng(0).normal(size=(23, 5))

    def fn(x):
        assert not torch.is_grad_enabled()
        return x @ W

    Y = predict_batches(fn, X, batch_size=4)
    assert Y.shape == (23, 3) and Y.dtype == np.float32
    assert np.allclose(Y, (torch.as_tensor(X, dtype=torch.float32) @ W).numpy(), atol=1e-6)
    assert predict_batches(fn, X[:0], batch_size=4).shape[0] == 0


class _Rows(torch.nn.Module):
    """y = x W (6 -> 2). ``padded``: W kept as 12 rows, the odd ones never read (an earlier layout of
    the same parameter); otherwise the 6 rows read. Plays ``UpgradesSavedTensors``: ``upgrade``
    takes the padded layout to today's."""

    def __init__(self, padded: bool):
        super().__init__()
        torch.manual_seed(0)
        full = torch.randn(12, 2)
        self.padded = padded
        self.w = torch.nn.Parameter(full if padded else full[::2].clone())

    def forward(self, x):
        return x @ (self.w[::2] if self.padded else self.w)

    def upgrade(self, name, t):
        return t[::2] if name == "w" and t.shape == (12, 2) and not self.padded else t

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        if prefix + "w" in state_dict:
            state_dict[prefix + "w"] = self.upgrade("w", state_dict[prefix + "w"])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)


def _rows_module(padded: bool):
    from fwk.engine import loss_module

    def loss(module, batch, stage):
        x, y = batch
        value = torch.mean(torch.abs(module.net(x) - y))
        module.log(f"{stage}_loss", value, on_epoch=True, on_step=False, batch_size=len(x))
        return value

    return loss_module({"net": _Rows(padded)}, loss)


def test_resume_reads_a_checkpoint_of_an_earlier_parameter_layout(tmp_path):
    """A training checkpointed with a parameter in an earlier layout (and Adam's states of that
    shape) resumes with today's module: the weights by the module's load_state_dict, the optimiser
    states by ``upgrade_optimizer_states``; it ends where a training with today's layout does."""
    from fwk.protocols import UpgradesSavedTensors

    assert isinstance(_Rows(False), UpgradesSavedTensors)
    train, val = _data()
    straight = fit(_rows_module(False), train, val, _ctx(tmp_path / "a", 4), "reg").net.w.detach().clone()
    ctx = _ctx(tmp_path / "b", 2)
    fit(_rows_module(True), train, val, ctx, "reg")
    ctx.resume = True
    resumed = fit(_rows_module(False), train, val, ctx, "reg", ctx.train.replace(epochs=4)).net.w.detach()
    assert resumed.shape == (6, 2) and torch.allclose(resumed, straight, atol=1e-6), (resumed - straight).abs().max()
