r"""An example third-party model: probabilistic PCA (Tipping & Bishop 1999, "Probabilistic
principal component analysis", J. R. Statist. Soc. B 61(3):611-622), model ``ppca``.

Each training mesh (n vertices, in fwk's evaluation space) is flattened to x in R^d, d = 3n.
PPCA is the latent-variable model

    z ~ N(0, I_q),     x | z ~ N(W z + mu, sigma^2 I_d),     so  x ~ N(mu, C),  C = W W^T + sigma^2 I_d,

with W (d x q). With S = (1/N) sum_i (x_i - mu)(x_i - mu)^T the sample covariance of the N
training meshes (mu their mean) and lambda_1 >= ... >= lambda_d its eigenvalues, eigenvectors
U, the log-likelihood

    L(W, sigma^2) = -N/2 (d log 2 pi + log |C| + tr(C^-1 S))

is maximised in closed form (Tipping & Bishop, section 3.2):

    sigma^2_ML = 1 / (d - q) sum_{j > q} lambda_j          (the mean of the discarded eigenvalues)
    W_ML       = U_q (Lambda_q - sigma^2 I)^{1/2} R           (R any rotation; here R = I)

The eigenpairs come from a thin SVD of the N x d centred data matrix (O(N^2 d)), never from the
d x d covariance. The posterior of the code is

    z | x ~ N(M^-1 W^T (x - mu), sigma^2 M^-1),     M = W^T W + sigma^2 I_q,

and ``encode`` returns its mean; ``decode(z) = W z + mu`` (the mean of p(x | z));
``reconstruct(P) = decode(encode(P))`` = mu + W M^-1 W^T (x - mu). Along principal direction j
this keeps the share (lambda_j - sigma^2) / lambda_j of the deviation from the mean: PPCA
shrinks a reconstruction towards the mean where the noise model explains part of the variance.

``sample(n, seed)`` decodes z ~ N(0, I) *without* the isotropic noise eps ~ N(0, sigma^2 I):
the noise term models what the q components leave unexplained as independent jitter of every
coordinate of every vertex; added to a mesh it is white per-vertex noise (a rough, speckled
surface), not a plausible face, so a sample is the mean mesh W z + mu of p(x | z).
``log_likelihood(P)`` is log p(x) under N(mu, C), computed through M (Woodbury and the matrix
determinant lemma: |C| = sigma^{2(d - q)} |M|), never forming the d x d matrix C.

How it differs from the built-in ``pca``: ``pca`` keeps orthonormal components and projects
orthogonally (reconstruct = mu + V^T V (x - mu), no noise model, codes of variance s^2/(m - 1));
``ppca`` is a density model: its columns of W are scaled by (lambda_j - sigma^2)^{1/2}, its codes
are posterior means with the prior N(0, I) that ``sample`` draws from, its reconstruction is
shrunk towards the mean (see above), and it has a likelihood. As sigma^2 -> 0 it becomes ``pca``.
It works on the positions themselves (no representation).

Registered through this package's own entry point (``example-ppca``).
"""
from __future__ import annotations

import numpy as np

from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import RECONSTRUCT

DEFAULT_COMPONENTS = 64  # kept when the recipe gives none (and the training set carries as many)


def fit_ppca(X: np.ndarray, q: int):
    """The ML solution of PPCA for the rows of X (N x d): (mu (d,), W (d, q), sigma^2, lambda_q (q,)),
    lambda_q the q largest eigenvalues of the sample covariance S = (1/N) sum (x - mu)(x - mu)^T."""
    N, d = X.shape
    mu = X.mean(axis=0)
    Xc = X - mu
    _, s, Vt = np.linalg.svd(Xc, full_matrices=False)  # S = Vt^T diag(s^2 / N) Vt: eigenpairs of S
    lam = s ** 2 / N
    total = float(np.sum(Xc ** 2) / N)                  # tr S = sum of all d eigenvalues
    sigma2 = (total - float(lam[:q].sum())) / (d - q)   # the mean of the d - q discarded eigenvalues
    W = np.ascontiguousarray(Vt[:q].T * np.sqrt(np.maximum(lam[:q] - sigma2, 0.0)))
    return mu, W, sigma2, np.ascontiguousarray(lam[:q])  # C order, as a state comes back from its file


