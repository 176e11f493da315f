r"""An example third-party model: personalised blendshapes by ridge regression, model ``ridge-bs``.

A linear baseline for the task of thesis chapter 5 (a subject's expressions from its neutral
head): each expression's displacement from the neutral is regressed linearly on the neutral,
in a small PCA basis of the training neutrals, with Tikhonov (ridge) regularisation (Hoerl &
Kennard 1970, "Ridge regression: biased estimation for nonorthogonal problems"). In the spirit
of the linear, example-based rigs that learn a subject-specific correction from training
subjects (e.g. Li, Weise & Pauly 2010, "Example-based facial rigging"), with the neutral as the
only input.

Data (fwk's blendshapes task prepares it; ``fwk.protocols.FitData``): every mesh is in the
evaluation space (centred, rigidly registered to the mean training neutral, scaled into
[-1, 1]); a subject's expressions move with its neutral, so the displacement
D = P_expr - P_neutral is meaningful per vertex.

Neutral code. The m training neutrals, flattened to x_i in R^{3n}, have the mean x-bar and the
thin SVD X - x-bar = U S V^T; with V_k the first k right singular vectors and
sd = s_k / sqrt(m - 1), a neutral's whitened code is

    c(x) = diag(sd)^-1 V_k^T (x - x-bar)          (unit variance on the training neutrals)

(a component of zero variance gets code 0).

Regression, per expression e. On the training subjects that have e (codes c_i, displacements
d_i = vec(P_e,i - P_neutral,i)), with their means c-bar_e and d-bar_e and the centred matrices
C (m_e x k) and D (m_e x 3n):

    B_e = argmin_B  || D - C B ||_F^2 + lambda || B ||_F^2  =  (C^T C + lambda I)^-1 C^T D    (k x 3n)

i.e. the ridge solution of min sum_i || d_i - d0 - B^T c_i ||^2 + lambda ||B||^2 with an
unpenalised intercept d0 (its solution centres both sides). Prediction for a neutral x:

    P'_e = P_neutral + d-bar_e + B_e^T (c(x) - c-bar_e)

With whitened codes C^T C ~ (m_e - 1) I, so lambda is relative to the number of subjects: every
coefficient is shrunk by about (m_e - 1) / (m_e - 1 + lambda); lambda -> infinity predicts the
mean displacement d-bar_e for everyone (the "average expression" baseline), lambda = 0 is least
squares (the minimum-norm solution where it is not unique). ``predict_all`` codes the neutrals
once for every expression. No ground truth is used: ``target`` is accepted and ignored (the
output keeps the neutral's placement).

Role: ``BlendshapeModel`` (``expressions``, ``predict``, ``predict_all``, ``fit``).
Registered through this package's own entry point (``example-ridge-bs``).
"""
from __future__ import annotations

import numpy as np

from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.protocols import BLENDSHAPES

DEFAULT_COMPONENTS = 16  # neutral components kept when the recipe gives none (and the training set carries as many)
ZERO_VARIANCE = 1e-10  # a neutral component whose sd is below this share of the largest is not coded


