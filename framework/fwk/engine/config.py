"""``TrainConfig``: the recipe's ``train:`` section.

This module imports neither torch nor Lightning: ``fwk.recipes`` and ``fwk.runs`` (loaded by
``fwk list`` and ``fwk --help``) validate recipes with it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import RecipeError, quote
from ..registry import did_you_mean

#: ``train.accelerator``: Lightning's accelerators
ACCELERATORS = ("auto", "cpu", "gpu", "cuda", "mps", "tpu")
#: ``train.precision``: Lightning's precisions
PRECISIONS = ("32-true", "32", "64-true", "64", "16-mixed", "16-true", "16", "bf16-mixed", "bf16-true", "bf16")
#: ``train.strategy``: Lightning's default, fwk's DDP launcher (fwk.engine.distributed), one device
STRATEGIES = ("auto", "ddp", "single_device")
#: the most devices (``train.devices``) and data-loading workers one training may ask for
MAX_DEVICES = 1024
MAX_WORKERS = 1024
#: the most epochs (and epoch checkpoints) a training may ask for
MAX_EPOCHS = 10**7
#: the largest batch and logging interval (int32: what the data loaders index with)
MAX_COUNT = 2**31 - 1


def _number(key: str, value, low: float, high: float = math.inf, low_open: bool = False) -> float:
    """``value`` as a float when it is a finite number in [low, high] (``(low, high]`` with
    ``low_open``); else a RecipeError naming ``train.<key>`` and the range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise RecipeError(f"train.{key}: expected a number, got {type(value).__name__} {quote(value)}")
    try:
        x = float(value)
    except OverflowError:
        raise RecipeError(f"train.{key}: {quote(value)} is out of range") from None
    if not math.isfinite(x):
        raise RecipeError(f"train.{key}: expected a finite number, got {x}")
    if x < low or (low_open and x == low) or x > high:
        lo = f"> {low:g}" if low_open else f">= {low:g}"
        hi = "" if high == math.inf else f" and <= {high:g}"
        raise RecipeError(f"train.{key}: {x:g} is out of range (expected {lo}{hi})")
    return x


def _integer(key: str, value, low: int, high: int) -> int:
    """``value`` when it is an integer in [low, high]; else a RecipeError naming ``train.<key>``."""
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise RecipeError(f"train.{key}: expected an integer, got {type(value).__name__} {quote(value)}")
    if not low <= value <= high:
        raise RecipeError(f"train.{key}: {quote(value)} is out of range (expected {low} to {high})")
    return value


def _choice(key: str, value, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise RecipeError(f"train.{key}: {quote(value)} is not one of {', '.join(choices)}")
    return value


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
        self.patience = _integer("early_stopping.patience", self.patience, 1, MAX_EPOCHS)
        self.min_delta = _number("early_stopping.min_delta", self.min_delta, 0.0)
        if not isinstance(self.monitor, str) or not self.monitor or len(self.monitor) > 200:
            raise RecipeError(f"train.early_stopping.monitor: expected a logged metric's name, got {quote(self.monitor)}")
        if not isinstance(self.relative, bool):
            raise RecipeError(f"train.early_stopping.relative: expected true or false, got {quote(self.relative)}")


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
    #: fit a run's models side by side, one forked process each, on CPU (fwk.sidebyside)
    side_by_side: bool = True
    #: the stopping rule on validation loss (``{patience, min_delta, monitor}``); None: train ``epochs``
    early_stopping: EarlyStopping | None = None

    def __post_init__(self):
        if isinstance(self.early_stopping, dict):  # `ctx.train.replace(early_stopping={...})`, a model's overrides
            names = [f.name for f in dataclasses.fields(EarlyStopping)]
            bad = [k for k in self.early_stopping if k not in names]
            if bad:
                raise RecipeError(f"train.early_stopping.{str(bad[0])[:200]}: unknown setting{did_you_mean(bad[0], names)}")
            self.early_stopping = EarlyStopping(**self.early_stopping)
        elif self.early_stopping is not None and not isinstance(self.early_stopping, EarlyStopping):
            raise RecipeError(f"train.early_stopping: expected a mapping {{patience, min_delta, monitor, relative}} or null, "
                              f"got {quote(self.early_stopping)}")
        if not isinstance(self.side_by_side, bool):
            raise RecipeError(f"train.side_by_side: expected true or false, got {quote(self.side_by_side)}")
        # every setting checked here, so that `replace` (a model's overrides) is checked like a recipe
        self.epochs = _integer("epochs", self.epochs, 1, MAX_EPOCHS)
        self.batch_size = _integer("batch_size", self.batch_size, 1, MAX_COUNT)
        self.lr = _number("lr", self.lr, 0.0, 10.0, low_open=True)
        self.lr_decay = _number("lr_decay", self.lr_decay, 0.0, 1.0, low_open=True)
        self.kl_weight = _number("kl_weight", self.kl_weight, 0.0)
        self.weight_decay = _number("weight_decay", self.weight_decay, 0.0)
        self.keep_checkpoints = _integer("keep_checkpoints", self.keep_checkpoints, 1, MAX_EPOCHS)
        self.num_workers = _integer("num_workers", self.num_workers, 0, MAX_WORKERS)
        self.log_every_n_steps = _integer("log_every_n_steps", self.log_every_n_steps, 1, MAX_COUNT)
        self.accelerator = _choice("accelerator", self.accelerator, ACCELERATORS)
        self.precision = _choice("precision", self.precision, PRECISIONS)
        self.strategy = _choice("strategy", self.strategy, STRATEGIES)
        d = self.devices
        if isinstance(d, str) and d.strip().lstrip("-").isdigit():
            d = int(d)
        if isinstance(d, str):
            if d != "auto" and not all(p.strip().isdigit() for p in d.split(",")):
                raise RecipeError(f"train.devices: {quote(d)} is not a device count, auto, or a list of device "
                                  f"numbers such as \"0,1\"")
        elif d != -1:
            d = _integer("devices", d, 1, MAX_DEVICES)
        self.devices = d

    def replace(self, **overrides) -> "TrainConfig":
        """A copy with ``overrides`` (training setting -> value), validated like a recipe's."""
        names = [f.name for f in dataclasses.fields(self)]
        bad = [k for k in overrides if k not in names]
        if bad:
            raise RecipeError(f"train.{bad[0]}: unknown training setting{did_you_mean(bad[0], names)}")
        return dataclasses.replace(self, **overrides)
