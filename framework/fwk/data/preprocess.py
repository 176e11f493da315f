"""Preprocessing of thesis 3.3.8 / 5.2.1, every step kept with its inverse.

1. centring: each neutral is moved so its centroid is at the origin (eq. 3.6); the subject's
   expressions move with it (the same translation);
2. rigid registration: each centred neutral is rotated onto the mean of the centred training
   neutrals by Kabsch with the reflection fix (eqs. 3.2-3.5); the mean is recomputed and the
   registration repeated until the mean stops changing (``tol``) or ``iterations`` run out;
   a subject's expressions follow its neutral's rotation;
3. one uniform scale s for the whole dataset so every training coordinate lies in [-1, 1]
   (eq. 3.7): s = 1 / max |x|, shrunk by ``margin``.

Forward, per subject: X = s R (P - c). Inverse: P = R^T X / s + c. New neutrals (a user's head)
are registered to the fitted mean with the same steps (``transform_neutrals``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.kabsch import kabsch
from .split import split_subjects


@dataclass
class PreprocessConfig:
    """Which steps run (centring, rigid registration, scale), the registration's iterations and
    tolerance, and the margin of the scale."""

    centre: bool = True
    register: bool = True
    scale: bool = True
    iterations: int = 20
    tol: float = 1e-10
    margin: float = 0.0


@dataclass
class Transforms:
    """Per-subject rigid transforms and the dataset scale: X = scale * R (P - centre)."""

    rotation: np.ndarray  # (S, 3, 3)
    centre: np.ndarray  # (S, 3)
    scale: float

    def select(self, idx) -> "Transforms":
        """The transforms of the subjects ``idx``."""
        idx = np.asarray(idx)
        return Transforms(self.rotation[idx], self.centre[idx], self.scale)

    def __len__(self):
        return len(self.rotation)


class Preprocessor:
    """The fitted preprocessing (mean registered neutral and scale) and its application and inverse
    per subject."""

    def __init__(self, config: PreprocessConfig | None = None):
        self.config = config or PreprocessConfig()
        self.mean_centred: np.ndarray | None = None  # mean training neutral after centring and registration
        self.scale: float = 1.0

    # fitting ---------------------------------------------------------------------
    def _centre_rotate(self, N: np.ndarray, target: np.ndarray | None):
        c = N.mean(axis=1) if self.config.centre else np.zeros((len(N), 3))
        Nc = N - c[:, None]
        if self.config.register and target is not None:
            R, _ = kabsch(Nc, np.broadcast_to(target, Nc.shape))
            # Kabsch allows a translation; with both sides centred it is ~0 and we drop it
            # so that the transform stays a pure rotation about the centroid.
        else:
            R = np.broadcast_to(np.eye(3), (len(N), 3, 3)).copy()
        return R, c

    def fit(self, neutrals: np.ndarray, shapes: np.ndarray | None = None) -> "Preprocessor":
        """Fit on the training neutrals (S, n, 3); ``shapes`` (S, E, n, 3), all of the training
        subjects' shapes, make the scale cover the expressions too (NaN = missing shape)."""
        N = np.asarray(neutrals, dtype=np.float64)
        if N.ndim != 3 or N.shape[-1] != 3 or len(N) == 0:
            raise ValueError(f"Preprocessor.fit expects (S, n, 3) neutrals, got {N.shape}")
        c = N.mean(axis=1) if self.config.centre else np.zeros((len(N), 3))
        Nc = N - c[:, None]
        mean = Nc.mean(axis=0)
        if self.config.register:
            for _ in range(max(1, self.config.iterations)):
                R, _ = kabsch(Nc, np.broadcast_to(mean, Nc.shape))
                X = np.einsum("bij,bnj->bni", R, Nc)
                new = X.mean(axis=0)
                if self.config.centre:
                    new = new - new.mean(axis=0)
                delta = np.abs(new - mean).max()
                mean = new
                if delta < self.config.tol:
                    break
        self.mean_centred = mean
        X, T = self.transform_neutrals(N, _scale=1.0)
        if shapes is not None:
            X = self.apply(np.asarray(shapes, dtype=np.float64), T)
        if self.config.scale:
            m = np.nanmax(np.abs(X))
            self.scale = float((1.0 - self.config.margin) / m) if m > 0 else 1.0
        else:
            self.scale = 1.0
        return self

    # applying --------------------------------------------------------------------
    def transform_neutrals(self, N: np.ndarray, _scale: float | None = None):
        """(X, Transforms): neutrals (S, n, 3) or (n, 3) centred, registered to the fitted mean and
        scaled."""
        N = np.asarray(N, dtype=np.float64)
        single = N.ndim == 2
        if single:
            N = N[None]
        R, c = self._centre_rotate(N, self.mean_centred)
        s = self.scale if _scale is None else _scale
        X = s * np.einsum("bij,bnj->bni", R, N - c[:, None])
        T = Transforms(R, c, s)
        return (X[0], T) if single else (X, T)

    def transform(self, P: np.ndarray, neutrals: np.ndarray):
        """P (S, E, n, 3) or (S, n, 3), each subject moved by its neutral's transform."""
        _, T = self.transform_neutrals(neutrals)
        return self.apply(P, T), T

    def apply(self, P: np.ndarray, T: Transforms) -> np.ndarray:
        """Shapes P (S, E, n, 3) or (S, n, 3) moved by their subjects' transforms: X = s R (P - c)."""
        P = np.asarray(P, dtype=np.float64)
        if P.ndim == 4:
            return T.scale * np.einsum("sij,senj->seni", T.rotation, P - T.centre[:, None, None])
        return T.scale * np.einsum("sij,snj->sni", T.rotation, P - T.centre[:, None])

    def inverse(self, X: np.ndarray, T: Transforms) -> np.ndarray:
        """Back to input units: P = R^T X / s + c (per subject)."""
        X = np.asarray(X, dtype=np.float64)
        if X.ndim == 4:
            return np.einsum("sji,senj->seni", T.rotation, X / T.scale) + T.centre[:, None, None]
        return np.einsum("sji,snj->sni", T.rotation, X / T.scale) + T.centre[:, None]

    @property
    def mean_neutral(self) -> np.ndarray:
        """(n, 3) the mean training neutral in the evaluation space."""
        return self.scale * self.mean_centred

    # saving ----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The fitted state and configuration as NumPy values (saved as ``stats/preprocess.npz``)."""
        c = self.config
        return {"mean_centred": self.mean_centred, "scale": np.float64(self.scale),
                "config": np.array([c.centre, c.register, c.scale], dtype=bool),
                "iterations": np.int64(c.iterations), "tol": np.float64(c.tol), "margin": np.float64(c.margin)}

    def load_state_dict(self, d) -> "Preprocessor":
        """Restore the state written by ``state_dict``."""
        cfg = np.asarray(d["config"])
        self.config = PreprocessConfig(bool(cfg[0]), bool(cfg[1]), bool(cfg[2]), int(d["iterations"]),
                                       float(d["tol"]), float(d["margin"]))
        self.mean_centred = np.asarray(d["mean_centred"], dtype=np.float64)
        self.scale = float(d["scale"])
        return self

    @classmethod
    def from_state(cls, d) -> "Preprocessor":
        """A Preprocessor restored from ``state_dict``'s output."""
        return cls().load_state_dict(d)


