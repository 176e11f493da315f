"""The roles components play, as runtime-checkable protocols. The docstrings here are the reference.

Every call that one part of fwk makes on another is declared here; a caller that needs a role
checks it with ``isinstance(obj, Role)`` (or ``issubclass(cls, Role)`` for method-only roles,
or the role's class attribute where a protocol cannot tell, e.g. ``Conv.strided``), never with
``hasattr``, ``inspect.signature`` or ``except TypeError``. ``fwk.testing`` has a contract
suite for every role; every built-in passes the suites of the roles it plays.

Conventions: geometry in float64 NumPy, training in float32 torch, batches are (b, n, c).
Every component is constructed from its recipe section: ``Cls(**params)``; the constructor
signature is the recipe schema (``fwk show KIND NAME`` prints it). Nested components arrive as
``fwk.recipes.Spec`` objects (``spec.name``, ``spec.params``, ``spec.build(*args, **extra)``);
a component that needs another (a model its representation, its assembler) takes it as a
recipe parameter with a default, never by looking a name up in the registry.

Roles by kind (``fwk list`` kinds on the left):

=============== ==========================================================================
dataset         :class:`Dataset`
representation  :class:`Representation`
sampler         :class:`Sampler` (builds a :class:`Hierarchy` of :class:`Level` s)
conv            :class:`Conv`; with ``strided = True`` also the strided / transposed role;
                optionally :class:`FusedPoolingConv` (computes a pooling or up-sampling with itself)
model           :class:`Model`, and one family: :class:`ReconstructionModel` or
                :class:`BlendshapeModel`; optionally :class:`GenerativeModel`,
                :class:`BandModel` (latent split by frequency band), :class:`NetworkFactory`
                (lends its encoder / decoder to other models), :class:`CutSelectingModel`
                (chooses a spectral cut on validation), :class:`CompositeModel` (reports
                its parts alone), :class:`TrainingModes` (end-to-end or two-step);
                any component: :class:`Described` (one line for a report's legend)
metric          :class:`Metric` (carries its display scale, unit and label)
assembler       :class:`Assembler`
task            :class:`Task`
=============== ==========================================================================
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:  # pragma: no cover
    import torch

    from .cache import Cache
    from .data import MeshCollection, Template
    from .runs import RunContext

#: The two model families; a task accepts the models of its own family only.
RECONSTRUCT = "reconstruct"  # name-ok: a model family (the task of this name trains it)
BLENDSHAPES = "blendshapes"  # name-ok: a model family (the task of this name trains it)
FAMILIES = (RECONSTRUCT, BLENDSHAPES)


# ----------------------------------------------------------------------------- data

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
    ``relative`` (class or instance attribute) says whether features are taken against ``ref``
    (an offset from it) rather than absolutely; ``places_rigidly`` whether ``decode`` loses the
    rigid placement (dr: positions come out up to a rigid motion and are placed onto ``target``).
    """

    name: str
    channels: int
    places_rigidly: bool
    relative: bool          # features taken against ``ref`` (an offset / a deformation from it)
    relative_option: bool   # class attribute: the constructor takes ``relative`` (else fixed)
    scaler: Any             # the fwk.scaling.Scaler that ``encode`` applies last (its settings are
                            # read by models that re-scale groups of features: pb per expression)

    def fit(self, P: np.ndarray, ref: np.ndarray | None, template: "Template") -> None: ...
    def encode(self, P: np.ndarray, ref: np.ndarray | None = None) -> np.ndarray:
        """(b, n, 3) float64 -> (b, n, c) float32, scaled (std / norm / none)."""
    def decode(self, F: np.ndarray, ref: np.ndarray | None = None, target: np.ndarray | None = None) -> np.ndarray:
        """Inverse of encode: (b, n, c) -> (b, n, 3) float64. ``target`` (optional ground truth)
        places representations that lose position (dr) by rigid registration onto it."""
    def unscale(self, F: "torch.Tensor") -> "torch.Tensor":
        """Differentiable: undo std / norm (the loss space of thesis table 3.2)."""
    def state_dict(self) -> dict: ...
    def load_state_dict(self, d: dict, ctx: "RunContext | None" = None) -> None: ...


# ----------------------------------------------------------------------------- graphs

@dataclass
class Neighbourhood:
    """Padded neighbour lists of one level's vertices: ``index`` (n, k) int64 into the source
    level, ``mask`` (n, k) bool (False where padded). Row i lists the support of vertex i."""

    index: np.ndarray
    mask: np.ndarray


