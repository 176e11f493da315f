"""``TrainConfig``: the recipe's ``train:`` section.

This module imports neither torch nor Lightning: ``fwk.recipes`` and ``fwk.runs`` (loaded by
``fwk list`` and ``fwk --help``) validate recipes with it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import RecipeError
from ..registry import did_you_mean


@dataclass
class EarlyStopping:
    """The stopping rule of ``train.early_stopping`` (off unless given): training ends after the
    first epoch e at which the monitored validation loss has not improved for ``patience``
    epochs in a row, an improvement being a value below the best so far by more than
    ``min_delta`` (in the loss's own units; with ``relative: true`` a fraction of the best value,
    so one rule suits losses of any scale: 0.001 is 0.1 %); a non-finite value also ends it.
    ``train.epochs`` stays the maximum. The weights kept are those of the last epoch trained (not
    the best one).
    """

    patience: int = 10
    min_delta: float = 0.0
    monitor: str = "val_loss"
    relative: bool = False

    def __post_init__(self):
        if isinstance(self.patience, bool) or not isinstance(self.patience, int) or self.patience < 1:
            raise RecipeError(f"train.early_stopping.patience: expected an integer >= 1, got {self.patience!r}")
        if isinstance(self.min_delta, bool) or not isinstance(self.min_delta, (int, float)) or not self.min_delta >= 0:
            raise RecipeError(f"train.early_stopping.min_delta: expected a number >= 0, got {self.min_delta!r}")
        if not isinstance(self.monitor, str) or not self.monitor:
            raise RecipeError(f"train.early_stopping.monitor: expected a logged metric's name, got {self.monitor!r}")
        if not isinstance(self.relative, bool):
            raise RecipeError(f"train.early_stopping.relative: expected true or false, got {self.relative!r}")
        self.min_delta = float(self.min_delta)


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
    #: the stopping rule on validation loss (``{patience, min_delta, monitor}``); None: train ``epochs``
    early_stopping: EarlyStopping | None = None

    def __post_init__(self):
        if isinstance(self.early_stopping, dict):  # `ctx.train.replace(early_stopping={...})`, a model's overrides
            names = [f.name for f in dataclasses.fields(EarlyStopping)]
            bad = [k for k in self.early_stopping if k not in names]
            if bad:
                raise RecipeError(f"train.early_stopping.{bad[0]}: unknown setting{did_you_mean(bad[0], names)}")
            self.early_stopping = EarlyStopping(**self.early_stopping)
        elif self.early_stopping is not None and not isinstance(self.early_stopping, EarlyStopping):
            raise RecipeError(f"train.early_stopping: expected a mapping {{patience, min_delta, monitor, relative}} or null, "
                              f"got {self.early_stopping!r}")
        checks = [("epochs", self.epochs >= 1), ("batch_size", self.batch_size >= 1), ("lr", self.lr > 0),
                  ("lr_decay", 0 < self.lr_decay <= 1), ("kl_weight", self.kl_weight >= 0),
                  ("keep_checkpoints", self.keep_checkpoints >= 1), ("num_workers", self.num_workers >= 0)]
        for key, ok in checks:
            if not ok:
                raise RecipeError(f"train.{key}: invalid value {getattr(self, key)!r}")

    def replace(self, **overrides) -> "TrainConfig":
        """A copy with ``overrides`` (training setting -> value), validated like a recipe's."""
        names = [f.name for f in dataclasses.fields(self)]
        bad = [k for k in overrides if k not in names]
        if bad:
            raise RecipeError(f"train.{bad[0]}: unknown training setting{did_you_mean(bad[0], names)}")
        return dataclasses.replace(self, **overrides)
