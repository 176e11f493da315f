"""The LightningModules of the built-in trainings: ``LossModule`` (any loss over named
networks) and ``AutoencoderModule`` (the unscaled L1 + KL loss of every (variational)
autoencoder)."""
from __future__ import annotations

import lightning.pytorch as pl

from .losses import l1_mean
from .trainer import make_optimizer, upgrade_optimizer_states
from .variational import kl_divergence, reparameterize


class LossModule(pl.LightningModule):
    """A LightningModule that trains the parameters of ``modules`` (attribute name -> nn.Module;
    the names prefix the checkpoint's keys) that require gradients by ``loss(module, batch,
    stage)``, stage ``"train"`` or ``"val"`` (log with ``module.log``), with Adam and per-epoch
    decay from the run's training settings (``make_optimizer``).

    A subclass may override ``loss(batch, stage)`` instead of passing ``loss``.
    """

    def __init__(self, modules: dict, loss=None):
        super().__init__()
        for name, m in modules.items():
            setattr(self, name, m)
        self.loss_fn = loss

    def loss(self, batch, stage: str):
        """The loss of ``batch`` at ``stage`` (``"train"`` or ``"val"``): ``loss_fn(self, batch, stage)``."""
        return self.loss_fn(self, batch, stage)

    def training_step(self, batch, _):
        """``loss(batch, "train")``."""
        return self.loss(batch, "train")

    def validation_step(self, batch, _):
        """``loss(batch, "val")``."""
        return self.loss(batch, "val")

    def configure_optimizers(self):
        """Adam with per-epoch decay over the parameters that require gradients
        (``make_optimizer``)."""
        return make_optimizer(self._trained(), self.train_config)

    def _trained(self):
        return [p for p in self.parameters() if p.requires_grad]

    def on_load_checkpoint(self, checkpoint):
        """A resumed checkpoint's optimiser states in today's layout of their parameters
        (``upgrade_optimizer_states``)."""
        upgrade_optimizer_states(self, checkpoint, [self._trained()])


def _encode(net, F):
    return net.enc(F)


def _decode(net, z):
    return net.dec(z)


class AutoencoderModule(LossModule):
    """The LightningModule of every (variational) autoencoder trained on one feature tensor F:
    loss = mean |unscale(decode(z)) - unscale(F)| + kl_weight KL (thesis table 3.2, eqs.
    3.19-3.23: L1 in the representation's own unscaled space; the KL term only where ``encode``
    returns a log-variance), z sampled by reparameterisation while training and the mean otherwise.

    ``net`` is the nn.Module holding the parameters (checkpointed as ``net.*``); ``encode(net, F)``
    returns (mu, logvar or None) and ``decode(net, z)`` the features (default: ``net.enc(F)`` and
    ``net.dec(z)``). Logs ``<stage>_loss`` and ``<stage>_l1``; Adam with per-epoch decay from the
    run's training settings.
    """

    def __init__(self, net, unscale, kl_weight: float, encode=None, decode=None):
        super().__init__({"net": net})
        self.unscale = unscale
        self.kl_weight = kl_weight
        self.encode = encode or _encode
        self.decode = decode or _decode

    def loss(self, batch, stage: str):
        """Unscaled L1 (+ kl_weight KL) of the one-tensor ``batch``; logs ``<stage>_loss``, ``<stage>_l1``."""
        (F,) = batch
        mu, logvar = self.encode(self.net, F)
        G = self.decode(self.net, reparameterize(mu, logvar, self.training))
        rec = l1_mean(self.unscale(G), self.unscale(F))  # mean |.| in one pass each way (fwk.native.ops)
        total = rec + self.kl_weight * kl_divergence(mu, logvar) if logvar is not None else rec
        self.log(f"{stage}_loss", total, prog_bar=True, on_epoch=True, on_step=False, batch_size=len(F))
        self.log(f"{stage}_l1", rec, on_epoch=True, on_step=False, batch_size=len(F))
        return total
