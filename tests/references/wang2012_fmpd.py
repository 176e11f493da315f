"""A literal port of the authors' FMPD code, as a test reference.

Source: ``PScan3Dcompare/Wang_perceptual_distance.m`` in psapirstein/mesh-comparing (a copy of
Wang, Torkhani & Montanvert's MATLAB code for "A fast roughness-based approach to the assessment
of 3D mesh visual quality", Computers & Graphics 2012). Not fast; not used by fwk itself:
``fwk_fmpd`` must agree with it (tests/metrics/test_fmpd_reference.py).

Translated line by line, loops where the MATLAB loops. Each translation choice:

* inputs: V (n, 3) and F (m, 3) 0-based, as ``scn.Vs`` / ``scn.F3s`` (1-based there); transposed
  to (3, n) / (3, m) inside, as the MATLAB does (``scn1.Vs'``);
* corner indices: MATLAB's ``i1 = mod(i-1,3)+1``, ``i2 = mod(i,3)+1``, ``i3 = mod(i+1,3)+1``
  for i = 1..3 become 0-based ``(i-1) % 3, i % 3, (i+1) % 3``: corner i1's angle, between
  pp = V(i2) - V(i1) and qq = V(i3) - V(i1), weights the edge (i2, i3) opposite it;
* ``pp_length(pp_length < 1e-10) = 1`` (no normalisation of a near-zero edge), then the cosine
  of the normalised vectors, clamped to [-1, 1], and ``acos`` of it, as written;
* ``cot`` is MATLAB's / Octave's ``1 ./ tan(x)``: cot(0) = Inf and cot(pi) = -8.2e15, which the
  clamp of each corner's cot/2 to [0.001, 1000] turns into 1000 and 0.001;
* the ``eval``-generated variables ``ctan_1..3``, ``ii_lap_1..3``, ``jj_lap_1..3`` are dicts;
* ``sparse(i, j, s, n, n)`` is ``scipy.sparse.csr_matrix((s, (i, j)), shape=(n, n))``: both sum
  duplicate entries, so an edge's weight is the sum of its (already clamped) corners;
* ``sum(laplacian, 1)`` (column sums) is ``sum(axis=0)``; ``spdiags(A, 0)`` and ``spdiags(Mass)``
  (a diagonal matrix has no other diagonal) are ``A.diagonal()``;
* the face area comes from the i == 1 pass, ``|crossinline(pp', -qq')| / 2`` = ``np.cross``;
* the border: ``I = find(adja' ~= 0); I = I(adja(I) == 0)`` selects, by one linear index into
  both matrices, the positions (r, c) where adja(c, r) != 0 and adja(r, c) == 0 (a directed
  half-edge c -> r without its reverse); both ends are flagged. Translated as a loop over the
  nonzeros (r, c) of adja' testing adja(r, c) == 0; ``adja`` sums face numbers (1..m, all
  positive), so a present half-edge is never 0;
* ``abs(cGauss)' * Lapl`` (a row) is ``Lapl.T @ |cGauss|``, divided by the Laplacian's diagonal;
  a vertex in no triangle gives 0/0 = NaN there, as in MATLAB;
* MATLAB's ``max`` / ``min`` ignore NaN: the ``clamp`` helper is ``fmin(fmax(x, a), b)`` and
  ``min(cGaussRmean)``, ``max(0.20, ...)``, ``max(threshold, ...)`` are ``fmin`` / ``fmax``
  (this matters only when a vertex is in no triangle: its NaN roughness makes both mean
  roughnesses NaN, so R_max = 0.2 and the threshold = 0.0005, and it is clamped to 0.0005);
* ``if distance > 1, distance = 1`` keeps a NaN, as written.

Checked against the MATLAB file itself run under GNU Octave 7.3.0
(``tests/references/check_against_octave.py``): FMPD equal to <= 7e-13 relative on 14 meshes
(grids, spheres, open caps, synthetic heads, ICT-FaceKit pairs, coincident vertices, a flipped
face, a non-manifold edge, an unreferenced vertex).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def _clamp(x, a=0.0, b=1.0):
    """MATLAB's ``clamp`` helper: min(max(x, a), b), where MATLAB's max/min ignore NaN (fmax/fmin)."""
    return np.fmin(np.fmax(x, a), b)


def compute_perception_quantities(Vs: np.ndarray, F3s: np.ndarray):
    """Vs (3, n) vertices, F3s (3, m) 0-based faces -> (cgauss (n,), laplacian (n, n), mass (n, n))."""
    n = Vs.shape[1]
    m = F3s.shape[1]
    sum_angles = np.zeros(n)
    epsilon = 1e-10
    ctan, ii_lap, jj_lap = {}, {}, {}
    area = None
    for i in range(1, 4):
        i1 = (i - 1) % 3
        i2 = i % 3
        i3 = (i + 1) % 3
        pp = Vs[:, F3s[i2, :]] - Vs[:, F3s[i1, :]]
        qq = Vs[:, F3s[i3, :]] - Vs[:, F3s[i1, :]]
        pp_length = np.sqrt(np.sum(pp ** 2, axis=0))
        qq_length = np.sqrt(np.sum(qq ** 2, axis=0))
        pp_length[pp_length < epsilon] = 1
        qq_length[qq_length < epsilon] = 1
        pp_nor = pp / np.tile(pp_length, (3, 1))
        qq_nor = qq / np.tile(qq_length, (3, 1))
        cos_ang = np.sum(pp_nor * qq_nor, axis=0)
        cos_ang = _clamp(cos_ang, -1, 1)
        ang = np.arccos(cos_ang)
        with np.errstate(divide="ignore"):
            c = (1.0 / np.tan(ang)) / 2.0                   # cot(ang) / 2; MATLAB's cot is 1 ./ tan
        ctan[i] = _clamp(c, 0.001, 1000)                    # clamped per corner
        ii_lap[i] = F3s[i2, :]
        jj_lap[i] = F3s[i3, :]
        for j in range(m):                                  # accumulate the angles on vertices
            sum_angles[F3s[i1, j]] += ang[j]
        if i == 1:
            rr = np.cross(pp.T, -qq.T).T
            area = np.sqrt(np.sum(rr ** 2, axis=0)) / 2.0
    ii = np.concatenate([ii_lap[1], jj_lap[1], ii_lap[2], jj_lap[2], ii_lap[3], jj_lap[3]])
    jj = np.concatenate([jj_lap[1], ii_lap[1], jj_lap[2], ii_lap[2], jj_lap[3], ii_lap[3]])
    ss = np.concatenate([ctan[1], ctan[1], ctan[2], ctan[2], ctan[3], ctan[3]])
    laplacian = sp.csr_matrix((ss, (ii, jj)), shape=(n, n))
    diag_laplacian = np.asarray(laplacian.sum(axis=0)).ravel()
    laplacian = (sp.diags(diag_laplacian) - laplacian).tocsr()

    ii_mass = np.concatenate([F3s[0], F3s[1], F3s[2]])
    area = area / 3.0
    mass = sp.csr_matrix((np.concatenate([area, area, area]), (ii_mass, ii_mass)), shape=(n, n))

    # facet-edge adjacency: adja(i, j) = (sum of) facet numbers (1-based) of the directed edge i -> j
    ii_adja = np.concatenate([F3s[0], F3s[1], F3s[2]])
    jj_adja = np.concatenate([F3s[1], F3s[2], F3s[0]])
    ss_adja = np.concatenate([np.arange(1, m + 1)] * 3).astype(float)
    adja = sp.csr_matrix((ss_adja, (ii_adja, jj_adja)), shape=(n, n)).todok()
    # add missing points: where adja' ~= 0 and adja == 0, set -1
    At = adja.transpose().tocoo()
    flag_boundary = np.zeros(n, dtype=bool)
    for r, c in zip(At.row, At.col):
        if adja.get((r, c), 0) == 0:
            flag_boundary[r] = True
            flag_boundary[c] = True
    constants = np.full(n, 2 * np.pi)
    constants[flag_boundary] = np.pi
    cgauss = constants - sum_angles
    return cgauss, laplacian, mass


def compute_roughness(cGauss, Lapl, Mass, SurfA):
    cGaussRough = Lapl.T @ np.abs(cGauss)                   # abs(cGauss)' * Lapl, as a column
    with np.errstate(divide="ignore", invalid="ignore"):  # 0/0 = NaN at unreferenced vertices
        cGaussRough = cGaussRough / Lapl.diagonal()
    cGaussRough = np.abs(cGaussRough)
    cGaussRmean = cGaussRough @ Mass.diagonal() / SurfA
    return cGaussRough, cGaussRmean


def modulate_roughness(cGaussRough, MMrough, threshold):
    a, b, epsilon = 0.15, 0.5, MMrough[0]
    cGRout = _clamp(cGaussRough, epsilon, MMrough[1])
    cGRout = cGRout ** a - epsilon ** a
    turnpoint = threshold ** a - epsilon ** a
    above = cGRout > turnpoint
    cGRout[above] = (cGRout[above] - turnpoint) * b + turnpoint
    return cGRout


def perceptual_distance(V1: np.ndarray, F1: np.ndarray, V2: np.ndarray, F2: np.ndarray | None = None) -> float:
    """FMPD between two triangle meshes: V (n, 3), F (m, 3) 0-based (F2 defaults to F1)."""
    return wang_perceptual_distance(V1, F1, V2, F2)[0]


def wang_perceptual_distance(V1, F1, V2, F2=None):
    """``[distance, cGaussRough1, cGaussRough2] = Wang_perceptual_distance(scn1, scn2)``:
    FMPD and the two meshes' local roughness (n,) before the modulation."""
    F2 = F1 if F2 is None else F2
    cGauss1, Lapl1, Mass1 = compute_perception_quantities(np.asarray(V1, float).T, np.asarray(F1).T)
    cGauss2, Lapl2, Mass2 = compute_perception_quantities(np.asarray(V2, float).T, np.asarray(F2).T)
    SurfA = [Mass1.diagonal().sum(), Mass2.diagonal().sum()]
    r1, m1 = compute_roughness(cGauss1, Lapl1, Mass1, SurfA[0])
    r2, m2 = compute_roughness(cGauss2, Lapl2, Mass2, SurfA[1])
    lo = np.fmin(m1, m2)                                   # MATLAB min(cGaussRmean): NaN ignored
    minmaxrough = [0.0005, np.fmax(0.20, 5.0 * lo)]
    threshold = np.fmax(lo, minmaxrough[0])
    mod1 = modulate_roughness(r1, minmaxrough, threshold)
    mod2 = modulate_roughness(r2, minmaxrough, threshold)
    sum_first = mod1 @ Mass1.diagonal() / SurfA[0]
    sum_second = mod2 @ Mass2.diagonal() / SurfA[1]
    distance = 8.0 * abs(sum_first - sum_second)
    if distance > 1:                                      # NaN stays NaN, as in MATLAB
        distance = 1.0
    return float(distance), r1, r2
