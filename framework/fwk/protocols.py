"""The typing.Protocol of every kind of component. The docstrings here are the reference.

Conventions: geometry in float64 NumPy, training in float32 torch, batches are (b, n, c).
Every component is constructed from its recipe section: ``Cls(**params)``; the constructor
signature is the recipe schema (``fwk show KIND NAME`` prints it). Nested components arrive as
``fwk.recipes.Spec`` objects (``spec.name``, ``spec.params``, ``spec.build(*args, **extra)``).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from .cache import Cache
    from .data import MeshCollection, Template
    from .runs import RunContext


@runtime_checkable
class Dataset(Protocol):
    name: str

    def load(self, cache: "Cache") -> "MeshCollection":
        """Load every subject and shape, in the dataset's own units (no preprocessing)."""


@runtime_checkable
class Representation(Protocol):
    """Encodes (b, n, 3) positions to (b, n, channels) features and back; fitted on train.

    ``ref`` is the reference shape(s) a relative representation is taken against: (n, 3) or
    (b, n, 3); ``None`` means the representation's own fitted reference (e.g. the train mean).
    """

    name: str
    channels: int

    def fit(self, P: np.ndarray, ref: np.ndarray | None, template: "Template") -> None: ...
    def encode(self, P: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
        """(b, n, 3) float64 -> (b, n, c) float32, scaled (std / norm / none)."""
    def decode(self, F: np.ndarray, ref: np.ndarray | None = None, target: np.ndarray | None = None) -> np.ndarray:
        """Inverse of encode: (b, n, c) -> (b, n, 3) float64. ``target`` (optional ground truth)
        places representations that lose position (dr) by rigid registration onto it."""
    def unscale(self, F: "torch.Tensor") -> "torch.Tensor":
        """Differentiable: undo std / norm (the loss space of thesis table 3.2)."""
    def state_dict(self) -> dict: ...
    def load_state_dict(self, d: dict) -> None: ...


@dataclass
class Level:
    """One graph level of a hierarchy."""

    n_vertices: int
    edges: np.ndarray                      # (e, 2) int64 undirected edges, i < j
    faces: np.ndarray | None = None        # (m, 3) triangles where the level is a mesh
    vertices: np.ndarray | None = None     # (n, 3) positions on the template where defined
    extra: dict[str, Any] = field(default_factory=dict)  # sampler-specific (neighbourhoods, ...)


@dataclass
class Hierarchy:
    """levels[0] is the template; down[i]: level i -> i+1, up[i]: level i+1 -> i.

    down[i] and up[i] are scipy.sparse CSR matrices of shape (n_{i+1}, n_i) and (n_i, n_{i+1}).
    """

    levels: list[Level]
    down: list[Any]
    up: list[Any]


@runtime_checkable
class Sampler(Protocol):
    name: str

    def build(self, template: "Template", cache: "Cache | None" = None) -> Hierarchy: ...


class Conv(Protocol):
    """A graph convolution: ``Cls(in_channels, out_channels, hierarchy, level, **params)`` is a
    torch.nn.Module mapping (b, n_level, c_in) -> (b, n_level, c_out). The class lists the
    arguments the model supplies in ``build_args`` so that recipes only give ``**params``."""

    name: str
    build_args: tuple = ("in_channels", "out_channels", "hierarchy", "level")


@runtime_checkable
class Metric(Protocol):
    name: str
    units: str  # e.g. "input" (the mesh's units), "input^2", "rad", "1"

    def __call__(self, pred: np.ndarray, target: np.ndarray, template: "Template") -> tuple[np.ndarray, np.ndarray]:
        """(b, n, 3) x2 -> per-mesh scores (b,) and per-vertex maps (b, n), float64."""


@runtime_checkable
class Assembler(Protocol):
    name: str

    def fit(self, template: "Template", mean: np.ndarray) -> None: ...
    def split(self, P: np.ndarray) -> list[np.ndarray]:
        """(b, n, 3) -> bands, each (b, n, 3) and centred on the mean as in DESIGN.md (band_j - mean
        sum to P - mean), so that ``assemble(split(P)) == P`` exactly."""
    def assemble(self, bands: list[np.ndarray]) -> np.ndarray: ...


@runtime_checkable
class Model(Protocol):
    """Learns from a collection. Two families share this protocol:

    * reconstruction models (pca, mlp-vae, ae, vae, dsm): ``task_family = "reconstruct"``;
      ``fit(data, ctx)`` learns from ``data.train`` shapes, ``reconstruct(P)`` maps (b, n, 3)
      positions in the evaluation space to their reconstruction; ``encode``/``decode``/``sample``
      where meaningful;
    * blendshape models (pb, pbs, dt): ``task_family = "blendshapes"``; ``fit(data, ctx)`` learns
      neutral -> expression; ``predict(neutrals, expression)`` maps (b, n, 3) neutrals to that
      expression.

    ``state_dict()`` / ``load_state_dict()`` save and restore everything ``reconstruct`` /
    ``predict`` needs (fwk stores it in the run directory).
    """

    name: str
    task_family: str

    def fit(self, data: "FitData", ctx: "RunContext") -> None: ...


@dataclass
class FitData:
    """What a model learns from, already preprocessed into the evaluation space.

    template  topology, with the mean training neutral as ``vertices``
    train/val MeshCollections of the split (positions in the evaluation space)
    shapes    the shape names a reconstruction model learns from (default ``["neutral"]``)
    """

    template: "Template"
    train: "MeshCollection"
    val: "MeshCollection"
    shapes: list[str] = field(default_factory=lambda: ["neutral"])

    def stack(self, which: str = "train") -> np.ndarray:
        """(b, n, 3) every present shape of ``shapes`` of every subject of a split."""
        col = self.train if which == "train" else self.val
        out = []
        for s in self.shapes:
            j = col.shape_index(s)
            out.append(np.asarray(col.positions[col.present[:, j], j]))
        return np.concatenate(out, axis=0) if out else np.zeros((0, self.template.n_vertices, 3))


class Task(Protocol):
    """What ``fwk run`` does. Its constructor's parameters are the recipe's top-level keys."""

    name: str

    def run(self, ctx: "RunContext") -> None: ...
