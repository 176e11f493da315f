"""Conv ``spiral``: the spiral convolution of Neural 3DMM (Bouritsas et al. 2019, "Neural 3D
Morphable Models: Spiral Convolutional Networks for 3D Shape Representation Learning and
Generation", ICCV; thesis 3.3, 3.4).

The features along a vertex's spiral S(i) are concatenated and mapped by one shared linear
layer (one gather and one matrix product for the whole batch):

    x'_i = W [x_{S(i,1)} || x_{S(i,2)} || ... || x_{S(i,L)}] + b

Unlike SpiralNet++ the spiral is *anchored*: the one-ring of vertex i starts at the next vertex
on the shortest (Euclidean edge-length) path from i to the reference vertex of i's connected
component (for the reference vertex itself: its closest neighbour), then runs round the fan
counter-clockwise; the following rings continue it (``fwk.graph.spiral_sequences``). A border
vertex whose fan is entered in the middle gets a -1 where the walk crosses the border, as in
the reference code. Per graph level (lists are indexed by the hierarchy level, the last entry
repeating):

* ``rings`` (Neural 3DMM's "step size"): how many rings the spiral covers, default
  [2, 2, 1, 1, 1];
* ``dilation``: keep the centre and every d-th entry after it, S[:1] + S[1::d], default
  [2, 2, 1, 1, 1] (thesis 3.4: the encoder's first two and the decoder's last two layers are
  dilated with step size 2 and dilation ratio 2);
* ``length``: the fixed spiral length L; None (default) takes int(mean + 2 std) of the level's
  natural spiral lengths, as the reference does. Shorter spirals are padded with -1, an index
  to a dummy vertex whose features are zero; longer ones are cut.

Reference vertices: ``reference`` lists template (level 0) vertex indices; each level uses the
vertex nearest to them in each component they lie in. Components without one (and every
component when ``reference`` is None) use their front-most vertex (largest z: the nose tip of a
face looking along +z). Meshes with several connected components get one reference each.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree
from torch import nn

from fwk.errors import RecipeError
from fwk.cache import content_key, memo
from fwk.graph import spiral_sequences, symmetric_adjacency
from fwk.hookspecs import hookimpl
from fwk.protocols import CONV_BUILD_ARGS


def _at(v, level: int):
    if isinstance(v, (list, tuple)):
        if not v:
            return None
        return v[min(level, len(v) - 1)]
    return v


def reference_vertices(lv, labels: np.ndarray, reference=None, template_vertices=None) -> list[int]:
    """One reference vertex per connected component of the level (see the module docstring)."""
    V = np.asarray(lv.vertices, dtype=np.float64) if lv.vertices is not None else np.zeros((lv.n_vertices, 3))
    refs = {}
    if reference is not None and len(reference) and template_vertices is not None:
        _, near = cKDTree(V).query(np.asarray(template_vertices)[np.asarray(reference, dtype=np.int64)])
        for v in np.atleast_1d(near):
            refs.setdefault(int(labels[v]), int(v))
    for c in range(labels.max() + 1 if len(labels) else 0):
        if c not in refs:
            members = np.flatnonzero(labels == c)
            refs[c] = int(members[np.argmax(V[members, 2])])
    return [refs[c] for c in sorted(refs)]


def anchored_spirals(lv, rings: int, dilation: int = 1, length: int | None = None,
                     reference=None, template_vertices=None) -> np.ndarray:
    """(n, L) Neural 3DMM spirals of a level, -1 where padded (see the module docstring);
    computed once per level and setting."""
    if lv.faces is None:
        raise RecipeError("conv spiral needs a sampler whose levels are triangle meshes (e.g. quadric)")
    V = np.asarray(lv.vertices, dtype=np.float64) if lv.vertices is not None else np.zeros((lv.n_vertices, 3))
    key = (lv.n_vertices, np.asarray(lv.faces, dtype=np.int64), V, rings, dilation, length,
           None if reference is None else tuple(reference),
           None if template_vertices is None or reference is None else np.asarray(template_vertices))
    return memo(f"{__name__}.spirals", content_key(*key),
                lambda: _anchored_spirals(lv, V, rings, dilation, length, reference, template_vertices))


def _anchored_spirals(lv, V, rings, dilation, length, reference, template_vertices) -> np.ndarray:
    n, e = lv.n_vertices, np.asarray(lv.edges, dtype=np.int64).reshape(-1, 2)
    w = np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1) + 1e-12  # zero-length edges still count
    W = symmetric_adjacency(e, n, weights=w)
    _, labels = connected_components(W, directed=False)
    refs = reference_vertices(lv, labels, reference, template_vertices)
    _, pred, _ = dijkstra(W, directed=False, indices=refs, return_predecessors=True, min_only=True)
    ref_set = set(refs)

    def first(v, ring):
        if v in ref_set or pred[v] < 0:  # the reference itself: its closest neighbour
            return min(ring, key=lambda u: (float(((V[u] - V[v]) ** 2).sum()), u))
        return int(pred[v])

    seqs = spiral_sequences(lv.faces, n, rings=rings, first=first, gap=-1)
    if dilation > 1:
        seqs = [s[:1] + s[1::dilation] for s in seqs]
    lens = np.array([len(s) for s in seqs], dtype=np.float64)
    L = int(length) if length is not None else max(1, int(lens.mean() + 2 * lens.std()))
    S = -np.ones((n, L), dtype=np.int64)
    for v, s in enumerate(seqs):
        s = s[:L]
        S[v, :len(s)] = s
    return S


class Spiral(nn.Module):
    r"""Neural 3DMM spiral convolution (reference-anchored spirals, -1 padding to a zero vertex).

    With S(i) = (s_1 = i, s_2, ..., s_L) the anchored spiral of vertex i (see the method below;
    a padded entry reads a dummy vertex whose features are zero):

        x'_i = W [x_{s_1} || x_{s_2} || ... || x_{s_L}] + b,    W in R^{c_out x L c_in}, b in R^{c_out}

    Args:
        in_channels (int): c_in, features of each input vertex.
        out_channels (int): c_out, features of each output vertex.
        hierarchy (fwk.protocols.Hierarchy): the sampler's hierarchy; the level must be a
            triangle mesh (``Level.faces``); level 0's positions place ``reference``.
        level (int): the level the convolution works on (stride 1).
        length (int, list or None): L per level; None: int(mean + 2 std) of the level's spirals.
        rings (int or list): rings a spiral covers per level (default [2, 2, 1, 1, 1]).
        dilation (int or list): keep the centre and every d-th entry after it, per level
            (default [2, 2, 1, 1, 1]).
        reference (list of int or None): template vertices that anchor the spirals (None: the
            front-most vertex, largest z, of each connected component).

    A list gives one entry per hierarchy level, the last entry repeating.

    Shapes:
        - **input:** (b, n, c_in), n = ``hierarchy.levels[level].n_vertices``
        - **output:** (b, n, c_out)

    ``reset_parameters()`` draws W Xavier-uniform and sets b = 0 (the constructor's
    ``torch.nn.Linear`` draws its own initialisation first, so the random stream is that of the
    reference implementation).
    """

    name = "spiral"
    build_args = CONV_BUILD_ARGS
    strided = False

    def __init__(self, in_channels: int, out_channels: int, hierarchy=None, level: int = 0,
                 length: int | list[int] | None = None, rings: int | list[int] = [2, 2, 1, 1, 1],  # noqa: B006
                 dilation: int | list[int] = [2, 2, 1, 1, 1], reference: list[int] | None = None):  # noqa: B006
        super().__init__()
        lv = hierarchy.levels[level]
        r, d, L = _at(rings, level), _at(dilation, level), _at(length, level)
        if r is None or r < 1:
            raise RecipeError(f"rings: at least 1 ring, got {rings}")
        if d is None or d < 1:
            raise RecipeError(f"dilation: at least 1, got {dilation}")
        if L is not None and L < 1:
            raise RecipeError(f"length: at least 1, got {length}")
        idx = anchored_spirals(lv, r, d, L, reference, hierarchy.levels[0].vertices)
        idx = np.where(idx < 0, lv.n_vertices, idx)  # the dummy vertex
        self.register_buffer("index", torch.as_tensor(idx.reshape(-1), dtype=torch.long))
        self.length = idx.shape[1]
        self.padded = bool((idx == lv.n_vertices).any())
        self.layer = nn.Linear(in_channels * self.length, out_channels)
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """W Xavier-uniform, b = 0."""
        nn.init.xavier_uniform_(self.layer.weight)
        nn.init.zeros_(self.layer.bias)

    def forward(self, x):
        b, n, c = x.shape
        if self.padded:
            x = torch.cat([x, x.new_zeros(b, 1, c)], dim=1)
        return self.layer(x[:, self.index].reshape(b, n, self.length * c))


@hookimpl
def fwk_register_convs():
    return [Spiral]