def log_likelihood(X: np.ndarray, mu: np.ndarray, W: np.ndarray, sigma2: float) -> np.ndarray:
    """log N(x; mu, W W^T + sigma^2 I) of every row x of X (b x d), through M = W^T W + sigma^2 I:
    C^-1 = (I - W M^-1 W^T) / sigma^2 and log |C| = (d - q) log sigma^2 + log |M|."""
    X = np.atleast_2d(np.asarray(X, dtype=np.float64))
    d, q = W.shape
    M = W.T @ W + sigma2 * np.eye(q)
    D = X - mu
    proj = D @ W                                              # (b, q)
    quad = (np.sum(D ** 2, axis=1) - np.sum(proj * np.linalg.solve(M, proj.T).T, axis=1)) / sigma2
    _, logdet_m = np.linalg.slogdet(M)
    logdet_c = (d - q) * np.log(sigma2) + logdet_m
    return -0.5 * (d * np.log(2 * np.pi) + logdet_c + quad)


class PPCA:
    r"""Probabilistic PCA (Tipping & Bishop 1999): a Gaussian latent model of the meshes, fitted in closed form.

    x = W z + mu + eps with z ~ N(0, I_q) and eps ~ N(0, sigma^2 I); the maximum-likelihood
    sigma^2 is the mean of the discarded covariance eigenvalues and W = U_q (Lambda_q - sigma^2 I)^{1/2}.
    ``encode`` is the posterior mean M^-1 W^T (x - mu), M = W^T W + sigma^2 I; ``decode(z) = W z + mu``;
    ``sample`` decodes z ~ N(0, I) without the isotropic noise (white per-vertex jitter is no face).

    Args:
        n_components (int | None): q, the latent size. At most the number of training meshes
            - 2 (the discarded eigenvalues must include a non-zero one: sigma^2 > 0); default
            min(64, training meshes - 2).

    Roles: ``ReconstructionModel`` (``reconstruct``) and ``GenerativeModel`` (``latent_size``,
    ``encode``, ``decode``, ``sample``); ``ChecksData`` (``n_components`` against the training set).
    """

    name = "ppca"
    task_family = RECONSTRUCT

    def __init__(self, n_components: int | None = None):
        if n_components is not None and (not isinstance(n_components, int) or isinstance(n_components, bool)
                                         or n_components < 1):
            raise RecipeError(f"n_components: expected an integer >= 1, got {n_components!r}")
        self.n_components = n_components
        self.mean = self.W = self.eigenvalues = None
        self.sigma2 = None
        self.n_vertices = self.n_train = 0

    # ------------------------------------------------------------------ sizes and checks
    @property
    def latent_size(self) -> int:
        """q: the columns of W once fitted (before: ``n_components``, or 64 when none given)."""
        if self.W is not None:
            return int(self.W.shape[1])
        return DEFAULT_COMPONENTS if self.n_components is None else self.n_components

    def check_data(self, data) -> None:
        """Raise a RecipeError before any model trains when ``n_components`` is above what the
        training meshes of ``data`` (a FitData) support: m meshes carry m - 1 non-zero
        eigenvalues, and sigma^2 > 0 needs one of them discarded, so q <= m - 2."""
        self._components_for(len(data.stack("train")))

    def _components_for(self, m: int) -> int:
        most = m - 2
        if most < 1:
            raise RecipeError(f"n_components: ppca needs at least 3 training meshes, the training split holds {m}")
        if self.n_components is None:
            return min(DEFAULT_COMPONENTS, most)
        if self.n_components > most:
            raise RecipeError(f"n_components: {self.n_components} components, but the training split holds {m} "
                              f"meshes: ppca keeps at most {most} (m - 2, so that sigma^2, the mean of the "
                              f"discarded eigenvalues, is not zero)")
        return self.n_components

    def _check(self, P=None) -> np.ndarray | None:
        if self.W is None:
            raise RuntimeError("ppca: used before fit() or load_state_dict()")
        if P is None:
            return None
        P = np.asarray(P, dtype=np.float64)
        if P.ndim != 3 or P.shape[1:] != (self.n_vertices, 3):
            raise DataError(f"ppca: meshes of shape {P.shape[1:]}, trained on ({self.n_vertices}, 3)")
        return P

    # ------------------------------------------------------------------ fitting
    def fit(self, data, ctx=None) -> None:
        """The closed-form ML solution on ``data.stack("train")`` (every training shape of
        ``data.shapes``), flattened to (m, 3n); ``ctx`` is not needed."""
        P = data.stack("train")
        q = self._components_for(len(P))
        mu, W, sigma2, lam = fit_ppca(P.reshape(len(P), -1), q)
        if not sigma2 > 1e-12 * max(float(lam[0]), 1e-300):
            raise DataError(f"ppca: the training meshes leave no variance beyond {q} components (sigma^2 = "
                            f"{sigma2:.3g}); give fewer n_components")
        self.mean, self.W, self.sigma2, self.eigenvalues = mu, W, float(sigma2), lam
        self.n_vertices, self.n_train = int(P.shape[1]), int(len(P))

    # ------------------------------------------------------------------ the roles
    def _m(self) -> np.ndarray:
        return self.W.T @ self.W + self.sigma2 * np.eye(self.W.shape[1])

    def encode(self, P) -> np.ndarray:
        """(b, n, 3) float64 -> (b, q) float64: the posterior means M^-1 W^T (x - mu)."""
        P = self._check(P)
        D = P.reshape(len(P), -1) - self.mean
        return np.linalg.solve(self._m(), (D @ self.W).T).T

    def decode(self, Z) -> np.ndarray:
        """(b, q) -> (b, n, 3) float64: W z + mu, the mean of p(x | z) (no noise added)."""
        self._check()
        Z = np.atleast_2d(np.asarray(Z, dtype=np.float64))
        return (self.mean + Z @ self.W.T).reshape(len(Z), self.n_vertices, 3)

    def reconstruct(self, P) -> np.ndarray:
        """(b, n, 3) -> (b, n, 3): decode(encode(P)) = mu + W M^-1 W^T (x - mu)."""
        return self.decode(self.encode(P))

    def sample(self, n: int, seed: int = 0) -> np.ndarray:
        """n meshes (n, n_vertices, 3): W z + mu for z ~ N(0, I) (NumPy's generator of ``seed``),
        without the isotropic noise (see the module docstring)."""
        self._check()
        return self.decode(np.random.default_rng(seed).standard_normal((n, self.latent_size)))

    def log_likelihood(self, P) -> np.ndarray:
        """(b, n, 3) -> (b,) log p(x) under N(mu, W W^T + sigma^2 I), in the evaluation space."""
        P = self._check(P)
        return log_likelihood(P.reshape(len(P), -1), self.mean, self.W, self.sigma2)

    # ------------------------------------------------------------------ saving
    def state_dict(self) -> dict:
        """Arrays and plain numbers only (fwk saves it as safetensors)."""
        self._check()
        return {"mean": self.mean, "W": self.W, "sigma2": self.sigma2, "eigenvalues": self.eigenvalues,
                "n_vertices": self.n_vertices, "n_train": self.n_train}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a fitted model (``ctx`` is not needed: arrays only)."""
        self.mean, self.W = np.asarray(d["mean"], dtype=np.float64), np.asarray(d["W"], dtype=np.float64)
        self.eigenvalues = np.asarray(d["eigenvalues"], dtype=np.float64)
        self.sigma2, self.n_vertices, self.n_train = float(d["sigma2"]), int(d["n_vertices"]), int(d["n_train"])


@hookimpl
def fwk_register_models():
    return [PPCA]
