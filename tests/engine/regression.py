"""The small regression problem and LightningModule the engine's tests train (imported by file
name: pytest puts this folder on sys.path, as the subprocess of test_early_stopping does)."""
from __future__ import annotations

import time

import torch

from fwk.engine import make_optimizer


def _data(n=40, d=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(n, d, generator=g)
    Y = X @ torch.randn(d, 2, generator=g) + 0.1 * torch.randn(n, 2, generator=g)
    return (X[:32], Y[:32]), (X[32:], Y[32:])


def _module(crash_at_step=None, sleep=0.0):
    import lightning.pytorch as pl

    class Reg(pl.LightningModule):
        """Dropout and injected noise draw from the global RNG (resume must restore it exactly);
        ``crash_at_step`` raises in that training step (a run killed in the middle of an epoch),
        ``sleep`` slows every step (a run to be killed from outside)."""

        def __init__(self):
            super().__init__()
            self.net = torch.nn.Sequential(torch.nn.Linear(6, 16), torch.nn.Dropout(0.2), torch.nn.ELU(),
                                           torch.nn.Linear(16, 2))
            self.steps = 0

        def training_step(self, batch, _):
            self.steps += 1
            if crash_at_step is not None and self.steps == crash_at_step:
                raise RuntimeError("killed")
            if sleep:
                time.sleep(sleep)
            x, y = batch
            loss = torch.mean(torch.abs(self.net(x + 0.01 * torch.randn_like(x)) - y))
            self.log("train_loss", loss, on_epoch=True, on_step=False, batch_size=len(x))
            return loss

        def validation_step(self, batch, _):
            x, y = batch
            self.log("val_loss", torch.mean(torch.abs(self.net(x) - y)), batch_size=len(x))

        def configure_optimizers(self):
            return make_optimizer(self.parameters(), self.train_config)

    torch.manual_seed(0)  # the caller seeds the initialisation
    return Reg()
