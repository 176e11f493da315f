"""The Lightning callbacks ``fit`` adds to every training: exact resume (and per-rank noise
under DDP), manual schedulers, thread sharing, the training curves with the optional stopping
rule, and progress as plain lines where no progress bar is shown."""
from __future__ import annotations

import json
import math
import random
import sys
import time
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import torch
from lightning.fabric.plugins.io.checkpoint_io import CheckpointIO

from ..cache import atomic_link, atomic_write_bytes
from ..errors import RecipeError
from ..safeio import load_state, save_state
from .threads import apply_threads, report_threads


def _snapshot(obj):
    """A copy of a checkpoint that training cannot change any more: every tensor copied to the CPU,
    every array copied, every dict, list and tuple rebuilt (Lightning's checkpoint holds the live
    parameters, the optimiser's states and callbacks' own containers)."""
    if isinstance(obj, torch.Tensor):
        return obj.detach().to("cpu", copy=True)
    if isinstance(obj, np.ndarray):
        return obj.copy()
    if isinstance(obj, dict):
        return {k: _snapshot(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_snapshot(v) for v in obj]
    if isinstance(obj, tuple):
        return tuple(_snapshot(v) for v in obj)
    return obj


class SafeCheckpointIO(CheckpointIO):
    """How Lightning writes and reads every checkpoint of ``fit`` (``last.ckpt``, the epoch files,
    a resume): ``fwk.safeio``'s format, tensors and plain data only, never a pickle; written
    atomically. A pickled checkpoint of an earlier fwk is refused (``fwk convert RUN --trust``),
    a damaged one raises ``DataError`` naming it.

    With ``background`` (the default) the files are written by one thread of their own while
    training goes on: a save takes a snapshot of the checkpoint (``_snapshot``, on the caller's
    thread) and queues its write; the removal of an older epoch file and ``last.ckpt``'s link
    (``LinkedLastCheckpoint``) queue behind it, so the folder changes in the order Lightning asked.
    A save first waits for the writes queued before it (one checkpoint in memory at a time); a
    load, ``wait`` and the end of ``fit`` (Lightning's ``teardown``) wait for all of them. A write
    that failed raises its error there, and nothing queued after it is done. Measured on the chapter
    5 width (20 training steps, 2 threads, beside a 450 MB save): 2.9-3.4 s against 4.0-4.2 s one
    after the other; the chapter 5 study's PBS alone, epochs 1.03-1.08x faster (2026-12-07)."""

    def __init__(self, background: bool = True):
        super().__init__()
        self.background = background
        self._pool = None
        self._last = None
        self._error: BaseException | None = None

    def _run(self, fn, *args) -> None:
        if self._error is not None:  # a write failed: the ones after it would leave the folder out of order
            return
        try:
            fn(*args)
        except BaseException as exc:  # raised on the training's thread, by the next save or wait
            self._error = exc

    def _queue(self, fn, *args) -> None:
        self._raise()
        if not self.background:
            fn(*args)
            return
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fwk-checkpoint")
        self._last = self._pool.submit(self._run, fn, *args)

    def _raise(self) -> None:
        if self._error is not None:
            exc, self._error = self._error, None
            raise exc

    def wait(self) -> None:
        """Return when every queued write is done; raise the first error one of them met."""
        if self._last is not None:
            self._last.result()
            self._last = None
        self._raise()

    def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
        if not self.background:
            save_state(Path(path), checkpoint)
            return
        self.wait()
        self._queue(save_state, Path(path), _snapshot(checkpoint))

    def link(self, path, linkpath) -> None:
        """``linkpath`` made the file ``path`` is (``fwk.cache.atomic_link``), after the writes queued."""
        self._queue(atomic_link, Path(path), Path(linkpath))

    def load_checkpoint(self, path, map_location=None, weights_only=None) -> dict:
        self.wait()
        # tensors come back on the CPU; Lightning moves the module's and the optimisers' states
        return load_state(Path(path))

    def remove_checkpoint(self, path) -> None:
        self._queue(lambda p: p.unlink(missing_ok=True), Path(path))

    def teardown(self) -> None:
        try:
            self.wait()
        finally:
            if self._pool is not None:
                self._pool.shutdown(wait=True)
                self._pool = None


class LinkedLastCheckpoint(pl.callbacks.ModelCheckpoint):
    """Lightning's ``ModelCheckpoint`` with ``save_last="link"``, the link a hard one: ``last.ckpt``
    is the epoch file just written under a second name (``fwk.cache.atomic_link``), not a second
    serialisation of the same state, nor Lightning's symlink (which could send a reader of a run
    directory anywhere, and which it makes by removing ``last.ckpt`` first).

    Each epoch then writes its checkpoint once instead of twice: the chapter 5 study's PBS (six
    vcconv VAEs, 465 MB with Adam's states) spent 2.9 s an epoch in the two writes, a third of its
    training (py-spy, 2 threads, 2026-12-07). A damaged epoch file is a damaged ``last.ckpt``: both
    names hold one file (a copy of the run, as ``cp -r`` makes it, holds two)."""

    @staticmethod
    def _link_checkpoint(trainer, filepath: str, linkpath: str) -> None:
        if trainer.is_global_zero and Path(filepath).resolve() != Path(linkpath).resolve():
            io = trainer.strategy.checkpoint_io
            if isinstance(io, SafeCheckpointIO):  # behind the epoch file's write, on its thread
                io.link(filepath, linkpath)
            else:
                atomic_link(Path(filepath), Path(linkpath))
        trainer.strategy.barrier()


def _rng_state() -> dict:
    # plain tensors, tuples and numbers only: a checkpoint holds no other objects (fwk.safeio)
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


def rank_seed(seed: int, epoch: int, rank: int) -> int:
    """The seed of the sampling noise of ``epoch`` (0-based) on DDP rank ``rank``."""
    return ((int(seed) * 1_000_003 + int(epoch)) * 10_007 + int(rank)) % (2**63 - 1)


class RNGState(pl.Callback):
    """Store the torch, NumPy, Python (and CUDA) RNG states in every checkpoint, under
    ``fwk_rng``, and restore them on resume, so that a resumed run draws what an uninterrupted
    one would (dropout, sampling noise).

    With several processes (DDP) and a ``seed``, every epoch instead seeds the global RNGs of
    each rank with ``rank_seed(seed, epoch, rank)``: the ranks draw different noise, and a
    resumed run the noise an uninterrupted one drew (the checkpoint holds rank 0's state only).
    """

    def __init__(self, seed: int | None = None):
        self.seed = seed

    def on_train_epoch_start(self, trainer, module):
        if self.seed is None or trainer.world_size <= 1:
            return
        s = rank_seed(self.seed, trainer.current_epoch, trainer.global_rank)
        torch.manual_seed(s)
        np.random.seed(s % (2**32))
        random.seed(s)

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


class ThreadShare(pl.Callback):
    """At the start of every epoch, size torch's threads by ``fwk.engine.threads``' rule (the
    cores shared among the live fwk processes, or the explicit ``FWK_THREADS`` /
    ``OMP_NUM_THREADS``); a count not said before is reported through ``log`` (``report_threads``)."""

    def __init__(self, log=None, key=None):
        # not ``self.log``: Lightning sets a callback's ``log`` to the module's (callback_connector)
        self.report = log
        self.key = key  # what report_threads says each count once for (the run's log file)

    def on_train_epoch_start(self, trainer, module):
        n, why, changed = apply_threads()
        if changed and self.report is not None:
            report_threads(self.report, n, why, self.key)


def stopping_rule(values, patience: int, min_delta: float, relative: bool = False) -> dict:
    """The early-stopping rule over the monitored values of epochs 1..E (in order): the best
    value so far counts as improved upon when a value falls below it by more than ``min_delta``
    (``relative``: by more than ``min_delta`` times its magnitude);
    training stops at the first epoch after which ``patience`` epochs in a row brought no
    improvement, or at a non-finite value. Returns {stop, reason, epoch (1-based, where it
    stopped, else None), wait (epochs without improvement at the end), best (the rule's
    reference value)}."""
    best, wait = None, 0
    for e, v in enumerate(values, start=1):
        if v is None or not math.isfinite(v):
            return {"stop": True, "reason": "non-finite", "epoch": e, "wait": wait, "best": best}
        if best is None or v < best - (min_delta * abs(best) if relative else min_delta):
            best, wait = v, 0
        else:
            wait += 1
        if wait >= patience:
            return {"stop": True, "reason": "no improvement", "epoch": e, "wait": wait, "best": best}
    return {"stop": False, "reason": None, "epoch": None, "wait": wait, "best": best}


class TrainingCurves(pl.Callback):
    """The per-epoch losses of one network, the stopping rule, and their record.

    At the end of every epoch (after validation, before the checkpoint) it records every scalar
    the module logged whose name starts with ``train_`` or ``val_`` (epoch means where logged
    per epoch), the epoch's wall time and thread count; applies ``rule`` (an ``EarlyStopping``,
    or None) to the monitored values of all epochs so far, setting ``trainer.should_stop``; and
    writes ``path`` (JSON, atomically). The history and the decision are stored in every
    checkpoint (``fwk_curves``) and restored on resume, so a resumed run stops where an
    uninterrupted one does and its record is the same (but for wall times).
    """

    def __init__(self, path, network: str, max_epochs: int, rule=None, note: str | None = None):
        self.path = Path(path)
        self.network, self.max_epochs, self.rule, self.note = network, int(max_epochs), rule, note
        self.history: list[dict] = []
        self.stop: dict | None = None
        self._t0 = None

    # state ------------------------------------------------------------------------
    def state(self) -> dict:
        """What a checkpoint stores: the history and the rule's decision."""
        return {"history": [dict(h) for h in self.history], "stop": dict(self.stop) if self.stop else None}

    def restore(self, state: dict) -> "TrainingCurves":
        """Take the history and decision of a checkpoint's ``fwk_curves``."""
        self.history = [dict(h) for h in state.get("history", [])]
        self.stop = dict(state["stop"]) if state.get("stop") else None
        return self

    def on_save_checkpoint(self, trainer, module, checkpoint):
        checkpoint["fwk_curves"] = self.state()

    def on_load_checkpoint(self, trainer, module, checkpoint):
        if checkpoint.get("fwk_curves"):
            self.restore(checkpoint["fwk_curves"])

    # recording --------------------------------------------------------------------
    def on_train_epoch_start(self, trainer, module):
        self._t0 = time.perf_counter()

    def on_train_epoch_end(self, trainer, module):
        epoch = trainer.current_epoch + 1  # `completed` is incremented after this hook
        rec = {"epoch": epoch}
        for key, value in sorted(trainer.callback_metrics.items()):
            if key.startswith(("train_", "val_")) and (not torch.is_tensor(value) or value.numel() == 1):
                rec[key] = float(value)
        if trainer.world_size > 1:  # every rank's epoch means, averaged over the ranks (equal sample counts)
            keys = [k for k in rec if k != "epoch"]
            mean = trainer.strategy.reduce(torch.tensor([rec[k] for k in keys], dtype=torch.float64),
                                           reduce_op="mean")
            rec.update({k: float(v) for k, v in zip(keys, mean.tolist())})
        rec["seconds"] = round(time.perf_counter() - self._t0, 3) if self._t0 is not None else None
        rec["threads"] = torch.get_num_threads()
        # a resumed epoch replaces whatever a killed run had recorded for it
        self.history = [h for h in self.history if h["epoch"] < epoch] + [rec]
        if self.rule is not None:
            if self.rule.monitor not in rec:
                logged = ", ".join(k for k in rec if k.startswith(("train_", "val_"))) or "nothing"
                raise RecipeError(f"train.early_stopping.monitor: {self.network} logs no {self.rule.monitor!r} "
                                  f"(logged: {logged})")
            d = stopping_rule([h.get(self.rule.monitor) for h in self.history], self.rule.patience,
                              self.rule.min_delta, self.rule.relative)
            if d["stop"]:
                self.stop = {"epoch": d["epoch"], "reason": d["reason"]}
                trainer.should_stop = True
        if trainer.is_global_zero:
            self.write()

    # the record -------------------------------------------------------------------
    def summary(self) -> dict:
        """The JSON record: settings, per-epoch values, why training ended, the best epoch."""
        monitor = self.rule.monitor if self.rule is not None else "val_loss"
        values = [(h["epoch"], h.get(monitor)) for h in self.history]
        finite = [(e, v) for e, v in values if v is not None and math.isfinite(v)]
        best_epoch, best = min(finite, key=lambda ev: ev[1]) if finite else (None, None)
        run = len(self.history)
        if self.stop:
            stopped_by = "early_stopping"
        elif run >= self.max_epochs:
            stopped_by = "max_epochs"
        else:
            stopped_by = None  # still training, or killed
        rule = None
        if self.rule is not None:
            rule = {"patience": self.rule.patience, "min_delta": self.rule.min_delta, "monitor": self.rule.monitor,
                    "relative": self.rule.relative}
        return {
            "network": self.network,
            "max_epochs": self.max_epochs,
            "early_stopping": rule,
            "note": self.note,
            "monitor": monitor,
            "epochs_run": run,
            "finished": stopped_by is not None,
            "stopped_by": stopped_by,
            "stop_reason": self.stop["reason"] if self.stop else None,
            "stopped_epoch": (self.stop["epoch"] if self.stop else run) if stopped_by else None,
            "best_epoch": best_epoch,
            "best_val_loss": best,
            "epochs": self.history,
        }

    def write(self) -> Path:
        """Write the record to ``path`` (atomically)."""
        text = json.dumps(self.summary(), indent=1, allow_nan=True) + "\n"
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(self.path, text.encode())
        return self.path


def duration(seconds: float) -> str:
    """``seconds`` as a person reads it: ``42 s``, ``3 min 05 s``, ``2 h 07 min``."""
    s = max(0, int(round(seconds)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


#: the least time between two progress lines
PROGRESS_EVERY_S = 5.0


class ProgressLines(pl.Callback):
    """Progress as plain lines, for a log file or a pipe (where no progress bar is drawn): the
    network, the epoch (and batch, within a long epoch), the last epoch's losses, the time
    elapsed and an estimate of the time left (at the rate of the batches trained so far; early
    stopping may end sooner), at most one line every ``every_s`` seconds, and always one for
    the last epoch. Rank 0 only under DDP."""

    def __init__(self, network: str, max_epochs: int, every_s: float = PROGRESS_EVERY_S, out=None, clock=None):
        self.network, self.max_epochs, self.every_s = network, int(max_epochs), float(every_s)
        self.out = out
        self.clock = clock or time.monotonic
        self._t0 = self._last = None
        self._first = 0

    def _print(self, text: str) -> None:
        print(f"[{self.network}] {text}", file=self.out or sys.stdout, flush=True)

    def on_train_start(self, trainer, module):
        if not trainer.is_global_zero:
            return
        self._t0 = self._last = self.clock()
        self._first = trainer.current_epoch
        if self._first:
            what = f"epochs {self._first + 1}-{self.max_epochs}"
        else:
            what = f"{self.max_epochs} epoch{'s' if self.max_epochs != 1 else ''}"
        nb = trainer.num_training_batches
        self._print(f"training {what}, {nb} batch{'es' if nb != 1 else ''} each")

    def _done_left(self, trainer, batches_in_epoch: int) -> tuple[float, float | None]:
        nb = max(1, trainer.num_training_batches if math.isfinite(trainer.num_training_batches) else 1)
        done = (trainer.current_epoch - self._first) * nb + batches_in_epoch
        total = (self.max_epochs - self._first) * nb
        elapsed = self.clock() - self._t0
        left = elapsed / done * (total - done) if done > 0 else None
        return elapsed, left

    def _line(self, trainer, where: str, batches_in_epoch: int, losses: str = "", final: bool = False) -> None:
        elapsed, left = self._done_left(trainer, batches_in_epoch)
        tail = f", {duration(elapsed)} elapsed"
        if not final and left is not None:
            tail += f", about {duration(left)} left"
        self._print(f"{where}{losses}{tail}")
        self._last = self.clock()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        nb = trainer.num_training_batches
        if self._t0 is None or self.clock() - self._last < self.every_s or batch_idx + 1 >= nb:
            return  # (an epoch's last batch: the epoch's end decides, with the losses)
        self._line(trainer, f"epoch {trainer.current_epoch + 1}/{self.max_epochs}, batch {batch_idx + 1}/{nb}",
                   batch_idx + 1)

    def on_train_epoch_end(self, trainer, module):
        if self._t0 is None:
            return
        epoch = trainer.current_epoch + 1
        last = epoch >= self.max_epochs or trainer.should_stop
        if not last and self.clock() - self._last < self.every_s:
            return
        values = []
        for key in sorted(trainer.callback_metrics):
            v = trainer.callback_metrics[key]
            if key.endswith("_loss") and key.startswith(("train_", "val_")) and (not torch.is_tensor(v) or v.numel() == 1):
                values.append(f"{key} {float(v):.4g}")
        nb = trainer.num_training_batches if math.isfinite(trainer.num_training_batches) else 0
        where = f"epoch {epoch}/{self.max_epochs}" + (" (stopping early)" if trainer.should_stop and epoch < self.max_epochs else "")
        self._line(trainer, where, int(nb), (", " + ", ".join(values)) if values else "", final=last)
