"""``fit``: train a LightningModule the way every fwk run does; seeding, the optimiser, batched
prediction."""
from __future__ import annotations

import contextlib
import logging
import random
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from ..errors import DataError, FwkError
from ..safeio import LegacyFormatError, load_state
from .config import TrainConfig
from .distributed import DistEnv, RankDone, make_job, make_strategy, rank_job, wants_ddp
from .loading import make_loader
from .memory import retain_freed_memory
from .threads import apply_threads, register, report_threads


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global RNGs (initialisation is drawn from them)."""
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def upgrade_optimizer_states(module, checkpoint: dict, params: list) -> None:
    """The optimiser states of a checkpoint in today's layout of their parameters: each state of a
    parameter whose module plays ``fwk.protocols.UpgradesSavedTensors`` goes through its ``upgrade``
    (in place; the parameters themselves go through the module's ``load_state_dict``). ``params``:
    each optimiser's parameter list, in the order ``configure_optimizers`` gave them to
    ``make_optimizer`` (a state's index is its parameter's place there)."""
    from fwk.protocols import UpgradesSavedTensors

    owner = {}
    for mod in module.modules():
        for name, p in mod.named_parameters(recurse=False):
            owner.setdefault(id(p), (mod, name))
    for opt, group in zip(checkpoint.get("optimizer_states") or [], params):
        for idx, state in (opt.get("state") or {}).items():
            if not isinstance(idx, int) or not 0 <= idx < len(group) or id(group[idx]) not in owner:
                continue
            p = group[idx]
            mod, name = owner[id(p)]
            if isinstance(mod, UpgradesSavedTensors):
                for key, value in state.items():
                    if torch.is_tensor(value) and value.shape != p.shape:  # contiguous: fused Adam reads memory
                        state[key] = mod.upgrade(name, value).contiguous()


def make_optimizer(params, config: TrainConfig):
    """Adam(lr, betas 0.9/0.999) with ExponentialLR(gamma = lr_decay) stepped once per epoch, as
    the dict ``configure_optimizers`` returns (a list of them for several optimisers). Adam runs
    fused (one kernel over every parameter; the same update to float32 rounding): torch's default
    on CPU loops over the parameters op by op, 96 ms a step for the thesis's vcconv VAE (12.1 M
    parameters) against 30 ms fused, 9.4 against 0.8 ms for the spiral++ AE (1 thread, measured
    2026-12-03)."""
    opt = torch.optim.Adam(params, lr=config.lr, betas=(0.9, 0.999), weight_decay=config.weight_decay, fused=True)
    sched = torch.optim.lr_scheduler.ExponentialLR(opt, gamma=config.lr_decay)
    return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "epoch"}}


def _quiet_lightning():
    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "pytorch_lightning"):
        logging.getLogger(name).setLevel(logging.ERROR)
    for pat in (".*does not have many workers.*", ".*num_workers.*", ".*LeafSpec.*", ".*is deprecated.*",
                ".*TensorBoard.*", ".*smaller than the logging interval.*", ".*Checkpoint directory.*exists.*",
                ".*predict_dataloader.*", ".*sync_dist.*", ".*GPU available but not used.*", ".*_pytree.*",
                ".*Precision.*", ".*treespec.*", ".*litlogger.*", ".*does not have a deterministic implementation.*",
                ".*lr_scheduler.step.*", ".*weights_only.*", ".*no `val_dataloader`.*"):
        warnings.filterwarnings("ignore", message=pat)


def _loadable(path: Path):
    """The checkpoint at ``path`` (``fwk.safeio``'s format), or None when it is damaged (a write
    a kill cut short); a pickled checkpoint of an earlier fwk is refused, never unpickled."""
    try:
        ck = load_state(path)
    except LegacyFormatError:
        raise
    except DataError:  # damaged, truncated
        return None
    return ck if isinstance(ck, dict) else None


def _resume_point(ckdir: Path):
    """The newest readable checkpoint (a run killed while writing ``last.ckpt`` leaves it
    truncated; the previous epoch's file then serves): (path, checkpoint dict) or (None, None)."""
    cands = [ckdir / "last.ckpt"] + sorted(ckdir.glob("epoch*.ckpt"), key=_epoch_of, reverse=True)
    for p in cands:
        if p.exists():
            ck = _loadable(p)
            if ck is not None and "state_dict" in ck:
                return p, ck
    return None, None


def _stopped_early(ck: dict) -> bool:
    """Whether the stopping rule ended the training this checkpoint saved."""
    return bool((ck.get("fwk_curves") or {}).get("stop"))


def network_name(ctx, name: str) -> str:
    """How reports name the network ``fit`` trains as ``name`` in ``ctx``: the context's scope
    (the model's label) and ``name``, once where they agree (``pca``, ``pbs``, ``pb/pb-step2``)."""
    scope = ctx.scope
    if not scope:
        return name
    return scope if scope.rsplit("/", 1)[-1] == name else f"{scope}/{name}"


def _epochs_done(ck: dict) -> int:
    try:
        return int(ck["loops"]["fit_loop"]["epoch_progress"]["current"]["processed"])
    except (KeyError, TypeError):
        return int(ck.get("epoch", -1)) + 1


def _epoch_of(p: Path) -> int:
    digits = "".join(ch for ch in p.stem if ch.isdigit())
    return int(digits) if digits else -1


def prune_checkpoints(ckdir: Path, keep: int) -> list[Path]:
    """Keep ``last.ckpt`` and the newest ``keep`` epoch files of ``ckdir``; remove the other
    epoch files (a run resumed from an older epoch file, or killed between writing an epoch's
    file and removing the previous one, leaves them). Returns the removed files."""
    files = sorted(Path(ckdir).glob("epoch*.ckpt"), key=_epoch_of, reverse=True)
    removed = []
    for p in files[max(1, keep):]:
        try:
            p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def _world_size(devices, on_cpu: bool) -> int:
    """How many processes ``devices`` means (an int, a list of device indices, ``auto`` / -1)."""
    if isinstance(devices, (list, tuple)):
        return max(1, len(devices))
    if isinstance(devices, str) and devices.strip().lstrip("-").isdigit():
        devices = int(devices)
    if isinstance(devices, int) and devices > 0:
        return devices
    return 1 if on_cpu else max(1, torch.cuda.device_count())


def fit(module, train, val, ctx, name: str, config: TrainConfig | None = None):
    """Train ``module`` (a LightningModule) on ``train`` (tensors or a Dataset), validating on
    ``val`` (or None) every epoch; checkpoints under ``ctx.path('checkpoints', name)``.
    Returns the module, in eval mode.

    ``config.early_stopping`` (an ``EarlyStopping``) ends training before ``config.epochs``
    once the validation loss stops improving (without validation data it is not applied).
    The per-epoch losses and why training ended are written to ``curves/<scope>/<name>.json``
    every epoch (``TrainingCurves``); torch's thread count follows ``fwk.engine.threads``,
    re-checked every epoch.

    The module reads its settings from ``module.train_config`` (set here) in
    ``configure_optimizers`` (use ``make_optimizer``; return a list of them, one per optimiser,
    with ``automatic_optimization = False`` for several). Parameters are initialised by the
    caller (seed first: ``seed_everything(ctx.seed)``); shuffling and sampling noise are seeded
    here from ``ctx.seed``.

    With ``ctx.resume`` and a checkpoint of this name, training continues from it and ends with
    the weights an uninterrupted run gives; a finished training is loaded, not repeated. Without
    ``ctx.resume`` old checkpoints of this name are discarded and training starts afresh.
    """
    # deferred: Lightning costs ~2.2 s of import time on top of torch's ~1 s (measured with
    # python -X importtime); plugins import `fit` at their top and `fwk list` imports every plugin
    import lightning.pytorch as pl
    from lightning.pytorch.callbacks import LearningRateMonitor
    from lightning.pytorch.loggers import TensorBoardLogger

    from .callbacks import (LinkedLastCheckpoint, ManualSchedulers, ProgressLines, RNGState, SafeCheckpointIO,
                            ThreadShare, TrainingCurves)

    _quiet_lightning()
    config = config or ctx.train
    module.train_config = config
    ckdir = ctx.path("checkpoints", name, "x").parent
    tbdir = ctx.path("tb", name, "x").parent
    network = network_name(ctx, name)

    def curves(rule=config.early_stopping, note=None):
        return TrainingCurves(ctx.path("curves", f"{name}.json"), network, config.epochs, rule, note)

    job = rank_job()  # in a DDP rank > 0 process: the one training it joins
    target = job is not None and Path(job["ckdir"]) == ckdir.resolve()
    ckpt_path = None
    if target:
        ckpt_path = Path(job["ckpt"]) if job["ckpt"] else None  # rank 0's choice
    elif ctx.resume:
        ckpt_path, ck = _resume_point(ckdir)
        done = _epochs_done(ck) if ck is not None else 0
        if ck is not None and (done >= config.epochs or _stopped_early(ck)):
            ctx.log(f"{network}: training finished before ({done} epoch{'s' if done != 1 else ''}); "
                    f"loaded from {ckpt_path.name}")
            module.on_load_checkpoint(ck)  # a LightningModule hook: no-op unless the module overrides it
            module.load_state_dict(ck["state_dict"])
            if ck.get("fwk_curves"):  # the record, as the finished training left it
                curves().restore(ck["fwk_curves"]).write()
            prune_checkpoints(ckdir, config.keep_checkpoints)
            module.eval()
            return module
        if ck is not None:
            ctx.log(f"{network}: resuming from {ckpt_path.name}: {done} of {config.epochs} epochs done, "
                    f"continuing with epoch {done + 1}")
        elif any(ckdir.glob("*.ckpt")):  # (none at all: a fresh start, e.g. a new grid member; no word)
            ctx.log(f"{network}: no readable checkpoint to resume from; training from epoch 1")
    else:
        for p in list(ckdir.glob("*.ckpt")):
            p.unlink()
        ctx.path("curves", f"{name}.json").unlink(missing_ok=True)
    if job is not None and not target:
        raise FwkError(f"train.strategy ddp: this rank would train {network} before the training it joins "
                       f"({job['ckdir']}); the run's finished trainings differ from rank 0's")
    register()  # this process counts among those that share the cores (fwk.engine.threads)
    retain_freed_memory()  # freed tensors stay in the heap for the next step (fwk.engine.memory)
    n, why, _ = apply_threads()
    report_threads(ctx.log, n, why, ctx.log_file)  # once per log file and count: not at every flip or fit
    seed_everything(ctx.seed)
    train_loader = make_loader(train, config.batch_size, ctx.seed, True, config.num_workers)
    if train_loader is None:
        raise DataError(f"{name}: no training samples")
    val_loader = make_loader(val, config.batch_size, ctx.seed, False, config.num_workers)
    if config.early_stopping is not None and val_loader is None:
        note = "no validation data: train.early_stopping not applied"
        ctx.log(f"{network}: {note}")
        recorder = curves(None, note)
    else:
        recorder = curves()
    accelerator = config.accelerator
    if accelerator == "auto" and ctx.device == "cpu":
        accelerator = "cpu"
    on_cpu = accelerator == "cpu" or (accelerator == "auto" and not torch.cuda.is_available())
    strategy, world, dist_env = config.strategy, 1, contextlib.nullcontext()
    if wants_ddp(config):
        world = _world_size(config.devices, on_cpu)
        strategy = make_strategy(job if job is not None else make_job(ctx, ckdir, ckpt_path), config.devices, world)
        if job is None:
            dist_env = DistEnv(world)
            ctx.log(f"{network}: DDP on {world} {'CPU processes' if on_cpu else 'devices'}, "
                    f"{config.batch_size} samples each per step (effective batch {world * config.batch_size})")
    checkpoint = LinkedLastCheckpoint(dirpath=ckdir, filename="epoch{epoch:03d}", auto_insert_metric_name=False,
                                      save_last="link", save_top_k=max(1, config.keep_checkpoints), monitor="epoch",
                                      mode="max", every_n_epochs=1,
                                      # at the end of the epoch, after TrainingCurves' record and decision
                                      save_on_train_epoch_end=True)
    show_bar = not ctx.quiet and sys.stderr.isatty()
    callbacks = [checkpoint, LearningRateMonitor("epoch"), RNGState(ctx.seed), ManualSchedulers(),
                 ThreadShare(ctx.log, ctx.log_file), recorder]
    if not ctx.quiet and not show_bar:  # a log file, a pipe: plain lines, a few seconds apart
        callbacks.append(ProgressLines(network, config.epochs))
    det = (torch.are_deterministic_algorithms_enabled(), torch.is_deterministic_algorithms_warn_only_enabled())
    try:
        with warnings.catch_warnings(), dist_env:
            _quiet_lightning()
            trainer = pl.Trainer(
                max_epochs=config.epochs, accelerator=accelerator, devices=config.devices,
                strategy=strategy, precision=config.precision,
                # bit-exact on CPU; on GPUs some scatter kernels have no deterministic variant
                deterministic=True if on_cpu else "warn",
                logger=TensorBoardLogger(str(tbdir), name="", version=""),
                # checkpoints: data only, never a pickle (fwk's DDP strategy carries the same IO itself:
                # Lightning refuses it twice, and a strategy instance otherwise pickles)
                callbacks=callbacks, plugins=[SafeCheckpointIO()] if isinstance(strategy, str) else [],
                enable_progress_bar=show_bar, enable_model_summary=False,
                log_every_n_steps=config.log_every_n_steps, num_sanity_val_steps=0, default_root_dir=str(ckdir),
                use_distributed_sampler=False,
            )
            # read through SafeCheckpointIO (fwk.safeio): nothing in a checkpoint is unpickled
            trainer.fit(module, train_loader, val_loader, ckpt_path=str(ckpt_path) if ckpt_path else None,
                        weights_only=True)
    finally:
        torch.use_deterministic_algorithms(det[0], warn_only=det[1])
    if job is not None:  # a DDP rank > 0: its part is over; rank 0 writes everything
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()
        raise RankDone()
    prune_checkpoints(ckdir, config.keep_checkpoints)
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
