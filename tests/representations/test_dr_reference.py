"""dr's deformation gradients against a naive per-vertex reference (issue 17).

The reference below re-implements the energy of fwk_dr's docstring from scratch, one vertex at
a time: cotangent weights by a loop over triangles, vertex normals by a loop, and for every
vertex its own small least-squares problem (9 unknowns, one row per edge coordinate, normal
coordinate and regulariser entry) solved by ``numpy.linalg.lstsq``; the polar decomposition by
the SVD. It shares no code with fwk_dr.
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fwk.data import Template
from fwk.plugins import get_registry

DR = get_registry().get("representation", "dr")


def naive_weights(V, F, floor, ceiling):
    """{(i, j): (cot a + cot b) / 2} for i < j, clamped to [floor x mean |w|, ceiling]."""
    cr = [np.linalg.norm(np.cross(V[b] - V[a], V[c] - V[a])) for a, b, c in F]
    small = 1e-14 * np.mean(cr)
    w = {}
    for (tri, dbl) in zip(F, cr):
        for k in range(3):
            o, i, j = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]
            u, v = V[i] - V[o], V[j] - V[o]
            cot = float(u @ v) / dbl if dbl > small else 0.0
            key = (min(i, j), max(i, j))
            w[key] = w.get(key, 0.0) + cot / 2
    m = np.mean(np.abs(list(w.values())))
    return {k: min(max(x, floor * m), np.inf if ceiling is None else ceiling) for k, x in w.items()}


def naive_normals(V, F):
    N = np.zeros_like(V)
    for a, b, c in F:
        x = np.cross(V[b] - V[a], V[c] - V[a])
        N[a] += x
        N[b] += x
        N[c] += x
    return N / np.linalg.norm(N, axis=1, keepdims=True)


def polar_svd(T):
    U, _, Vt = np.linalg.svd(T)
    d = np.sign(np.linalg.det(U @ Vt))
    R = U @ np.diag([1, 1, d]) @ Vt
    S = R.T @ T
    return R, (S + S.T) / 2


def naive_gradients(ref, P, F, normal_weight=0.1, weight_floor=1e-3, weight_ceiling=10.0, regularisation=1e-2):
    """T_i (n, 3, 3) minimising the energy of fwk_dr's docstring, vertex by vertex."""
    n = len(ref)
    w = naive_weights(ref, F, weight_floor, weight_ceiling)
    nbrs = [[] for _ in range(n)]
    for (i, j), x in w.items():
        nbrs[i].append((j, x))
        nbrs[j].append((i, x))
    n0, n1 = naive_normals(ref, F), naive_normals(P, F)
    kappa = np.array([sum(x * (ref[i] - ref[j]) @ (ref[i] - ref[j]) for j, x in nbrs[i]) for i in range(n)])
    kappa1 = np.array([sum(x * (P[i] - P[j]) @ (P[i] - P[j]) for j, x in nbrs[i]) for i in range(n)])
    m = regularisation * np.median(kappa[kappa > 0])
    mus = [m * m / (kappa[i] + 1e-12 * m) for i in range(n)]  # mu_i = (tau kappa~)^2 / kappa_i
    lam = np.array([normal_weight * kappa[i] / len(nbrs[i]) for i in range(n)])
    s = np.sqrt(kappa1 / kappa)
    B = np.zeros((n, 3, 3))
    for i in range(n):
        for j, x in nbrs[i]:
            B[i] += x * np.outer(P[i] - P[j], ref[i] - ref[j])
        B[i] += lam[i] * s[i] * np.outer(n1[i], n0[i])
    T = np.zeros((n, 3, 3))
    for i in range(n):
        rows, rhs = [], []

        def add(weight, vec, target, a):  # sqrt(weight) (T[a] . vec - target)
            r = np.zeros(9)
            r[3 * a:3 * a + 3] = vec
            rows.append(np.sqrt(weight) * r)
            rhs.append(np.sqrt(weight) * target)
        for j, x in nbrs[i]:
            for a in range(3):
                add(x, ref[i] - ref[j], (P[i] - P[j])[a], a)
        for a in range(3):
            add(lam[i], n0[i], s[i] * n1[i][a], a)
        mu = mus[i]
        if m > 0:
            hood = [i] + [j for j, _ in nbrs[i]]
            Rbar, _ = polar_svd(sum(B[k] for k in hood))
            sbar = np.sqrt(sum(kappa1[k] for k in hood) / sum(kappa[k] for k in hood))
            for a in range(3):
                for c in range(3):
                    e = np.zeros(3)
                    e[c] = 1.0
                    add(mu, e, sbar * Rbar[a, c], a)
        t, *_ = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)
        T[i] = t.reshape(3, 3)
    return T


def naive_features(T):
    out = []
    for Ti in T:
        R, S = polar_svd(Ti)
        iu = np.triu_indices(3)
        out.append(np.concatenate([Rotation.from_matrix(R).as_rotvec(), (S - np.eye(3))[iu]]))
    return np.array(out)


@pytest.fixture(scope="module")
def head():
    col = get_registry().get("dataset", "synthetic-heads")(n_subjects=2, n_vertices=300).load(None)
    V = np.asarray(col.positions[0, 0])
    V = (V - V.mean(0)) / np.abs(V - V.mean(0)).max()
    return V, Template(V, col.template.triangles)


