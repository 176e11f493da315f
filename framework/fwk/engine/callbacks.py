"""The Lightning callbacks ``fit`` adds to every training: exact resume and manual schedulers."""
from __future__ import annotations

import random

import lightning.pytorch as pl
import numpy as np
import torch


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


class RNGState(pl.Callback):
    """Store the torch, NumPy, Python (and CUDA) RNG states in every checkpoint, under
    ``fwk_rng``, and restore them on resume, so that a resumed run draws what an uninterrupted
    one would (dropout, sampling noise)."""

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
