"""Assembler ``spectral``: split a mesh into frequency bands and assemble bands back
(thesis 4.2.1, 4.2.3, 4.4.5, 5.3.3; eqs. 4.2, 4.11, 4.15, 5.10).

With L the cotangent Laplacian, M the Voronoi mass matrix and U the K smallest generalised
eigenvectors (L u = lambda M u, U^T M U = I) of the template (the training mean), and cut
points 0 = k_0 < k_1 < ... < k_B = K (``k: 500`` gives two bands, the thesis's; a list gives
more, as its future work proposes), let U_j = U[:, k_{j-1}:k_j] and X_j = U_j U_j^T M. For a
mesh P and the mean P-bar:

    band_j(P) = X_j (P - P-bar) + P-bar                        j < B      (eq. 4.11, low bands)
    band_B(P) = (I - X_1 - ... - X_{B-1}) (P - P-bar) + P-bar          (the high band)

which for two bands is P_low = U_k U_k^T M (P - P-bar) + P-bar and P_high = P - P_low + P-bar
(DESIGN.md). Assembly from per-band reconstructions P'_j (eq. 4.15 / 5.10) projects each onto
its own band and adds the mean once:

    P' = sum_{j<B} X_j (P'_j - P-bar) + (I - sum_{j<B} X_j)(P'_B - P-bar) + P-bar

so ``assemble(split(P)) == P`` exactly (to round-off). ``mass: false`` uses the un-weighted
basis (eq. 4.1, M = I). The n x n matrices X_j are never formed: everything is U (U^T (M P)),
one (n, 3b) block product for a batch. ``assemble_many([low, high], ks)`` assembles two bands
for many cut points k at once (the PBS k sweep, thesis 5.3.3) from cumulative coefficient sums;
``eigen_k`` computes a larger basis than the last cut so that such a sweep can reach further.
``project(P, j)`` is band j's part of P - mean; ``band_shares(D)`` the share of a displacement's
M-weighted energy in each band. A differentiable torch version for training-time
use is ``Spectral.torch()`` (``TorchSpectral``, built on ``fwk.geometry.spectral_torch``).

How the mean enters: every band is a mesh centred on the mean (band_j - mean is the band's
displacement), so each band can be fed to a representation and a model like any mesh; the
displacements of all bands sum to P - mean and assembly adds the mean back exactly once.
"""
from __future__ import annotations

import numpy as np
import torch

from fwk.cache import default_cache
from fwk.errors import RecipeError
from fwk.geometry.operators import mass_matrix
from fwk.geometry.spectral import SpectralProjector, eigenbasis
from fwk.geometry.spectral_torch import TorchSpectralProjector
from fwk.hookspecs import hookimpl


def _energy(D, m):
    """sum_n m_n |D_n|^2 over the vertices of (..., n, 3) (m = None: unweighted)."""
    w = np.ones(D.shape[-2]) if m is None else np.asarray(m).reshape(-1)
    return np.einsum("...ni,...ni,n->...", D, D, w)


