"""The training engine: Lightning glue for every trainable model.

``fit(module, train, val, ctx, name)`` trains a LightningModule with what every fwk run needs:

* one seed (the recipe's) drives initialisation, shuffling and sampling; the shuffle of epoch
  e is a function of (seed, e) and the RNG states are stored in every checkpoint, so a run
  killed after any epoch and resumed ends with the same weights as an uninterrupted run;
* Adam with per-epoch exponential learning-rate decay (``make_optimizer``);
* validation and a checkpoint every epoch (``checkpoints/<name>/last.ckpt`` plus the newest ``keep_checkpoints`` epoch files);
* TensorBoard scalars under ``tb/<name>/``; a progress bar on a terminal unless quiet;
* CUDA when available (``accelerator: auto``); several devices and DDP are settings
  (``devices``, ``strategy``), not a rewrite;
* modules with several optimisers (Deep Spectral Meshes: one Adam per band) use Lightning's
  manual optimisation and return one ``make_optimizer(...)`` per parameter group from
  ``configure_optimizers``; the engine steps their per-epoch schedulers (unless the module did);
* ``ctx.resume``: continue from ``last.ckpt`` (or the newest readable epoch checkpoint), or load
  a finished training without repeating it; without it a name's old checkpoints are discarded.
  A name identifies one network within a (scoped) run context.
"""
from __future__ import annotations

import dataclasses
import logging
import random
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass
class TrainConfig:
    """Training settings from the recipe's ``train:`` section (thesis 3.4 and 4.5: Adam with
    betas 0.9 / 0.999, lr decay 1 % per epoch, batch 16, KL weight 1e-6)."""

    epochs: int = 10
    batch_size: int = 16
    lr: float = 1e-3
    lr_decay: float = 0.99
    kl_weight: float = 1e-6
    accelerator: str = "auto"
    devices: int | str = 1
    strategy: str = "auto"
    precision: str = "32-true"
    keep_checkpoints: int = 1  # epoch checkpoints kept beside last.ckpt (a vcconv dsm's is 300 MB at 11k vertices)
    num_workers: int = 0
    log_every_n_steps: int = 10
    weight_decay: float = 0.0

    def __post_init__(self):
        checks = [("epochs", self.epochs >= 1), ("batch_size", self.batch_size >= 1), ("lr", self.lr > 0),
                  ("lr_decay", 0 < self.lr_decay <= 1), ("kl_weight", self.kl_weight >= 0),
                  ("keep_checkpoints", self.keep_checkpoints >= 1), ("num_workers", self.num_workers >= 0)]
        for key, ok in checks:
            if not ok:
                from ..errors import RecipeError

                raise RecipeError(f"train.{key}: invalid value {getattr(self, key)!r}")

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
    """Adam(lr, betas 0.9/0.999) with ExponentialLR(gamma = lr_decay) stepped once per epoch, as
    the dict ``configure_optimizers`` returns (a list of them for several optimisers)."""
    opt = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.999), weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=config.lr_decay)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}