@dataclass
class Level:
    """One graph level of a hierarchy.

    The optional neighbourhoods are the supports a sampler may define for strided convolutions
    (``Conv.strided``); a conv falls back to ``Hierarchy.down`` / ``up`` and hop distances where
    they are absent:

    conv     this level's own convolution support (stride 1)
    pool     for each vertex of this level, its support on the level above (finer): the
             strided convolution level l -> l + 1 reads ``levels[l + 1].pool``
    unpool   for each vertex of this level, its support on the level below (coarser): the
             transposed convolution l + 1 -> l reads ``levels[l].unpool``
    centres  (n,) indices of this level's vertices on the level above, where they are a subset
    """

    n_vertices: int
    edges: np.ndarray                      # (e, 2) int64 undirected edges, i < j
    faces: np.ndarray | None = None        # (m, 3) triangles where the level is a mesh
    vertices: np.ndarray | None = None     # (n, 3) positions on the template where defined
    conv: Neighbourhood | None = None
    pool: Neighbourhood | None = None
    unpool: Neighbourhood | None = None
    centres: np.ndarray | None = None


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


@runtime_checkable
class Conv(Protocol):
    """A graph convolution: a ``torch.nn.Module``,
    ``Cls(in_channels, out_channels, hierarchy, level, **params)``, mapping
    (b, n_level, c_in) -> (b, n_level, c_out). The model supplies the four ``build_args``; a
    recipe gives only ``**params``. ``reset_parameters()`` re-draws the weights (PyG's
    convention).

    **Strided role** (``strided = True``): the class also accepts ``mode``,
    ``residual_rate`` and ``activation``, supplied by the model (its ``build_args`` are
    ``CONV_BUILD_ARGS + STRIDED_BUILD_ARGS``, so a recipe cannot set them): ``mode="down"`` maps level l -> l + 1
    ((b, n_l, c_in) -> (b, n_{l+1}, c_out)), ``mode="up"`` maps level l + 1 -> l,
    ``mode="same"`` is the plain convolution; ``activation`` (a ``torch.nn.Module`` or None
    for the identity, supplied by the model, not a recipe key) acts on the conv branch, and
    ``residual_rate`` r (or None) mixes the residual in after it, as the thesis (4.4.3) and
    Zhou et al.'s reference compute a block:
    y = sqrt(1 - r) act(conv(x)) + sqrt(r) res(x) (y = act(conv(x)) without r; no activation
    after the mix). A model that needs strided convolutions (``ae fully_convolutional``)
    composes a conv without this role with the sampler's pooling instead, the same block
    (see ``fwk_autoencoder.strided``).
    """

    name: ClassVar[str]
    build_args: ClassVar[tuple]
    strided: ClassVar[bool]

    def forward(self, x: "torch.Tensor") -> "torch.Tensor": ...
    def reset_parameters(self) -> None: ...


@runtime_checkable
class UpgradesSavedTensors(Protocol):
    """Optional role of any module: its parameters' layout changed between versions, and it reads
    the old one. ``upgrade(name, t)`` returns the saved tensor ``t`` of its own parameter ``name``
    (the parameter itself, or an optimiser state of the parameter's shape) in today's layout, and
    ``t`` unchanged when it already is. The module applies it to its ``load_state_dict``; fwk's
    trainer applies it to the optimiser states of a checkpoint it resumes
    (``fwk.engine.upgrade_optimizer_states``), so a training started with an earlier version
    continues."""

    def upgrade(self, name: str, t: "torch.Tensor") -> "torch.Tensor": ...


@runtime_checkable
class FusedPoolingConv(Protocol):
    """Optional conv role: the conv fuses a pooling that keeps a vertex subset, and an
    up-sampling, into itself (``fuses_pooling = True``), with the same maths and less work:

    - ``forward(x, rows=m)``: (b, n, c_in) -> (b, len(m), c_out), equal to ``forward(x)[:, m]``
      but computed only at the rows m (an encoder whose pooling D selects one vertex per row,
      D[i, m_i] = 1, computes pool(act(conv(x))) as act(conv(x, rows=m)));
    - ``forward_up(x, up)``: (b, n_coarse, c_in) -> (b, n, c_out), equal to ``forward(up @ x)``
      for a sparse up-sampling ``up`` (n, n_coarse) without forming ``up @ x``.

    Equal up to float rounding (the sums run in another order); gradients too. A model uses it
    where it is played and ``fuses_pooling`` is True, and pools then convolves otherwise
    (``fwk.testing.conv.ConvContract`` checks both equalities, values and gradients).
    """

    fuses_pooling: ClassVar[bool]

    def forward(self, x: "torch.Tensor", rows: "torch.Tensor | None" = None) -> "torch.Tensor": ...
    def forward_up(self, x: "torch.Tensor", up: "torch.Tensor") -> "torch.Tensor": ...


