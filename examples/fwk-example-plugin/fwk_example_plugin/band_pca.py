r"""An example third-party model: band-wise PCA, a linear analogue of Deep Spectral Meshes
(Kosk et al., "Deep Spectral Meshes: Multi-Frequency Facial Mesh Processing with Graph Neural
Networks", Electronics 13(4):720, 2024; thesis chapter 4), model ``band-pca``.

Bands. An assembler (the recipe's ``assembler``, default ``spectral``; any component playing
``fwk.protocols.Assembler``) is fitted on the template and the mean training mesh P-bar and splits
every mesh P into B bands, each a mesh centred on the mean (thesis eq. 4.11 for ``spectral``:
P_low = X (P - P-bar) + P-bar, P_high = (I - X)(P - P-bar) + P-bar, X = U_k U_k^T M):

    P = sum_j (band_j(P) - P-bar) + P-bar,       assemble(split(P)) = P.

Per band, PCA. Band j of the m training meshes, flattened, x_ij = vec(band_j(P_i) - P-bar) in R^{3n},
has the mean mu_j and the centred data matrix X_j = U_j S_j V_j^T (thin SVD); the model keeps the
first q_j right singular vectors V_j (3n x q_j) and the standard deviations sd_j = s_j / sqrt(m - 1)
of the training codes. Each band's code is whitened, so that the training codes have unit
variance and the prior of the generative role, N(0, I), is the codes' own distribution:

    z_j = diag(sd_j)^-1 V_j^T (x_j - mu_j)                     (encode, per band)
    band'_j = P-bar + mu_j + V_j diag(sd_j) z_j                 (decode_bands)
    Z = [z_1 | ... | z_B],    P' = assemble([band'_1, ..., band'_B])   (decode, thesis eq. 4.15)

A component of (numerically) zero variance gets sd = 0 in both directions, so it neither
codes nor decodes anything. Because every training band lies in its band's subspace, so do
its principal components, and the assembly adds each band's reconstruction back unchanged:
reconstruct(P) = P-bar + sum_j mu_j + V_j V_j^T (x_j - mu_j), one orthogonal PCA projection per
band. Where DSM trains one VAE per band (and conditions each decoder on the other bands' codes),
this model has one linear, closed-form autoencoder per band and no conditioning: what DSM adds
over it is the non-linear decoders and the conditioning factor.

Roles: ``ReconstructionModel`` and ``BandModel`` (hence ``GenerativeModel``): ``band_names``,
``latent_slice(band)``, ``split``, ``assemble``, ``decode_bands``, ``band_shares`` (the
assembler's), ``encode``, ``decode``, ``sample(n, seed)`` (Z ~ N(0, I)); so the ``edit`` and
``interpolate`` tasks and ``fwk sample`` take it like ``dsm``.

Registered through this package's own entry point (``example-band-pca``).
"""
from __future__ import annotations

from typing import Annotated

import numpy as np

from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT
from fwk.recipes import Kind, Spec, make_spec, with_key_path

ZERO_VARIANCE = 1e-10  # a component whose sd is below this share of the largest is not coded


def _positive_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


