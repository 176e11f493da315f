"""The training engine: Lightning glue for every trainable model.

``fit(module, train, val, ctx, name)`` trains a LightningModule with what every fwk run needs:

* one seed (the recipe's) drives initialisation, shuffling and sampling; the shuffle of epoch
  e is a function of (seed, e) and the RNG states are stored in every checkpoint, so a run
  killed after any epoch and resumed ends with the same weights as an uninterrupted run;
* Adam with per-epoch exponential learning-rate decay (``make_optimizer``);
* validation and a checkpoint every epoch (``checkpoints/<name>/last.ckpt`` plus the newest
  ``keep_checkpoints`` epoch files, older ones removed when training ends, a resumed one too);
* TensorBoard scalars under ``tb/<name>/``; a progress bar on a terminal unless quiet, and plain
  progress lines (epoch, losses, elapsed, time left; at most one every 5 s) elsewhere;
* the per-epoch train and validation losses and why training ended (``max_epochs`` or the
  optional ``early_stopping`` rule on validation loss, and at which epoch) in
  ``curves/<name>.json``, written every epoch; the reports draw them;
* torch's thread count shared among the live fwk processes, re-checked every epoch;
* CUDA when available (``accelerator: auto``); several devices and DDP are settings
  (``devices``, ``strategy``), not a rewrite: ``strategy: ddp`` uses fwk's launcher
  (``distributed``), whose extra ranks rebuild the run from its recipe and join the training;
* modules with several optimisers (Deep Spectral Meshes: one Adam per band) use Lightning's
  manual optimisation and return one ``make_optimizer(...)`` per parameter group from
  ``configure_optimizers``; the engine steps their per-epoch schedulers (unless the module did);
* ``ctx.resume``: continue from ``last.ckpt`` (or the newest readable epoch checkpoint), saying
  from which epoch, or load a finished training without repeating it; without it a name's old
  checkpoints are discarded.
  A name identifies one network within a (scoped) run context.

Modules:

* ``config``: ``TrainConfig``, the recipe's ``train:`` section, and its ``EarlyStopping`` rule
  (imports neither torch nor Lightning);
* ``threads``: how many threads a process computes with (the cores shared by the live fwk
  processes; ``FWK_THREADS`` / ``OMP_NUM_THREADS`` override), no torch at import;
* ``loading``: ``EpochSampler``, ``make_loader``, ``fit_features`` (a representation fitted, its features);
* ``trainer``: ``fit``, ``seed_everything``, ``make_optimizer``, ``predict_batches``;
* ``callbacks``: ``RNGState``, ``ManualSchedulers``, ``ThreadShare``, ``TrainingCurves``,
  ``ProgressLines`` (the Lightning callbacks ``fit`` adds);
* ``distributed``: DDP with fwk's launcher (ranks started as ``python -m fwk.rank``, above ``fwk.runs``);
* ``modules``: ``LossModule``, ``AutoencoderModule`` (the LightningModules of the built-in models);
* ``factories``: ``loss_module``, ``autoencoder_module`` (their call forms for plugins);
* ``variational``: ``kl_divergence``, ``reparameterize``;
* ``losses``: ``l1_mean`` (the L1 loss, fused where ``fwk.native.ops`` applies).

Every name is importable from ``fwk.engine``. Only ``TrainConfig`` and ``EarlyStopping`` are imported with the package;
the others load their module on first access (PEP 562): torch costs ~1 s and Lightning ~2.2 s
more of import time (measured with ``python -X importtime``), and ``fwk.recipes`` / ``fwk.runs``,
which ``fwk list`` and ``fwk --help`` load, import ``TrainConfig`` from here.
"""
from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .config import EarlyStopping, TrainConfig

if TYPE_CHECKING:  # what the lazy names below are, for type checkers and editors
    from .callbacks import ManualSchedulers, ProgressLines, RNGState, ThreadShare, TrainingCurves
    from .factories import autoencoder_module, loss_module
    from .loading import EpochSampler, fit_features, make_loader
    from .modules import AutoencoderModule, LossModule
    from .trainer import fit, make_optimizer, predict_batches, seed_everything, upgrade_optimizer_states
    from .losses import l1_mean
    from .variational import kl_divergence, reparameterize

#: exported name -> the module of this package that defines it (loaded on first access)
_HOME = {
    "EpochSampler": "loading", "make_loader": "loading", "fit_features": "loading",
    "fit": "trainer", "make_optimizer": "trainer", "seed_everything": "trainer", "predict_batches": "trainer",
    "upgrade_optimizer_states": "trainer",
    "RNGState": "callbacks", "ManualSchedulers": "callbacks", "ThreadShare": "callbacks", "TrainingCurves": "callbacks",
    "ProgressLines": "callbacks",
    "LossModule": "modules", "AutoencoderModule": "modules",
    "loss_module": "factories", "autoencoder_module": "factories",
    "kl_divergence": "variational", "reparameterize": "variational",
    "l1_mean": "losses",
}

__all__ = ["TrainConfig", "fit", "fit_features", "make_optimizer", "upgrade_optimizer_states", "seed_everything", "predict_batches", "make_loader", "EpochSampler",
           "kl_divergence", "reparameterize", "l1_mean", "autoencoder_module", "loss_module", "LossModule", "AutoencoderModule",
           "RNGState", "ManualSchedulers", "ThreadShare", "TrainingCurves", "ProgressLines", "EarlyStopping"]


def __getattr__(name: str):
    try:
        home = _HOME[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(importlib.import_module(f"{__name__}.{home}"), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
