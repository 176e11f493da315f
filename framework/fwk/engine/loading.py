"""Batches in an order that is a function of (seed, epoch): ``EpochSampler`` and ``make_loader``."""
from __future__ import annotations

import numpy as np
import torch


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
        """The epoch whose shuffle ``__iter__`` gives next."""
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


def fit_features(representation, data):
    """The first step of every model trained on one representation's features (ae, vae,
    mlp-vae): ``(rep, F, Fv)``, the representation built from its Spec and fitted on the
    training shapes of ``data`` (FitData), and the train / validation features as float32
    tensors (b, n, c) (``Fv`` None when the validation split is empty)."""
    P, V = data.stack("train"), data.stack("val")
    rep = representation.build()
    rep.fit(P, None, data.template)
    F = torch.as_tensor(rep.encode(P))
    Fv = torch.as_tensor(rep.encode(V)) if len(V) else None
    return rep, F, Fv