def smooth_deformation(V, seed, amplitude=0.05):
    """A random smooth (band-limited) displacement field, then a random rotation, scale and shift."""
    rng = np.random.default_rng(seed)
    D = np.zeros_like(V)
    for _ in range(4):
        k = rng.normal(size=3) * 2.0
        D += amplitude * rng.normal(size=3) * np.sin(V @ k + rng.uniform(0, 2 * np.pi))[:, None]
    Q = Rotation.random(random_state=seed).as_matrix()
    return rng.uniform(0.8, 1.3) * (V + D) @ Q.T + rng.normal(size=3)


@pytest.mark.parametrize("regularisation,weight_ceiling", [(1e-2, 10.0), (0.0, None), (0.1, 10.0)])
@pytest.mark.parametrize("seed", [0, 1])
def test_gradients_equal_the_naive_reference(head, seed, regularisation, weight_ceiling):
    V, t = head
    P = smooth_deformation(V, seed)
    r = DR(scaling="none", regularisation=regularisation, weight_ceiling=weight_ceiling)
    r.fit(V[None], None, t)
    F = r.raw_features(P[None])[0]
    G = naive_features(naive_gradients(V, P, t.triangles, weight_ceiling=weight_ceiling,
                                       regularisation=regularisation))
    assert np.abs(F - G).max() < 1e-8


def test_regularisation_vanishes_where_the_mesh_is_well_conditioned(head):
    """Against the thesis's energy (eq. 2.5 with the normal guard; no Tikhonov term, no weight
    ceiling), naive: on a well-shaped mesh the default moves each rotation by under 1 % of the
    deformation's largest local rotation (its docstring's bound: 60 tau^2 = 0.6 % for a typical
    one-ring)."""
    V, t = head
    for seed in range(3):
        P = smooth_deformation(V, seed)
        r = DR(scaling="none")
        r.fit(V[None], None, t)
        Rm = Rotation.from_rotvec(r.raw_features(P[None])[0, :, :3])
        R0 = Rotation.from_rotvec(naive_features(naive_gradients(V, P, t.triangles, weight_ceiling=None,
                                                                 regularisation=0.0))[:, :3])
        moved = (Rm.inv() * R0).magnitude()
        local = (R0.mean().inv() * R0).magnitude()  # each vertex's rotation against the mesh's mean one
        assert moved.max() < 0.01 * local.max()
        assert np.median(moved) < 1e-3 * local.max()


def test_similarity_transforms_exactly(head):
    V, t = head
    r = DR(scaling="none")
    r.fit(V[None], None, t)
    assert np.abs(r.raw_features(V[None])).max() < 1e-12  # the reference encodes to zero
    for seed in range(3):
        rng = np.random.default_rng(seed)
        Q = Rotation.random(random_state=seed)
        s = rng.uniform(0.5, 2.0)
        P = s * V @ Q.as_matrix().T + rng.normal(size=3)
        F = r.raw_features(P[None])[0]
        assert np.abs(F[:, :3] - Q.as_rotvec()).max() < 1e-10
        assert np.abs(F[:, 3:] - (s - 1) * np.array([1, 0, 0, 1, 0, 1])).max() < 1e-10
        assert np.abs(r.decode(F[None], None, P[None])[0] - P).max() < 1e-10


def test_smooth_deformations_round_trip(head):
    V, t = head
    r = DR(scaling="none")
    r.fit(V[None], None, t)
    for seed in range(3):
        P = smooth_deformation(V, seed, amplitude=0.03)
        X = r.decode(r.raw_features(P[None]), None, P[None])[0]
        Pr = P - P.mean(0)
        assert np.abs(X - P).max() < 0.01 * np.abs(Pr).max()


def test_polar_equals_the_svd_matrix_by_matrix():
    """fwk_dr.polar (Newton on contiguous components) against polar_svd one matrix at a time:
    near-rotations, strong stretches, and det <= 0 (a reflection, a singular matrix: the SVD
    branch, det R = +1); any batch shape."""
    import fwk_dr

    rng = np.random.default_rng(3)
    T = np.eye(3) + 0.3 * rng.standard_normal((4, 5, 3, 3))
    T[0, 0] = np.diag([1.0, 1.0, -1.0])                       # a reflection
    T[0, 1] = np.outer([1.0, 2.0, 0.5], [0.3, -1.0, 2.0])      # rank one
    T[1, 2] = np.diag([5.0, 0.2, 1.0]) @ T[1, 2]              # a strong stretch
    R, S = fwk_dr.polar(T)
    assert R.shape == S.shape == T.shape
    for idx in np.ndindex(4, 5):
        Rr, Sr = polar_svd(T[idx])
        if np.linalg.det(T[idx]) > 1e-12:
            assert np.allclose(R[idx], Rr, atol=1e-12) and np.allclose(S[idx], Sr, atol=1e-12)
        assert np.allclose(R[idx] @ R[idx].T, np.eye(3), atol=1e-12) and np.linalg.det(R[idx]) > 0
        assert np.allclose(S[idx], S[idx].T)