class EpochSampler(torch.utils.data.Sampler):
    """A shuffle that depends only on (seed, epoch), so it is identical after a resume.

    With several processes (DDP) each rank takes every ``num_replicas``-th index of the same
    permutation, padded by wrapping around so that every rank sees as many samples; rank and
    world size default to those of ``torch.distributed`` when it is initialised.
    """

    def __init__(self, n: int, seed: int, shuffle: bool = True, num_replicas: int | None = None,
                 rank: int | None = None):
        self.n, self.seed, self.shuffle, self.epoch = n, seed, shuffle, 0
        self._replicas, self._rank = num_replicas, rank

    def _world(self) -> tuple[int, int]:
        if self._replicas is not None:
            return self._replicas, self._rank or 0
        dist = torch.distributed
        if dist.is_available() and dist.is_initialized():
            return dist.get_world_size(), dist.get_rank()
        return 1, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __iter__(self):
        if self.shuffle:
            g = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
            idx = torch.randperm(self.n, generator=g).tolist()
        else:
            idx = list(range(self.n))
        world, rank = self._world()
        if world > 1:
            total = len(self) * world
            idx = (idx * (total // max(self.n, 1) + 1))[:total][rank::world]
        return iter(idx)

    def __len__(self):
        world, _ = self._world()
        return -(-self.n // world)


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
    """A DataLoader over tensors / a tuple of tensors / a Dataset, batches in EpochSampler order."""
    ds = _as_dataset(data)
    if ds is None or len(ds) == 0:
        return None
    return torch.utils.data.DataLoader(ds, batch_size=batch_size, sampler=EpochSampler(len(ds), seed, shuffle),
                                       num_workers=num_workers, drop_last=False,
                                       persistent_workers=num_workers > 0,
                                       # its own generator: creating an iterator draws a worker base
                                       # seed, which must not consume the global RNG (exact resume)
                                       generator=torch.Generator().manual_seed(seed))


def _rng_state() -> dict:
    # plain tensors and tuples only: loadable with torch.load(weights_only=True)
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"torch": torch.get_rng_state(), "numpy": (str(kind), torch.as_tensor(keys.astype(np.int64)), int(pos),
            int(has_gauss), float(cached)), "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else []}


def _set_rng_state(st: dict) -> None:
    torch.set_rng_state(st["torch"])
    kind, keys, pos, has_gauss, cached = st["numpy"]
    np.random.set_state((kind, np.asarray(keys).astype(np.uint32), pos, has_gauss, cached))
    random.setstate(st["python"])
    if st.get("cuda") and torch.cuda.is_available() and len(st["cuda"]) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(st["cuda"])


def _callbacks():
    import lightning.pytorch as pl

    class RNGState(pl.Callback):
        """Store and restore the RNG states with every checkpoint (exact resume)."""

        def on_save_checkpoint(self, trainer, module, checkpoint):
            checkpoint["fwk_rng"] = _rng_state()

        def on_load_checkpoint(self, trainer, module, checkpoint):
            if checkpoint.get("fwk_rng"):
                _set_rng_state(checkpoint["fwk_rng"])

    class ManualSchedulers(pl.Callback):
        """Manual optimisation (several optimisers): step each per-epoch scheduler at the end of
        the epoch's last batch, where Lightning steps them in automatic optimisation (before
        validation and the checkpoint), unless the module already stepped it itself."""

        def on_train_epoch_start(self, trainer, module):
            self._seen = [c.scheduler.last_epoch for c in trainer.lr_scheduler_configs]

        def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
            if module.automatic_optimization or batch_idx + 1 < trainer.num_training_batches:
                return
            for c, seen in zip(trainer.lr_scheduler_configs, self._seen):
                if c.interval == "epoch" and not c.reduce_on_plateau and c.scheduler.last_epoch == seen:
                    c.scheduler.step()

    return [RNGState(), ManualSchedulers()]


def _quiet_lightning():
    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "pytorch_lightning"):
        logging.getLogger(name).setLevel(logging.ERROR)
    for pat in (".*does not have many workers.*", ".*num_workers.*", ".*LeafSpec.*", ".*is deprecated.*",
                ".*TensorBoard.*", ".*smaller than the logging interval.*", ".*Checkpoint directory.*exists.*",
                ".*predict_dataloader.*", ".*sync_dist.*", ".*GPU available but not used.*", ".*_pytree.*",
                ".*Precision.*", ".*treespec.*", ".*litlogger.*", ".*does not have a deterministic implementation.*",
                ".*lr_scheduler.step.*", ".*weights_only.*"):
        warnings.filterwarnings("ignore", message=pat)


def _loadable(path: Path):
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception:
        return None


def _resume_point(ckdir: Path):
    """The newest readable checkpoint (a run killed while writing ``last.ckpt`` leaves it
    truncated; the previous epoch's file then serves): (path, checkpoint dict) or (None, None)."""
    def epoch_of(p):
        digits = "".join(ch for ch in p.stem if ch.isdigit())
        return int(digits) if digits else -1

    cands = [ckdir / "last.ckpt"] + sorted(ckdir.glob("epoch*.ckpt"), key=epoch_of, reverse=True)
    for p in cands:
        if p.exists():
            ck = _loadable(p)
            if ck is not None and "state_dict" in ck:
                return p, ck
    return None, None


def _epochs_done(ck: dict) -> int:
    try:
        return int(ck["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"])
    except (KeyError, TypeError):
        return int(ck.get("epoch", -1)) + 1


def fit(module, train, val, ctx, name: str, config: TrainConfig | None = None):
    """Train ``module`` (a LightningModule) on ``train`` (tensors or a Dataset), validating on
    ``val`` (or None) every epoch; checkpoints under ``ctx.path('checkpoints', name)``.
    Returns the module, in eval mode.

    The module reads its settings from ``module.train_config`` (set here) in
    ``configure_optimizers`` (use ``make_optimizer``; return a list of them, one per optimiser,
    with ``automatic_optimization = False`` for several). Parameters are initialised by the
    caller (seed first: ``seed_everything(ctx.seed)``); shuffling and sampling noise are seeded
    here from ``ctx.seed``.

    With ``ctx.resume`` and a checkpoint of this name, training continues from it and ends with
    the weights an uninterrupted run gives; a finished training is loaded, not repeated. Without
    ``ctx.resume`` old checkpoints of this name are discarded and training starts afresh.
    """
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
    from lightning.pytorch.loggers import TensorBoardLogger

    _quiet_lightning()
    config = config or ctx.train
    module.train_config = config
    ckdir = ctx.path("checkpoints", name, "x").parent
    tbdir = ctx.path("tb", name, "x").parent
    ckpt_path = None
    if getattr(ctx, "resume", False):
        ckpt_path, ck = _resume_point(ckdir)
        if ck is not None and _epochs_done(ck) >= config.epochs:
            if hasattr(module, "on_load_checkpoint"):
                module.on_load_checkpoint(ck)
            module.load_state_dict(ck["state_dict"])
            module.eval()
            return module
    else:
        for p in list(ckdir.glob("*.ckpt")):
            p.unlink()
    seed_everything(ctx.seed)
    train_loader = make_loader(train, config.batch_size, ctx.seed, True, config.num_workers)
    if train_loader is None:
        from ..errors import DataError

        raise DataError(f"{name}: no training samples")
    val_loader = make_loader(val, config.batch_size, ctx.seed, False, config.num_workers)
    accelerator = config.accelerator
    if accelerator == "auto" and getattr(ctx, "device", "cpu") == "cpu":
        accelerator = "cpu"
    on_cpu = accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())
    checkpoint = ModelCheckpoint(dirpath=ckdir, filename="epoch{epoch:03d}", auto_insert_metric_name=False,
                                 save_last=True, save_top_k=max(1, config.keep_checkpoints), monitor="epoch",
                                 mode="max", every_n_epochs=1, save_on_train_epoch_end=val_loader is None)
    show_bar = not ctx.quiet and sys.stderr.isatty()
    det = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    try:
        with warnings.catch_warnings():
            _quiet_lightning()
            trainer = pl.Trainer(
                max_epochs=config.epochs, accelerator=accelerator, devices=config.devices,
                strategy=config.strategy, precision=config.precision,
                # bit-exact on CPU; on GPUs some scatter kernels have no deterministic variant
                deterministic=True if on_cpu else "warn",
                logger=TensorBoardLogger(str(tbdir), name="", version=""),
                callbacks=[checkpoint, LearningRateMonitor("epoch"), *_callbacks()], enable_progress_bar=show_bar, enable_model_summary=False,
                log_every_n_steps=config.log_every_n_steps, num_sanity_val_steps=0, default_root_dir=str(ckdir),
                use_distributed_sampler=False,
            )
            trainer.fit(module, train_loader, val_loader, ckpt_path=str(ckpt_path) if ckpt_path else None,
                        weights_only=False)
    finally:
        torch.use_deterministic_algorithms(det[0], warn_only=det[1])
    module.eval()
    return module


def kl_divergence(mu, logvar):
    """KL(N(mu, diag exp(logvar)) || N(0, I)) = -1/2 sum_j (1 + logvar_j - mu_j^2 - exp(logvar_j)),
    averaged over the batch (thesis eq. 3.22); zero for a deterministic code (``logvar`` None)."""
    if logvar is None:
        return mu.new_zeros(())
    return -0.5 * torch.mean(torch.sum(1 + logvar - mu.pow(2) - logvar.exp(), dim=1))


def reparameterize(mu, logvar, sample: bool):
    """z = mu + sigma eps with eps ~ N(0, I) when ``sample`` (training a VAE), else the mean."""
    if not sample or logvar is None:
        return mu
    return mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)


