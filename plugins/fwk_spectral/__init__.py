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
one (n, 3b) block product for a batch. ``assemble_many(bands, ks)`` assembles two bands for many
cut points k at once (the PBS k sweep, thesis 5.3.3) from cumulative coefficient sums. A
differentiable torch version for training-time use is ``TorchSpectral``.
"""
from __future__ import annotations

import numpy as np

from fwk.errors import RecipeError
from fwk.geometry.operators import mass_matrix
from fwk.geometry.spectral import SpectralProjector, eigenbasis
from fwk.hookspecs import hookimpl


class Spectral:
    """Spectral bands of the cotangent Laplacian (low / high frequencies, or more bands)."""

    name = "spectral"

    def __init__(self, k: int | list[int] = 500, mass: bool = True):
        cuts = [k] if isinstance(k, int) else list(k)
        if not cuts or any(c <= 0 for c in cuts) or cuts != sorted(set(cuts)):
            raise RecipeError(f"k: cut points must be positive and increasing, got {k}")
        self.cuts, self.mass = cuts, mass
        self.proj: SpectralProjector | None = None
        self.mean = None

    @property
    def n_bands(self) -> int:
        return len(self.cuts) + 1

    def fit(self, template, mean=None, cache=None) -> None:
        n = template.n_vertices
        if self.cuts[-1] > n:
            raise RecipeError(f"k: cut point {self.cuts[-1]} exceeds the template's {n} vertices")
        V = template.vertices if mean is None else np.asarray(mean, dtype=np.float64)
        self.mean = V.copy()
        _, U = eigenbasis(V, template.triangles, self.cuts[-1], weighted=self.mass, cache=cache)
        m = mass_matrix(V, template.triangles).diagonal() if self.mass else None
        self.proj = SpectralProjector(U, m)

    def _ranges(self):
        edges = [0, *self.cuts]
        return [(edges[j], edges[j + 1]) for j in range(len(self.cuts))]

    def split(self, P) -> list[np.ndarray]:
        P = np.asarray(P, dtype=np.float64)
        D = P - self.mean
        bands, low_sum = [], 0.0
        for lo, hi in self._ranges():
            x = self.proj.project(D, lo, hi)
            bands.append(x + self.mean)
            low_sum = low_sum + x
        bands.append(D - low_sum + self.mean)
        return bands

    def assemble(self, bands) -> np.ndarray:
        if len(bands) != self.n_bands:
            raise ValueError(f"assemble: {len(bands)} bands given, the assembler has {self.n_bands}")
        out = 0.0
        high = np.asarray(bands[-1], dtype=np.float64) - self.mean
        for (lo, hi), b in zip(self._ranges(), bands[:-1]):
            out = out + self.proj.project(np.asarray(b, dtype=np.float64) - self.mean, lo, hi)
            high = high - self.proj.project(high, lo, hi)
        return out + high + self.mean

    def project(self, P, band: int) -> np.ndarray:
        """The part of P - mean in one band (no mean added)."""
        return self.split(P)[band] - self.mean

    def assemble_many(self, low, high, ks) -> np.ndarray:
        """Two-band assembly for every cut k in ``ks`` (each <= the fitted K): (len(ks), b, n, 3)."""
        low = np.asarray(low, dtype=np.float64) - self.mean
        high = np.asarray(high, dtype=np.float64) - self.mean
        single = low.ndim == 2
        if single:
            low, high = low[None], high[None]
        b, n = low.shape[:2]
        c = self.proj.coefficients(low - high)  # (K, 3b)
        U = self.proj.U
        out = np.empty((len(ks), b, n, 3))
        # P'(k) = U_k c_k + high + mean with c = U^T M (low - high): cumulative in k
        for i, k in enumerate(ks):
            k = int(min(max(k, 0), U.shape[1]))
            corr = (U[:, :k] @ c[:k]).reshape(n, b, 3).transpose(1, 0, 2) if k else 0.0
            out[i] = high + corr + self.mean
        return out[:, 0] if single else out

    def state_dict(self) -> dict:
        return {"cuts": self.cuts, "mass": self.mass, "U": self.proj.U, "m": self.proj.m, "mean": self.mean}

    def load_state_dict(self, d) -> None:
        self.cuts, self.mass, self.mean = list(d["cuts"]), bool(d["mass"]), np.asarray(d["mean"])
        self.proj = SpectralProjector(np.asarray(d["U"]), None if d["m"] is None else np.asarray(d["m"]))


class TorchSpectral:
    """Differentiable, batched two-band (or multi-band) projection in torch (CPU or GPU)."""

    def __init__(self, assembler: Spectral, device="cpu", dtype=None):
        import torch

        dtype = dtype or torch.float32
        self.U = torch.as_tensor(assembler.proj.U, dtype=dtype, device=device)
        self.UtM = torch.as_tensor(assembler.proj.UtM, dtype=dtype, device=device)
        self.mean = torch.as_tensor(assembler.mean, dtype=dtype, device=device)
        self.ranges = assembler._ranges()

    def project(self, P, lo, hi):
        # P (b, n, 3): U[:, lo:hi] @ (UtM[lo:hi] @ P) batched via einsum, no n x n
        c = self.UtM[lo:hi] @ P  # (b, K, 3) by broadcasting
        return self.U[:, lo:hi] @ c

    def assemble(self, bands):
        out = 0.0
        high = bands[-1] - self.mean
        for (lo, hi), b in zip(self.ranges, bands[:-1]):
            out = out + self.project(b - self.mean, lo, hi)
            high = high - self.project(high, lo, hi)
        return out + high + self.mean


@hookimpl
def fwk_register_assemblers():
    return [Spectral]