def split_and_preprocess(collection, split_cfg, pre_cfg, seed: int, ctx, neutral: str = "neutral"):
    """What every task that trains on a collection does first: split by subject
    (``split.json``), fit the preprocessing on the training neutrals (``stats/preprocess.npz``)
    and apply it to each split, every shape of a subject moved with its neutral.

    Returns (split dict, Preprocessor, preprocessed collection per split, transforms per split).
    """
    split = split_subjects(collection.subjects, split_cfg, seed)
    ctx.write_json("split.json", split)
    index = {s: i for i, s in enumerate(collection.subjects)}
    j = collection.shape_index(neutral)
    tr = np.array([index[s] for s in split["train"]])
    pre = Preprocessor(pre_cfg).fit(np.asarray(collection.positions[tr, j]), np.asarray(collection.positions[tr]))
    ctx.save_npz("stats/preprocess.npz", **pre.state_dict())
    cols, transforms = {}, {}
    for name in ("train", "val", "test"):
        idx = np.array([index[s] for s in split[name]], dtype=np.int64)
        sub = collection.select(idx)
        X, T = pre.transform(np.asarray(sub.positions), np.asarray(sub.positions[:, j]))
        sub.positions = X
        cols[name], transforms[name] = sub, T
    return split, pre, cols, transforms
