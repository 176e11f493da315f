"""The LightningModule that trains Deep Spectral Meshes (thesis 4.4.4): one Adam per band,
Lightning manual optimisation.

Its own module because it imports ``lightning`` at the top: ``import lightning.pytorch`` costs
2-5 s beyond torch (``python -X importtime`` here; the engine measured 2.2 s), which ``fwk list``
(it imports every plugin's package) need not pay; ``fwk_dsm.DSM.fit`` imports this module when
it trains.
"""
from __future__ import annotations

import lightning.pytorch as pl

from fwk.engine import make_optimizer, upgrade_optimizer_states

from . import DSMNet, band_losses


class DSMModule(pl.LightningModule):
    """Trains a :class:`fwk_dsm.DSMNet`: per step, the band losses L_b (eqs. 4.13-4.14), one
    backward of their sum and one step of each band's own Adam (over E_b and D_b only); logs
    ``<stage>_loss`` and per band ``<stage>_loss_<band>``, ``<stage>_l1_<band>``.

    Args:
        net: the bands' encoders and decoders (checkpointed as ``net.*``).
        unscales: per band, the representation's differentiable ``unscale`` (the L1 is taken in
            each representation's own unscaled space).
        kl_weight: phi, the weight of the KL term.
        band_names: the bands' names, for the logged keys.
    """

    def __init__(self, net: DSMNet, unscales, kl_weight: float, band_names):
        super().__init__()
        self.net = net
        self.unscales, self.kl_weight, self.band_names = list(unscales), kl_weight, list(band_names)
        self.automatic_optimization = False

    def _log(self, stage, losses, l1s, n):
        total = sum(losses)
        self.log(f"{stage}_loss", total, prog_bar=True, on_epoch=True, on_step=False, batch_size=n)
        for name, l, l1 in zip(self.band_names, losses, l1s):
            self.log(f"{stage}_loss_{name}", l, on_epoch=True, on_step=False, batch_size=n)
            self.log(f"{stage}_l1_{name}", l1, on_epoch=True, on_step=False, batch_size=n)
        return total

    def training_step(self, batch, _):
        opts = self.optimizers()
        opts = opts if isinstance(opts, (list, tuple)) else [opts]
        for o in opts:
            o.zero_grad()
        losses, l1s = band_losses(self.net, list(batch), self.unscales, self.kl_weight)
        total = self._log("train", losses, l1s, len(batch[0]))
        # parameters are disjoint and other bands' codes are detached in each decoder's
        # input, so one backward of the sum gives every band exactly dL_b / d theta_b
        self.manual_backward(total)
        for o in opts:
            o.step()
        return total.detach()

    def validation_step(self, batch, _):
        losses, l1s = band_losses(self.net, list(batch), self.unscales, self.kl_weight)
        return self._log("val", losses, l1s, len(batch[0]))

    def _bands(self):
        """Each band's parameters, one optimiser each."""
        return [list(self.net.encoders[b].parameters()) + list(self.net.decoders[b].parameters())
                for b in range(self.net.n_bands)]

    def configure_optimizers(self):
        return [make_optimizer(params, self.train_config) for params in self._bands()]

    def on_load_checkpoint(self, checkpoint):
        """A resumed checkpoint's optimiser states in today's layout of their parameters."""
        upgrade_optimizer_states(self, checkpoint, self._bands())