def loss_module(modules: dict, loss):
    """A LightningModule that trains the parameters of ``modules`` (attribute name -> nn.Module;
    the names prefix the checkpoint's keys) that require gradients by ``loss(module, batch,
    stage)``, stage ``"train"`` or ``"val"`` (log with ``module.log``), with Adam and per-epoch
    decay from the run's training settings (``make_optimizer``)."""
    import lightning.pytorch as pl

    class LossModule(pl.LightningModule):
        def __init__(self):
            super().__init__()
            for name, m in modules.items():
                setattr(self, name, m)

        def _loss(self, batch, stage):
            return loss(self, batch, stage)

        def training_step(self, batch, _):
            return self._loss(batch, "train")

        def validation_step(self, batch, _):
            return self._loss(batch, "val")

        def configure_optimizers(self):
            return make_optimizer([p for p in self.parameters() if p.requires_grad], self.train_config)

    return LossModule()


def autoencoder_module(net, unscale, kl_weight: float, encode=None, decode=None):
    """The LightningModule of every (variational) autoencoder trained on one feature tensor F:
    loss = mean |unscale(decode(z)) - unscale(F)| + kl_weight KL (thesis table 3.2, eqs.
    3.19-3.23: L1 in the representation's own unscaled space; the KL term only where ``encode``
    returns a log-variance), z sampled by reparameterisation while training and the mean otherwise.

    ``net`` is the nn.Module holding the parameters (checkpointed as ``net.*``); ``encode(net, F)``
    returns (mu, logvar or None) and ``decode(net, z)`` the features (default: ``net.enc(F)`` and
    ``net.dec(z)``). Logs ``<stage>_loss`` and
    ``<stage>_l1``; Adam with per-epoch decay from the run's training settings.
    """
    encode = encode or (lambda n, F: n.enc(F))
    decode = decode or (lambda n, z: n.dec(z))

    def loss(module, batch, stage):
        (F,) = batch
        mu, logvar = encode(module.net, F)
        G = decode(module.net, reparameterize(mu, logvar, module.training))
        rec = torch.mean(torch.abs(unscale(G) - unscale(F)))
        total = rec + kl_weight * kl_divergence(mu, logvar) if logvar is not None else rec
        module.log(f"{stage}_loss", total, prog_bar=True, on_epoch=True, on_step=False, batch_size=len(F))
        module.log(f"{stage}_l1", rec, on_epoch=True, on_step=False, batch_size=len(F))
        return total

    return loss_module({"net": net}, loss)


@torch.no_grad()
def predict_batches(fn, X, batch_size: int = 64, device: str | torch.device = "cpu", dtype=torch.float32) -> np.ndarray:
    """Apply ``fn`` to X (numpy or tensor, first dim = samples) in batches without gradients."""
    outs = []
    X = X if torch.is_tensor(X) else torch.as_tensor(np.asarray(X), dtype=dtype)
    for i in range(0, len(X), batch_size):
        y = fn(X[i:i + batch_size].to(device))
        outs.append(y.detach().cpu().numpy() if torch.is_tensor(y) else np.asarray(y))
    return np.concatenate(outs, axis=0) if outs else np.zeros((0,))


__all__ = ["TrainConfig", "fit", "make_optimizer", "seed_everything", "predict_batches", "make_loader", "EpochSampler",
           "kl_divergence", "reparameterize", "autoencoder_module", "loss_module"]