class RidgeBlendshapes:
    r"""Ridge-regression blendshapes: each expression's displacement regressed linearly on the neutral's PCA code.

    P'_e = P_neutral + d-bar_e + B_e^T (c(x) - c-bar_e), c(x) the whitened PCA code of the
    neutral x and B_e = (C^T C + lambda I)^-1 C^T D the ridge solution on the training subjects.

    Args:
        n_components (int | None): k, the neutral PCA components used as regressors (at most the
            training neutrals - 1; default min(16, training neutrals - 1)). The state holds
            E x k x 3n numbers (B_e of E expressions): keep k small on a large mesh.
        ridge_weight (float): lambda >= 0, the Tikhonov weight on B (the codes are whitened, so
            1 shrinks each coefficient by about (m - 1) / m for m training subjects).
        expressions (list[str] | None): the expressions to learn (default: every expression the
            task gives, else every non-neutral shape of the training split).
    """

    name = "ridge-bs"
    task_family = BLENDSHAPES
    expressions: list[str] | None = None  # the blendshape role's member, declared on the class; set per instance

    def __init__(self, n_components: int | None = None, ridge_weight: float = 1.0,
                 expressions: list[str] | None = None):
        if n_components is not None and (not isinstance(n_components, int) or isinstance(n_components, bool)
                                         or n_components < 1):
            raise RecipeError(f"n_components: expected an integer >= 1, got {n_components!r}")
        if isinstance(ridge_weight, bool) or not isinstance(ridge_weight, (int, float)) \
                or not (np.isfinite(ridge_weight) and ridge_weight >= 0):
            raise RecipeError(f"ridge_weight: expected a finite number >= 0, got {ridge_weight!r}")
        self.n_components, self.ridge_weight = n_components, float(ridge_weight)
        self.expressions = list(expressions) if expressions else None
        self.mean = self.basis = self.sd = None   # x-bar (3n,), V_k^T (k, 3n), sd (k,)
        self.coef = None                          # (E, k, 3n): B_e of every expression
        self.code_mean = self.disp_mean = None    # (E, k) c-bar_e, (E, 3n) d-bar_e
        self.n_vertices = 0

    # ------------------------------------------------------------------ checks
    def _components_for(self, m: int) -> int:
        if m < 2:
            raise RecipeError(f"n_components: ridge-bs needs at least 2 training neutrals, the training split holds {m}")
        if self.n_components is None:
            return min(DEFAULT_COMPONENTS, m - 1)
        if self.n_components > m - 1:
            raise RecipeError(f"n_components: {self.n_components} components, but the training split holds {m} "
                              f"neutrals, which carry at most {m - 1}")
        return self.n_components

    @staticmethod
    def _neutrals(col) -> np.ndarray:
        j0 = col.shape_index("neutral")
        return np.asarray(col.positions[col.present[:, j0], j0], dtype=np.float64)

    def check_data(self, data) -> None:
        """Raise a RecipeError before any model trains when ``n_components`` is above the
        training neutrals - 1."""
        self._components_for(len(self._neutrals(data.train)))

    # ------------------------------------------------------------------ fitting
    def fit(self, data, ctx=None) -> None:
        """The neutral PCA basis on every training neutral, then one ridge regression per
        expression on the training subjects that have it (``ctx`` is not needed)."""
        col = data.train
        N = self._neutrals(col)
        k = self._components_for(len(N))
        names = [s for s in col.shape_names if s != "neutral"]
        if self.expressions is None:
            self.expressions = [s for s in (data.shapes or names) if s in names] or names
        for e in self.expressions:
            col.shape_index(e)  # an unknown expression: a DataError naming the shapes
        self.n_vertices = int(N.shape[1])
        X = N.reshape(len(N), -1)
        self.mean = X.mean(axis=0)
        _, s, Vt = np.linalg.svd(X - self.mean, full_matrices=False)
        self.basis = np.ascontiguousarray(Vt[:k])
        sd = s[:k] / np.sqrt(len(N) - 1)
        self.sd = np.where(sd > ZERO_VARIANCE * max(float(sd.max()), 1e-300), sd, 0.0)
        j0 = col.shape_index("neutral")
        coef, cm, dm = [], [], []
        for e in self.expressions:
            je = col.shape_index(e)
            ok = col.present[:, j0] & col.present[:, je]
            if not ok.any():
                raise DataError(f"{self.name}: no training subject has both the neutral and {e!r}")
            Ne = np.asarray(col.positions[ok, j0], dtype=np.float64)
            C = self.codes(Ne)
            D = (np.asarray(col.positions[ok, je], dtype=np.float64) - Ne).reshape(len(Ne), -1)
            c0, d0 = C.mean(axis=0), D.mean(axis=0)
            coef.append(ridge(C - c0, D - d0, self.ridge_weight))
            cm.append(c0)
            dm.append(d0)
        # C order, as a state comes back from its file (BLAS rounds by memory layout: a reloaded model is bit-identical)
        self.coef, self.code_mean, self.disp_mean = (np.ascontiguousarray(np.stack(x)) for x in (coef, cm, dm))

    def codes(self, N) -> np.ndarray:
        """(b, n, 3) neutrals -> (b, k) their whitened PCA codes c(x)."""
        X = np.asarray(N, dtype=np.float64).reshape(len(N), -1)
        inv = np.divide(1.0, self.sd, out=np.zeros_like(self.sd), where=self.sd > 0)
        return ((X - self.mean) @ self.basis.T) * inv

    # ------------------------------------------------------------------ the role
    def _check(self, neutrals, expressions) -> np.ndarray:
        if self.coef is None:
            raise RuntimeError(f"{self.name}: used before fit() or load_state_dict()")
        for e in expressions:
            if e not in self.expressions:
                raise DataError(f"{self.name}: not trained for expression {e!r} (trained: {', '.join(self.expressions)})")
        N = np.asarray(neutrals, dtype=np.float64)
        if N.ndim == 2:
            N = N[None]
        if N.ndim != 3 or N.shape[1:] != (self.n_vertices, 3):
            raise DataError(f"{self.name}: neutrals of shape {N.shape[1:]}, trained on ({self.n_vertices}, 3)")
        return N

    def predict(self, neutrals, expression: str, target=None) -> np.ndarray:
        """(b, n, 3) float64 neutrals (evaluation space) -> (b, n, 3) float64 the expression.
        ``target`` (ground truth) is not used: the prediction keeps the neutral's placement."""
        return self.predict_all(neutrals, [expression])[expression]

    def predict_all(self, neutrals, expressions: list[str], target: dict | None = None) -> dict:
        """{expression: (b, n, 3)} for every expression of ``expressions``; the neutrals are coded
        once (``target`` is not used)."""
        N = self._check(neutrals, expressions)
        C = self.codes(N)
        out = {}
        for e in expressions:
            i = self.expressions.index(e)
            D = self.disp_mean[i] + (C - self.code_mean[i]) @ self.coef[i]
            out[e] = N + D.reshape(N.shape)
        return out

    # ------------------------------------------------------------------ saving
    def state_dict(self) -> dict:
        """Arrays, the expression names and plain numbers (fwk saves it as safetensors)."""
        if self.coef is None:
            raise RuntimeError(f"{self.name}: not fitted")
        return {"expressions": list(self.expressions), "mean": self.mean, "basis": self.basis, "sd": self.sd,
                "coef": self.coef, "code_mean": self.code_mean, "disp_mean": self.disp_mean,
                "n_vertices": self.n_vertices, "ridge_weight": self.ridge_weight}

    def load_state_dict(self, d: dict, ctx=None) -> None:
        """Restore a fitted model (``ctx`` is not needed: arrays only)."""
        self.expressions = [str(e) for e in d["expressions"]]
        self.mean, self.basis, self.sd = (np.asarray(d[k], dtype=np.float64) for k in ("mean", "basis", "sd"))
        self.coef = np.asarray(d["coef"], dtype=np.float64)
        self.code_mean = np.asarray(d["code_mean"], dtype=np.float64)
        self.disp_mean = np.asarray(d["disp_mean"], dtype=np.float64)
        self.n_vertices = int(d["n_vertices"])


def ridge(C: np.ndarray, D: np.ndarray, weight: float) -> np.ndarray:
    """argmin_B ||D - C B||_F^2 + weight ||B||_F^2 = (C^T C + weight I)^-1 C^T D, (k x 3n), for
    centred C (m x k) and D (m x 3n); the minimum-norm least-squares solution where singular."""
    A = C.T @ C + weight * np.eye(C.shape[1])
    return np.linalg.lstsq(A, C.T @ D, rcond=None)[0]


@hookimpl
def fwk_register_models():
    return [RidgeBlendshapes]