@runtime_checkable
class ChecksData(Protocol):
    """Optional model role: ``check_data(data)`` raises a ``RecipeError`` when a recipe value
    is impossible for this data (e.g. pca's ``n_components`` above what the training set
    carries), before any model of the run trains (``fwk.lifecycle.build_models``)."""

    def check_data(self, data: "FitData") -> None: ...


CONV_BUILD_ARGS = ("in_channels", "out_channels", "hierarchy", "level")
#: what a model supplies besides to a conv playing the strided role; with CONV_BUILD_ARGS its
#: ``build_args``, so that a recipe cannot set them (recipe validation refuses them)
STRIDED_BUILD_ARGS = ("mode", "residual_rate", "activation")


# ----------------------------------------------------------------------------- metrics, assemblers

@runtime_checkable
class Metric(Protocol):
    """A per-mesh score and per-vertex map, lower is better.

    Class attributes say how reports show it: ``label`` (column header, e.g. "L1 norm"),
    ``display_scale`` (tables show value / display_scale, e.g. 1e-3 for the thesis's L1),
    ``units`` ("input": the mesh's units, "input^2", "rad", "1"), ``power`` (values in the
    dataset's units are value / scale**power), and ``default`` (part of the default metric
    list of evaluating tasks, in ``default_rank`` order).
    """

    name: str
    label: str
    units: str
    display_scale: float
    power: int
    default: bool
    default_rank: int

    def __call__(self, pred: np.ndarray, target: np.ndarray, template: "Template") -> tuple[np.ndarray, np.ndarray]:
        """(b, n, 3) x2 -> per-mesh scores (b,) and per-vertex maps (b, n), float64."""


@runtime_checkable
class Assembler(Protocol):
    """Splits a mesh into frequency bands on a template and assembles bands back.

    The models that take an ``assembler:`` build it with the cut(s) they need, overriding the
    recipe's keys: ``dsm`` with ``spec.build(k=<its k>, mass=<its mass>)``, ``pbs`` with
    ``spec.build(k=<the largest cut of its sweep>)``; so a constructor takes ``k`` (an int or a
    list of increasing cuts, one per boundary between bands) and ``mass`` (bool: the mass-weighted
    inner product), and gives what they mean for its own split (``docs/writing-a-plugin.md``).
    A model keeps what it built the assembler with in its own state; ``state_dict`` holds the
    assembler's fitted operators, plain data or arrays (``fwk.safeio``).
    """

    name: str

    def fit(self, template: "Template", mean: np.ndarray, cache: "Cache | None" = None) -> None: ...
    def split(self, P: np.ndarray) -> list[np.ndarray]:
        """(b, n, 3) -> bands, each (b, n, 3) and centred on the mean as in DESIGN.md (band_j - mean
        sum to P - mean), so that ``assemble(split(P)) == P`` exactly."""
    def assemble(self, bands: list[np.ndarray]) -> np.ndarray: ...
    def band_shares(self, D: np.ndarray) -> np.ndarray:
        """(b, n, 3) displacements -> (b, bands): each band's share of the M-weighted energy."""
    def assemble_many(self, bands: list[np.ndarray], ks: list[int]) -> np.ndarray:
        """Two bands [low source, high source], each (b, n, 3), assembled at every cut k of
        ``ks``: (len(ks), b, n, 3), the low frequencies below cut k of the first (spectral: the
        k smallest eigenvectors) and the rest of the second; one factorisation for all k."""
    def state_dict(self) -> dict: ...
    def load_state_dict(self, d: dict, ctx: "RunContext | None" = None) -> None: ...


# ----------------------------------------------------------------------------- models

@runtime_checkable
class Model(Protocol):
    """Learns from a collection; everything a run stores and reopens.

    ``task_family`` is ``"reconstruct"`` or ``"blendshapes"``. ``state_dict()`` /
    ``load_state_dict(d, ctx=None)`` save and restore everything inference needs (fwk stores it
    as ``models/<label>.safetensors``); ``ctx`` lends the run's cache to graph hierarchies and the like.
    """

    name: str
    task_family: str

    def fit(self, data: "FitData", ctx: "RunContext") -> None: ...
    def state_dict(self) -> dict: ...
    def load_state_dict(self, d: dict, ctx: "RunContext | None" = None) -> None: ...


