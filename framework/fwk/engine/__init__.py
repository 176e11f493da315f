"""The training engine: Lightning glue for every trainable model.

``fit(module, train, val, ctx, name)`` trains a LightningModule with what every fwk run needs:

* one seed (the recipe's) drives initialisation, shuffling and sampling; the shuffle of epoch
  e is a function of (seed, e) and the RNG states are stored in every checkpoint, so a run
  killed after any epoch and resumed ends with the same weights as an uninterrupted run;
* Adam with per-epoch exponential learning-rate decay (``make_optimizer``);
* validation and a checkpoint every epoch (``checkpoints/<name>/last.ckpt`` plus the last few);
* TensorBoard scalars under ``tb/<name>/``; a progress bar on a terminal unless quiet;
* CUDA when available (``accelerator: auto``); several devices and DDP are settings
  (``devices``, ``strategy``), not a rewrite;
* modules with several optimisers (Deep Spectral Meshes: one Adam per band) use Lightning's
  manual optimisation and ``make_optimizer`` per parameter group.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import random
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch


@dataclass
class TrainConfig:
    """Training settings from the recipe's ``train:`` section (thesis 3.4 defaults)."""

    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    lr_decay: float = 0.99
    kl_weight: float = 1e-6
    accelerator: str = "auto"
    devices: Any = 1
    strategy: str = "auto"
    precision: str = "32-true"
    keep_checkpoints: int = 3
    num_workers: int = 0
    log_every_n_steps: int = 10
    weight_decay: float = 0.0

    def replace(self, **overrides) -> "TrainConfig":
        bad = [k for k in overrides if k not in {f.name for f in dataclasses.fields(self)}]
        if bad:
            from ..errors import RecipeError
            from ..registry import did_you_mean

            raise RecipeError(f"train.{bad[0]}: unknown training setting{did_you_mean(bad[0], [f.name for f in dataclasses.fields(self)])}")
        return dataclasses.replace(self, **overrides)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def make_optimizer(params, config: TrainConfig):
    """Adam(lr, betas 0.9/0.999) with ExponentialLR(gamma = lr_decay) stepped once per epoch."""
    opt = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.999), weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=config.lr_decay)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}


class EpochSampler(torch.utils.data.Sampler):
    """A shuffle that depends only on (seed, epoch): identical after a resume."""

    def __init__(self, n: int, seed: int, shuffle: bool = True):
        self.n, self.seed, self.shuffle, self.epoch = n, seed, shuffle, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self):
        if not self.shuffle:
            return iter(range(self.n))
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        return iter(torch.randperm(self.n, generator=g).tolist())

    def __len__(self):
        return self.n


def _as_dataset(data):
    if data is None:
        return None
    if isinstance(data, torch.utils.data.Dataset):
        return data
    if isinstance(data, (tuple, list)):
        return torch.utils.data.TensorDataset(*[torch.as_tensor(np.asarray(d) if not torch.is_tensor(d) else d) for d in data])
    t = data if torch.is_tensor(data) else torch.as_tensor(np.asarray(data))
    return torch.utils.data.TensorDataset(t)


def make_loader(data, batch_size: int, seed: int, shuffle: bool, num_workers: int = 0):
    ds = _as_dataset(data)
    if ds is None or len(ds) == 0:
        return None
    return torch.utils.data.DataLoader(ds, batch_size=batch_size, sampler=EpochSampler(len(ds), seed, shuffle),
                                       num_workers=num_workers, drop_last=False)


def _rng_callback():
    import lightning.pytorch as pl

    class RNGState(pl.Callback):
        """Store and restore the RNG states with every checkpoint (exact resume)."""

        def on_save_checkpoint(self, trainer, module, checkpoint):
            checkpoint["fwk_rng"] = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(),
                                     "python": random.getstate()}

        def on_load_checkpoint(self, trainer, module, checkpoint):
            st = checkpoint.get("fwk_rng")
            if st:
                torch.set_rng_state(st["torch"])
                np.random.set_state(st["numpy"])
                random.setstate(st["python"])

    return RNGState()