class Spectral:
    """Spectral bands of the cotangent Laplacian (low / high frequencies, or more bands)."""

    name = "spectral"

    def __init__(self, k: int | list[int] = 500, mass: bool = True, eigen_k: int | None = None,
                 slice_size: int = 60):
        cuts = [k] if isinstance(k, int) else list(k)
        if not cuts or any(int(c) != c or c <= 0 for c in cuts) or cuts != sorted(set(cuts)):
            raise RecipeError(f"k: cut points must be positive increasing integers, got {k}")
        if eigen_k is not None and eigen_k < cuts[-1]:
            raise RecipeError(f"eigen_k: {eigen_k} is below the last cut point {cuts[-1]}")
        self.cuts, self.mass = [int(c) for c in cuts], bool(mass)
        self.eigen_k, self.slice_size = eigen_k, slice_size
        self.proj: SpectralProjector | None = None
        self.mean = None
        self.evals = None

    @property
    def n_bands(self) -> int:
        return len(self.cuts) + 1

    def fit(self, template, mean=None, cache=None) -> None:
        """Eigenbasis of the mean's geometry (``mean`` (n, 3); default the template's vertices),
        cached in ``cache`` (default: fwk's content-hash cache)."""
        n = template.n_vertices
        K = self.eigen_k or self.cuts[-1]
        if K > n:
            raise RecipeError(f"k: cut point {K} exceeds the template's {n} vertices")
        V = template.vertices if mean is None else np.asarray(mean, dtype=np.float64)
        if V.shape != (n, 3):
            raise RecipeError(f"mean: expected shape ({n}, 3), got {V.shape}")
        self.mean = V.copy()
        self.evals, U = eigenbasis(V, template.triangles, K, weighted=self.mass,
                                   cache=cache if cache is not None else default_cache(), slice_size=self.slice_size)
        m = mass_matrix(V, template.triangles).diagonal() if self.mass else None
        self.proj = SpectralProjector(U, m)

    def _ranges(self):
        edges = [0, *self.cuts]
        return [(edges[j], edges[j + 1]) for j in range(len(self.cuts))]

    def _check(self):
        if self.proj is None:
            raise RuntimeError("spectral assembler used before fit()")

    def split(self, P) -> list[np.ndarray]:
        """Bands of P (b, n, 3) or (n, 3), each centred on the mean: band_j - mean sum to P - mean."""
        self._check()
        D = np.asarray(P, dtype=np.float64) - self.mean
        bands, low_sum = [], 0.0
        for lo, hi in self._ranges():
            x = self.proj.project(D, lo, hi)
            bands.append(x + self.mean)
            low_sum = low_sum + x
        bands.append(D - low_sum + self.mean)
        return bands

    def assemble(self, bands) -> np.ndarray:
        """Eq. 4.15 / 5.10: each band contributes only its own eigen-slice, the mean is added once."""
        self._check()
        if len(bands) != self.n_bands:
            raise ValueError(f"assemble: {len(bands)} bands given, the assembler has {self.n_bands}")
        # sum_j X_j (b_j - mean) + (I - sum_j X_j)(b_B - mean) + mean = sum_j X_j (b_j - b_B) + b_B:
        # one pass over the basis (each slice applied once) for the whole batch
        last = np.asarray(bands[-1], dtype=np.float64)
        out = last.copy()
        for (lo, hi), b in zip(self._ranges(), bands[:-1]):
            out += self.proj.project(np.asarray(b, dtype=np.float64) - last, lo, hi)
        return out

    def project(self, P, band: int) -> np.ndarray:
        """The part of P - mean in one band (no mean added): X_j (P - mean), or for the last band
        (I - sum X_j)(P - mean)."""
        self._check()
        if not -self.n_bands <= band < self.n_bands:
            raise IndexError(f"band {band} out of range for {self.n_bands} bands")
        band %= self.n_bands
        D = np.asarray(P, dtype=np.float64) - self.mean
        if band < len(self.cuts):
            return self.proj.project(D, *self._ranges()[band])
        return D - self.proj.project(D, 0, self.cuts[-1])

    def band_shares(self, D) -> np.ndarray:
        """(..., n, 3) displacements D -> (..., bands): the share of their M-weighted energy in
        each band, ||X_j D||_M^2 / ||D||_M^2 (M = I with ``mass: false``). The bands are
        M-orthogonal, so the shares sum to 1 (the disentanglement of thesis 4.7.3's edits)."""
        self._check()
        D = np.asarray(D, dtype=np.float64)
        flat = D.reshape(-1, *D.shape[-2:])
        parts = np.stack([_energy(self.project(flat + self.mean, j), self.proj.m) for j in range(self.n_bands)], -1)
        total = np.maximum(_energy(flat, self.proj.m), 1e-300)
        return (parts / total[:, None]).reshape(*D.shape[:-2], self.n_bands)

    def assemble_many(self, bands, ks) -> np.ndarray:
        """Two-band assembly ``[low, high]`` for every cut k in ``ks`` (each <= the fitted basis
        size, ``eigen_k``): (len(ks), b, n, 3), or (len(ks), n, 3) for single meshes. With
        c = U^T M (low - high), P'(k) = U_k c_k + high, accumulated over the sorted ks, so the
        whole sweep costs one projection (the PBS k sweep, thesis 5.3.3)."""
        self._check()
        low, high = (np.asarray(x, dtype=np.float64) - self.mean for x in bands)
        single = low.ndim == 2
        if single:
            low, high = low[None], high[None]
        b, n = low.shape[:2]
        U = self.proj.U
        K = U.shape[1]
        ks = [int(k) for k in ks]
        if any(k < 0 or k > K for k in ks):
            raise ValueError(f"assemble_many: every k must lie in [0, {K}] (the fitted basis), got {ks}")
        c = self.proj.coefficients(low - high)  # (K, 3b)
        out = np.empty((len(ks), b, n, 3))
        acc, prev = np.zeros((n, 3 * b)), 0
        for i in np.argsort(ks, kind="stable"):
            k = ks[i]
            if k > prev:
                acc += U[:, prev:k] @ c[prev:k]
                prev = k
            out[i] = acc.reshape(n, b, 3).transpose(1, 0, 2) + high + self.mean
        return out[:, 0] if single else out

    def torch(self, device="cpu", dtype=None) -> "TorchSpectral":
        """The differentiable torch version of this fitted assembler."""
        return TorchSpectral(self, device, dtype)

    def state_dict(self) -> dict:
        self._check()
        return {"cuts": self.cuts, "mass": self.mass, "eigen_k": self.eigen_k, "U": self.proj.U, "m": self.proj.m,
                "mean": self.mean, "evals": self.evals}

    def truncated_state(self, k: int) -> dict:
        """The state of this fitted assembler built with the single cut k (``TruncatesCuts``):
        the first k eigenvectors (and eigenvalues) only; ``assemble_many`` at any cut up to k gives
        what it gave before (the basis columns are the same numbers)."""
        self._check()
        K = self.proj.U.shape[1]
        if not 0 < int(k) <= K:
            raise ValueError(f"truncated_state: k must lie in [1, {K}] (the fitted basis), got {k}")
        k = int(k)
        return {"cuts": [k], "mass": self.mass, "eigen_k": None, "U": np.ascontiguousarray(self.proj.U[:, :k]),
                "m": self.proj.m, "mean": self.mean, "evals": None if self.evals is None else self.evals[:k]}

    def load_state_dict(self, d, ctx=None) -> None:
        self.cuts, self.mass = [int(c) for c in d["cuts"]], bool(d["mass"])
        self.eigen_k = d.get("eigen_k")
        self.evals = d.get("evals")
        # float64 whatever the file stores (a packed model may keep the basis in float32)
        self.mean = np.asarray(d["mean"], dtype=np.float64)
        self.proj = SpectralProjector(np.asarray(d["U"], dtype=np.float64),
                                      None if d["m"] is None else np.asarray(d["m"], dtype=np.float64))


class TorchSpectral:
    """Differentiable, batched band projection and assembly in torch (CPU or GPU), from a fitted
    ``Spectral``: ``project(P, lo, hi)``, ``split(P)``, ``assemble(bands)`` on (b, n, 3) tensors."""

    def __init__(self, assembler: Spectral, device="cpu", dtype=None):
        dtype = dtype or torch.float32
        self.proj = TorchSpectralProjector(assembler.proj.U, assembler.proj.m, dtype=dtype).to(device)
        self.U, self.UtM = self.proj.U, self.proj.UtM
        self.mean = torch.as_tensor(assembler.mean, dtype=dtype, device=device)
        self.cuts = list(assembler.cuts)
        self.ranges = assembler._ranges()

    def project(self, P, lo, hi):
        return self.proj.project(P, lo, hi)

    def split(self, P):
        D = P - self.mean
        bands, low_sum = [], 0.0
        for lo, hi in self.ranges:
            x = self.proj.project(D, lo, hi)
            bands.append(x + self.mean)
            low_sum = low_sum + x
        return bands + [D - low_sum + self.mean]

    def assemble(self, bands):
        return self.proj.assemble(bands, self.cuts, self.mean)


@hookimpl
def fwk_register_assemblers():
    return [Spectral]