class BandPCA:
    r"""Band-wise PCA: one PCA per frequency band of an assembler, codes concatenated (a linear Deep Spectral Meshes).

    Each training mesh is split into bands by the assembler (``spectral``: low / high
    frequencies of the cotangent Laplacian); band j gets its own PCA with q_j whitened
    components, Z = [z_1 | ... | z_B]; decoding decodes every band and assembles them.

    Args:
        assembler (assembler): splits meshes into bands and assembles them back (default
            ``spectral`` with its own settings; on a small template give its ``k``, e.g.
            ``{name: spectral, k: 20}``).
        n_components (int | list[int]): q_j, the latent size of each band: one number for every
            band or one per band (low to high). At most the training meshes - 1.
        band_names (list[str] | None): the bands' names, low to high (default ``low``, ``high``
            for two bands, else ``band0``, ``band1``, ..., ``high``).
    """

    name = "band-pca"
    task_family = RECONSTRUCT

    def __init__(self, assembler: Annotated[Spec, Kind("assembler")] = "spectral",
                 n_components: int | list[int] = 8, band_names: list[str] | None = None):
        ks = [n_components] if not isinstance(n_components, (list, tuple)) else list(n_components)
        if not ks or not all(_positive_int(k) for k in ks):
            raise RecipeError(f"n_components: expected an integer >= 1 or a list of them (one per band), "
                              f"got {n_components!r}")
        if band_names is not None and (len(set(band_names)) != len(band_names) or len(band_names) < 2
                                       or not all(isinstance(b, str) and b for b in band_names)):
            raise RecipeError(f"band_names: give distinct names, at least two, got {band_names!r}")
        if band_names is not None and isinstance(n_components, (list, tuple)) and len(ks) != len(band_names):
            raise RecipeError(f"n_components: {len(ks)} given for {len(band_names)} band_names")
        self.assembler_spec = make_spec("assembler", assembler, "assembler")
        self.n_components = n_components
        self.band_names_param = None if band_names is None else list(band_names)
        self.assembler = None
        self._band_names: list[str] | None = None
        self.mean = None          # (n, 3) P-bar, the mean training mesh
        self.means = None         # per band (3n,) mu_j
        self.components = None    # per band (q_j, 3n) V_j^T
        self.sds = None           # per band (q_j,) sd_j (0 for a component of zero variance)

    # ------------------------------------------------------------------ sizes
    @property
    def band_names(self) -> list[str]:
        """The bands' names, low to high (known once fitted: the number of bands is the assembler's)."""
        return list(self._band_names or self.band_names_param or [])

    @property
    def latents(self) -> list[int]:
        """q_j of every band once fitted; before, the recipe's list (or [] for one number)."""
        if self.components is not None:
            return [int(len(c)) for c in self.components]
        return list(self.n_components) if isinstance(self.n_components, (list, tuple)) else []

    @property
    def latent_size(self) -> int:
        """|Z| = sum_j q_j (0 before fitting when the number of bands is not known yet)."""
        return int(sum(self.latents))

    def latent_slice(self, band: str | int) -> slice:
        """The entries of Z that band ``band`` (its name or index) owns; an unknown band is a DataError."""
        names = self.band_names
        if isinstance(band, int) and not isinstance(band, bool):
            if not -len(names) <= band < len(names):
                raise DataError(f"band {band}: out of range; the model has {len(names)} bands ({', '.join(names)})")
            band = names[band]
        if band not in names:
            raise DataError(f"band {band!r}: unknown; the model's bands are {', '.join(names)}")
        j = names.index(band)
        start = sum(self.latents[:j])
        return slice(start, start + self.latents[j])

    def check_data(self, data) -> None:
        """Raise a RecipeError before any model trains when an ``n_components`` is above the
        training meshes - 1 (m meshes carry at most m - 1 components per band)."""
        m = len(data.stack("train"))
        ks = self.n_components if isinstance(self.n_components, (list, tuple)) else [self.n_components]
        if max(ks) > m - 1:
            raise RecipeError(f"n_components: {max(ks)} components, but the training split holds {m} meshes, "
                              f"which carry at most {m - 1} per band")

    # ------------------------------------------------------------------ fitting
    def _check(self):
        if self.components is None:
            raise RuntimeError("band-pca: used before fit() or load_state_dict()")

    def fit(self, data, ctx=None) -> None:
        """Fit the assembler on the template and the mean training mesh, then one PCA per band
        of ``data.stack("train")``; ``ctx`` lends its cache to the assembler's eigenbasis."""
        self.check_data(data)
        P = data.stack("train")
        m = len(P)
        self.mean = P.mean(axis=0)
        assembler = self.assembler_spec.build()
        try:
            assembler.fit(data.template, self.mean, cache=ctx.cache if ctx is not None else None)
        except RecipeError as exc:  # a setting of the assembler the template refutes (k above n)
            raise RecipeError(with_key_path(str(exc), "assembler")) from None
        self.assembler = assembler
        bands = assembler.split(P)
        B = len(bands)
        ks = list(self.n_components) if isinstance(self.n_components, (list, tuple)) else [self.n_components] * B
        if len(ks) != B:
            raise RecipeError(f"n_components: {len(ks)} given, the assembler makes {B} bands")
        names = self.band_names_param or (["low", "high"] if B == 2 else [*(f"band{i}" for i in range(B - 1)), "high"])
        if len(names) != B:
            raise RecipeError(f"band_names: {len(names)} given, the assembler makes {B} bands")
        self._band_names = list(names)
        self.means, self.components, self.sds = [], [], []
        for band, q in zip(bands, ks):
            X = (band - self.mean).reshape(m, -1)
            mu = X.mean(axis=0)
            _, s, Vt = np.linalg.svd(X - mu, full_matrices=False)
            self.means.append(mu)
            self.components.append(np.ascontiguousarray(Vt[:q]))
            self.sds.append(s[:q] / np.sqrt(max(m - 1, 1)))
        top = max((float(sd.max()) for sd in self.sds if len(sd)), default=0.0)
        self.sds = [np.where(sd > ZERO_VARIANCE * top, sd, 0.0) for sd in self.sds]

    # ------------------------------------------------------------------ bands
    def split(self, P) -> list[np.ndarray]:
        """(b, n, 3) -> B bands, each (b, n, 3) float64 and centred on the mean (the assembler's)."""
        self._check()
        return self.assembler.split(np.asarray(P, dtype=np.float64))

    def assemble(self, bands) -> np.ndarray:
        """B bands, each (b, n, 3) -> (b, n, 3): the assembler's inverse of ``split``."""
        self._check()
        return self.assembler.assemble([np.asarray(b, dtype=np.float64) for b in bands])

    def band_shares(self, D) -> np.ndarray:
        """(b, n, 3) displacements -> (b, B): each band's share of their energy (the assembler's)."""
        self._check()
        return self.assembler.band_shares(np.asarray(D, dtype=np.float64))

    # ------------------------------------------------------------------ codes
    def encode(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, |Z|) float64: every band's whitened PCA code, concatenated low to high."""
        self._check()
        P = np.asarray(P, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != self.mean.shape:
            raise DataError(f"band-pca: meshes of shape {P.shape[1:]}, trained on {self.mean.shape}")
        codes = []
        for band, mu, V, sd in zip(self.split(P), self.means, self.components, self.sds):
            c = ((band - self.mean).reshape(len(P), -1) - mu) @ V.T
            codes.append(c * np.divide(1.0, sd, out=np.zeros_like(sd), where=sd > 0))
        return np.concatenate(codes, axis=1)

    def decode_bands(self, Z) -> list[np.ndarray]:
        """(b, |Z|) -> B bands, each (b, n, 3): band j decoded from its own slice of Z alone."""
        self._check()
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        if Z.shape[1] != self.latent_size:
            raise DataError(f"band-pca: codes of {Z.shape[1]} entries, the model's have {self.latent_size}")
        out = []
        for j, (mu, V, sd) in enumerate(zip(self.means, self.components, self.sds)):
            x = mu + (Z[:, self.latent_slice(j)] * sd) @ V
            out.append(self.mean + x.reshape(len(Z), *self.mean.shape))
        return out

    def decode(self, Z) -> np.ndarray:
        """(b, |Z|) -> (b, n, 3): the bands decoded and assembled."""
        return self.assemble(self.decode_bands(Z))

    def reconstruct(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, n, 3): decode(encode(P)), one PCA projection per band."""
        return self.decode(self.encode(P))

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n meshes decoded from Z ~ N(0, I) (NumPy's generator of ``seed``)."""
        self._check()
        return self.decode(np.random.default_rng(seed).standard_normal((n, self.latent_size)))

    # ------------------------------------------------------------------ saving
    def state_dict(self) -> dict:
        """Arrays, lists and the assembler's own state (plain data: fwk saves it as safetensors)."""
        self._check()
        return {"assembler": self.assembler.state_dict(), "band_names": list(self._band_names), "mean": self.mean,
                "means": list(self.means), "components": list(self.components), "sds": list(self.sds)}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a fitted model; the assembler is rebuilt from the recipe's spec and loaded."""
        assembler = self.assembler_spec.build()
        assembler.load_state_dict(d["assembler"], ctx=ctx)
        self.assembler = assembler
        self._band_names = [str(b) for b in d["band_names"]]
        self.mean = np.asarray(d["mean"], dtype=np.float64)
        self.means = [np.asarray(x, dtype=np.float64) for x in d["means"]]
        self.components = [np.asarray(x, dtype=np.float64) for x in d["components"]]
        self.sds = [np.asarray(x, dtype=np.float64) for x in d["sds"]]


@hookimpl
def fwk_register_models():
    return [BandPCA]
