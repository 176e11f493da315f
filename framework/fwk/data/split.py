"""Split subjects into train / val / test (85:5:10 by default), seeded and saved by the task.

All shapes of a subject go to the same split, so no identity is seen in training and tested.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import RecipeError


@dataclass
class SplitConfig:
    """ratios: train, val, test fractions (normalised); seed: None uses the recipe's seed."""

    ratios: list[float] = field(default_factory=lambda: [0.85, 0.05, 0.1])
    seed: int | None = None

    def __post_init__(self):
        r = [float(x) for x in self.ratios]
        if len(r) != 3 or any(x < 0 for x in r) or sum(r) <= 0:
            raise RecipeError(f"split.ratios: expected three non-negative fractions (train, val, test), got {self.ratios}")
        self.ratios = r


def split_subjects(subjects: list[str], config: SplitConfig | None = None, seed: int = 0) -> dict[str, list[str]]:
    """Seeded split by subject. With >= 3 subjects, val and test get at least one each
    when their ratio is positive; the remainder goes to train."""
    config = config or SplitConfig()
    r = np.asarray(config.ratios, dtype=np.float64)
    r = r / r.sum()
    n = len(subjects)
    if n == 0:
        raise RecipeError("split: the dataset has no subjects")
    rng = np.random.default_rng(config.seed if config.seed is not None else seed)
    order = rng.permutation(n)
    n_val = int(round(r[1] * n))
    n_test = int(round(r[2] * n))
    if n >= 3:
        n_val = max(n_val, 1 if r[1] > 0 else 0)
        n_test = max(n_test, 1 if r[2] > 0 else 0)
    n_val = min(n_val, max(n - 1 - n_test, 0))
    n_train = n - n_val - n_test
    if n_train < 1:
        raise RecipeError(f"split: {n} subjects leave none for training with ratios {config.ratios}")
    idx = {"train": order[:n_train], "val": order[n_train:n_train + n_val], "test": order[n_train + n_val:]}
    return {k: [subjects[i] for i in sorted(v)] for k, v in idx.items()}