@runtime_checkable
class ReconstructionModel(Model, Protocol):
    """``task_family = "reconstruct"`` (pca, mlp-vae, ae, vae, dsm): ``fit`` learns from the
    ``data.shapes`` of the training subjects; ``reconstruct(P)`` maps (b, n, 3) positions in the
    evaluation space to their reconstruction."""

    def reconstruct(self, P: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class GenerativeModel(Protocol):
    """A model with a latent space and a prior: ``encode`` (b, n, 3) -> (b, latent_size) (the
    mean code), ``decode`` back to positions, ``sample(n, seed)`` decodes draws from N(0, I)
    (deterministic for a seed). ``fwk sample`` uses any model playing this role."""

    latent_size: int

    def encode(self, P: np.ndarray) -> np.ndarray: ...
    def decode(self, Z: np.ndarray) -> np.ndarray: ...
    def sample(self, n: int, seed: int = 0) -> np.ndarray: ...


@runtime_checkable
class BandModel(GenerativeModel, Protocol):
    """A generative model whose latent code is split by frequency band (Deep Spectral Meshes):
    ``band_names`` (low to high), ``latent_slice(band)`` the part of Z that band owns,
    ``split(P)`` the bands of a mesh (its assembler's), ``assemble(bands)`` its inverse,
    ``decode_bands(Z)`` each band decoded alone, ``band_shares(D)`` each band's share of a
    displacement's energy. The ``edit`` and ``interpolate`` tasks work on every model playing
    this role."""

    band_names: list[str]

    def latent_slice(self, band: "str | int") -> slice: ...
    def split(self, P: np.ndarray) -> list[np.ndarray]: ...
    def assemble(self, bands: list[np.ndarray]) -> np.ndarray: ...
    def decode_bands(self, Z: np.ndarray) -> list[np.ndarray]: ...
    def band_shares(self, D: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class NetworkFactory(Protocol):
    """Lends its networks to other models (pb, pbs and dsm take ``network:``).

    ``build_encoder(template, in_channels, ctx=None)`` returns a module (b, n, c_in) ->
    (mu (b, latent_size), logvar or None); ``variational`` says whether the encoder returns a
    log-variance. A code may be a latent *map*: n_latent latent vertices x c channels,
    flattened vertex-major (entry v c + j is channel j of latent vertex v); a flat code is
    one latent vertex.

    ``build_decoder(template, out_channels, ctx=None, latent_in=None, latent_parts=None)``
    returns a module (b, d) -> (b, n, c_out) reading

    * its own code (d = latent_size), by default;
    * ``latent_parts = [d_0, d_1, ...]``: Z = [z_0 | z_1 | ...], codes of networks with this
      one's latent layout (d = sum d_j), read as one (b, n_latent, sum_j d_j / n_latent) map,
      the codes' channels concatenated per latent vertex, by the first (transposed)
      convolution: no dense layer where the code is a map (Deep Spectral Meshes, thesis 4.4.2);
      a part that is not a whole number of latent vertices is an error;
    * ``latent_in``: a foreign flat code of d entries (e.g. a code with a one-hot condition),
      through a linear layer first.
    """

    latent_size: int
    variational: bool

    def build_encoder(self, template: "Template", in_channels: int, ctx: "RunContext | None" = None): ...
    def build_decoder(self, template: "Template", out_channels: int, ctx: "RunContext | None" = None,
                      latent_in: int | None = None, latent_parts: list[int] | None = None): ...


@runtime_checkable
class BlendshapeModel(Model, Protocol):
    """``task_family = "blendshapes"`` (pb, pbs, dt): ``fit`` learns neutral -> expression for
    ``expressions`` (None before fit means: every expression the task gives);
    ``predict(neutrals, expression, target=None)`` maps (b, n, 3) neutrals to that expression.
    ``target`` (the ground truth, optional) is used only by models whose output loses its rigid
    placement (a dr network alone) to be scored as the thesis scores them; ``predict_all``
    predicts several expressions at once (a model may share work between them)."""

    expressions: list[str] | None

    def predict(self, neutrals: np.ndarray, expression: str, target: np.ndarray | None = None) -> np.ndarray: ...
    def predict_all(self, neutrals: np.ndarray, expressions: list[str],
                    target: dict | None = None) -> dict[str, np.ndarray]: ...


@runtime_checkable
class TrainingModes(Protocol):
    """A blendshape model trained ``end-to-end`` or ``two-step`` (pb, thesis 5.2.2), whose output
    representation does or does not lose the rigid placement (``places_rigidly``: dr). The
    blendshapes task's end-to-end against two-step table (thesis table 5.1) pairs the two modes
    of one kind of representation."""

    mode: str
    places_rigidly: bool


@runtime_checkable
class CompositeModel(Protocol):
    """A model made of parts that are models of their own (pbs: two PB networks): ``parts(
    neutrals, expression, target=None)`` returns {part label: prediction}; tasks report each
    part as its own row. ``part_models()`` returns {part label: the part as a model} (same labels),
    so a task can read the roles a part plays (pbs's parts are end-to-end PBs: ``TrainingModes``,
    paired with two-step PBs in thesis table 5.1)."""

    def parts(self, neutrals: np.ndarray, expression: str, target: np.ndarray | None = None) -> dict[str, np.ndarray]: ...
    def part_models(self) -> dict[str, Any]: ...


@runtime_checkable
class CutSelectingModel(Protocol):
    """A model that chooses a spectral cut per expression on validation (pbs): ``k`` {expression:
    chosen k} and ``sweep`` {expression: the sweep's scores, fronts and choice}, both reported."""

    k: dict
    sweep: dict


@runtime_checkable
class Packable(Protocol):
    """Optional role of a model: ``packed_state()`` is the state ``fwk pack`` ships (``fwk.pack``):
    what prediction needs, without what only training and reports read (a k sweep's curves, a
    basis larger than the cuts chosen). ``load_state_dict`` reads it back, and the model then
    predicts what it predicted before (to round-off; ``fwk pack`` measures the difference on the
    model's mean neutral). A model without this role is packed with its ``state_dict()``."""

    def packed_state(self) -> dict: ...


@runtime_checkable
class TruncatesCuts(Protocol):
    """Optional role of an assembler: ``truncated_state(k)`` is the state of the same fitted
    assembler built with the single cut k (at most its largest), which ``load_state_dict`` reads
    and which assembles two bands at every cut up to k exactly as before (a packed ``pbs`` keeps
    the basis up to its largest chosen k only)."""

    def truncated_state(self, k: int) -> dict: ...


@runtime_checkable
class Described(Protocol):
    """Optional role of any component: ``describe()`` says in one line what this instance is,
    with its parameters (dt with ``sources: 0``: "Deformation Transfer from training subject 0
    as the source"). Reports put it in their legend of model labels
    (``fwk.evaluation.legend``); a component without it is described by its class docstring's
    first line and its recipe parameters."""

    def describe(self) -> str: ...


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


@runtime_checkable
class Task(Protocol):
    """What ``fwk run`` does. Its constructor's parameters are the recipe's top-level keys."""

    name: str

    def run(self, ctx: "RunContext") -> None: ...


def role_members(role) -> list[str]:
    """The attribute and method names a protocol declares (its own and its protocol bases')."""
    names: list[str] = []
    for base in role.__mro__:
        if base in (object, Protocol) or not getattr(base, "_is_protocol", False):
            continue
        for n in [*getattr(base, "__annotations__", {}), *vars(base)]:
            if n.startswith("_") or n in names or n in ("__annotations__",):
                continue
            names.append(n)
    return names


def missing_members(cls: type, role) -> list[str]:
    """The members ``role`` declares that the class ``cls`` does not define, in the role's order
    (what recipe validation names when a component does not play its role). This is the one place
    where members are looked up by name."""
    return [n for n in role_members(role) if not hasattr(cls, n)]  # justified: the role check on classes


def plays(obj, role) -> bool:
    """Whether a component (instance or class) plays ``role``: ``isinstance`` for instances; for
    a class (before it is built, e.g. a recipe's Spec.cls), whether it defines every member the
    role declares (``missing_members``)."""
    if isinstance(obj, type):
        return not missing_members(obj, role)
    return isinstance(obj, role)


#: The role every component of a kind plays: recipe validation refuses a component that does not
#: define every member of it, naming the missing ones (``fwk.recipes.make_spec``), before any data
#: loads. A parameter may ask for more (``Kind("model", BlendshapeModel)``).
KIND_ROLES = {"dataset": Dataset, "representation": Representation, "sampler": Sampler, "conv": Conv,
              "model": Model, "metric": Metric, "assembler": Assembler, "task": Task}