def _quiet_lightning():
    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "pytorch_lightning"):
        logging.getLogger(name).setLevel(logging.ERROR)
    for pat in (".*does not have many workers.*", ".*num_workers.*", ".*LeafSpec.*", ".*is deprecated.*",
                ".*TensorBoard.*", ".*smaller than the logging interval.*", ".*Checkpoint directory.*exists.*",
                ".*predict_dataloader.*", ".*sync_dist.*", ".*GPU available but not used.*", ".*_pytree.*",
                ".*Precision.*", ".*treespec.*", ".*litlogger.*"):
        warnings.filterwarnings("ignore", message=pat)


def fit(module, train, val, ctx, name: str, config: TrainConfig | None = None):
    """Train ``module`` (a LightningModule) on ``train`` (tensors or a Dataset), validating on
    ``val`` every epoch; checkpoints under ``ctx.path('checkpoints', name)``. Returns the module.

    The module reads its settings from ``module.train_config`` (set here) in
    ``configure_optimizers`` (use ``make_optimizer``). A finished training (final checkpoint at
    the last epoch) is loaded, not repeated.
    """
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import TensorBoardLogger

    _quiet_lightning()
    config = config or ctx.train
    module.train_config = config
    seed_everything(ctx.seed)
    ckdir = ctx.path("checkpoints", name, "x").parent
    tbdir = ctx.path("tb", name, "x").parent
    train_loader = make_loader(train, config.batch_size, ctx.seed, True, config.num_workers)
    if train_loader is None:
        from ..errors import DataError

        raise DataError(f"{name}: no training samples")
    val_loader = make_loader(val, config.batch_size, ctx.seed, False, config.num_workers)
    accelerator = config.accelerator
    if accelerator == "auto" and getattr(ctx, "device", "cpu") == "cpu":
        accelerator = "cpu"
    checkpoint = ModelCheckpoint(dirpath=ckdir, filename="epoch{epoch:03d}", auto_insert_metric_name=False,
                                 save_last=True, save_top_k=max(1, config.keep_checkpoints), monitor="epoch",
                                 mode="max", every_n_epochs=1, save_on_train_epoch_end=val_loader is None)
    show_bar = not ctx.quiet and sys.stderr.isatty()
    trainer = pl.Trainer(
        max_epochs=config.epochs, accelerator=accelerator, devices=config.devices, strategy=config.strategy,
        precision=config.precision, deterministic=True, logger=TensorBoardLogger(str(tbdir), name="", version=""),
        callbacks=[checkpoint, _rng_callback()], enable_progress_bar=show_bar, enable_model_summary=False,
        log_every_n_steps=config.log_every_n_steps, num_sanity_val_steps=0, default_root_dir=str(ckdir),
        use_distributed_sampler=False,
    )
    last = ckdir / "last.ckpt"
    ckpt_path = str(last) if last.exists() else None
    with warnings.catch_warnings():
        _quiet_lightning()
        trainer.fit(module, train_loader, val_loader, ckpt_path=ckpt_path)
    module.eval()
    return module


@torch.no_grad()
def predict_batches(fn, X, batch_size: int = 64, device: str | torch.device = "cpu", dtype=torch.float32) -> np.ndarray:
    """Apply ``fn`` to X (numpy or tensor, first dim = samples) in batches without gradients."""
    outs = []
    X = X if torch.is_tensor(X) else torch.as_tensor(np.asarray(X), dtype=dtype)
    for i in range(0, len(X), batch_size):
        y = fn(X[i:i + batch_size].to(device))
        outs.append(y.detach().cpu().numpy() if torch.is_tensor(y) else np.asarray(y))
    return np.concatenate(outs, axis=0) if outs else np.zeros((0,))


__all__ = ["TrainConfig", "fit", "make_optimizer", "seed_everything", "predict_batches", "make_loader", "EpochSampler"]
