"""DAME, FMPD and the point-wise metrics against naive loops, and their properties."""
import math

import numpy as np
import pytest

from fwk.data import Template
from fwk.plugins import get_registry
from fwk.testing.metric import small_mesh

REG = get_registry()


def icosphere(sub=2):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub)
    return np.asarray(m.vertices, float), Template(np.asarray(m.vertices), np.asarray(m.faces))


def naive_pointwise(P, T):
    n = len(P)
    l1 = sum(abs(P[i, k] - T[i, k]) for i in range(n) for k in range(3)) / (3 * n)
    l2 = sum((P[i, k] - T[i, k]) ** 2 for i in range(n) for k in range(3)) / (3 * n)
    eu = sum(math.dist(P[i], T[i]) for i in range(n)) / n
    return l1, l2, eu


def test_pointwise_naive():
    V, t = small_mesh()
    P = V + np.random.default_rng(0).normal(0, 0.1, V.shape)
    ref = naive_pointwise(P, V)
    for name, r in zip(("l1", "l2", "euclidean"), ref):
        s, _ = REG.get("metric", name)()(P[None], V[None], t)
        assert s[0] == pytest.approx(r, rel=1e-12)


def naive_dame(P, T, F, mask_scale=0.1):
    """Per-edge loops: find each interior edge's two faces by scanning all faces."""
    def normal(V, f):
        n = np.cross(V[f[1]] - V[f[0]], V[f[2]] - V[f[0]])
        return n / np.linalg.norm(n), 0.5 * np.linalg.norm(n)

    edges = {}
    for fi, f in enumerate(F):
        for k in range(3):
            a, b = int(f[(k + 1) % 3]), int(f[(k + 2) % 3])
            edges.setdefault(tuple(sorted((a, b))), []).append((fi, a, b))
    phi = {}
    for V, tag in ((T, "t"), (P, "p")):
        for key, uses in edges.items():
            if len(uses) != 2 or uses[0][1] != uses[1][2]:
                continue
            (f1, a, b), (f2, _, _) = uses
            n1, _ = normal(V, F[f1])
            n2, _ = normal(V, F[f2])
            e = (V[b] - V[a]) / np.linalg.norm(V[b] - V[a])
            phi[(key, tag)] = math.atan2(np.dot(np.cross(n1, n2), e), np.dot(n1, n2))
    interior = [k for k in edges if (k, "t") in phi]
    face_edges = {fi: [] for fi in range(len(F))}
    for key, uses in edges.items():
        for fi, _, _ in uses:
            face_edges[fi].append(key)
    num = den = 0.0
    per_vertex = {i: [] for i in range(len(T))}
    for key in interior:
        d = phi[(key, "p")] - phi[(key, "t")]
        d = math.atan2(math.sin(d), math.cos(d))
        (f1, _, _), (f2, _, _) = edges[key]
        rough = []
        for fi in (f1, f2):
            rough.append(np.mean([abs(phi[(k, "t")]) if (k, "t") in phi else 0.0 for k in face_edges[fi]]))
        m = abs(d) / (1 + np.mean(rough) / mask_scale)
        w = 0.5 * (normal(T, F[f1])[1] + normal(T, F[f2])[1])
        num += w * m
        den += w
        per_vertex[key[0]].append(m)
        per_vertex[key[1]].append(m)
    return num / den, np.array([np.mean(v) if v else 0.0 for v in per_vertex.values()])


def test_dame_naive():
    V, t = icosphere(1)
    P = V + np.random.default_rng(3).normal(0, 0.02, V.shape)
    s, vm = REG.get("metric", "dame")()(P[None], V[None], t)
    ref_s, ref_vm = naive_dame(P, V, t.triangles)
    assert s[0] == pytest.approx(ref_s, rel=1e-10)
    assert np.allclose(vm[0], ref_vm, atol=1e-12)


def test_dame_ignores_border_edges():
    V, t = small_mesh()  # open grid: border edges present
    P = V.copy()
    s0, _ = REG.get("metric", "dame")()(P[None], V[None], t)
    ref, _ = naive_dame(P, V, t.triangles)
    assert s0[0] == 0 and ref == 0


def naive_fmpd_roughness(V, F):
    n = len(V)
    ang_sum = np.zeros(n)
    W = {}
    area = np.zeros(n)
    edge_faces = {}
    for f in F:
        for k in range(3):
            i, j, l = f[k], f[(k + 1) % 3], f[(k + 2) % 3]
            u, v = V[j] - V[i], V[l] - V[i]
            a = math.atan2(np.linalg.norm(np.cross(u, v)), np.dot(u, v))
            ang_sum[i] += a
            key = tuple(sorted((int(j), int(l))))
            # each corner's cot/2 clamped before the corners of an edge are summed (authors' code)
            W[key] = W.get(key, 0.0) + min(max(0.5 / math.tan(a), 0.001), 1000)
            edge_faces[key] = edge_faces.get(key, 0) + 1
        A = 0.5 * np.linalg.norm(np.cross(V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]))
        for k in range(3):
            area[f[k]] += A / 3
    border = np.zeros(n, bool)
    for (i, j), c in edge_faces.items():
        if c == 1:
            border[i] = border[j] = True
    K = np.abs(np.where(border, math.pi, 2 * math.pi) - ang_sum)
    R = np.zeros(n)
    for i in range(n):
        d = s = 0.0
        for (a, b), w in W.items():
            if a == i:
                d += w
                s += w * K[b]
            elif b == i:
                d += w
                s += w * K[a]
        R[i] = abs((d * K[i] - s) / d)
    return R, area


def test_fmpd_naive():
    from fwk_fmpd import EPS, EXP

    V, t = icosphere(1)
    P = V + np.random.default_rng(4).normal(0, 0.03, V.shape)
    R1, a1 = naive_fmpd_roughness(V, t.triangles)
    R2, a2 = naive_fmpd_roughness(P, t.triangles)
    rb1, rb2 = (R1 * a1).sum() / a1.sum(), (R2 * a2).sum() / a2.sum()
    lo = min(rb1, rb2)
    rmax, tt = max(0.2, 5 * lo), max(lo, EPS)

    def mod(R):
        out = []
        T = tt ** EXP - EPS ** EXP
        for r in R:
            x = min(max(r, EPS), rmax) ** EXP - EPS ** EXP
            out.append((x - T) * 0.5 + T if x > T else x)
        return np.array(out)

    g1, g2 = (mod(R1) * a1).sum() / a1.sum(), (mod(R2) * a2).sum() / a2.sum()
    ref = min(1.0, 8 * abs(g1 - g2))
    s, _ = REG.get("metric", "fmpd")()(P[None], V[None], t)
    assert s[0] == pytest.approx(ref, rel=1e-10)


@pytest.mark.parametrize("name", ["dame", "fmpd"])
def test_local_bump_changes_only_nearby_vertices(name):
    V, t = icosphere(3)
    i0 = 0
    d = np.linalg.norm(V - V[i0], axis=1)
    P = V + (0.05 * np.clip(1 - (d / 0.2) ** 2, 0, None) ** 2)[:, None] * V  # compact support
    _, vm = REG.get("metric", name)()(P[None], V[None], t)
    far = d > 0.6
    assert vm[0][far].max() == 0
    assert vm[0][d < 0.2].max() > 0


@pytest.mark.parametrize("name", ["l1", "dame", "fmpd"])
def test_more_noise_scores_higher_on_average(name):
    V, t = icosphere(3)
    rng = np.random.default_rng(5)
    m = REG.get("metric", name)()
    means = []
    for sigma in (0.0005, 0.002, 0.008):
        P = np.stack([V + rng.normal(0, sigma, V.shape) for _ in range(4)])
        means.append(m(P, np.stack([V] * 4), t)[0].mean())
    assert means[0] < means[1] < means[2]


def naive_fmpd(P, T, F):
    """Score and per-vertex map from the loop roughness above (steps 3-5 in plain Python)."""
    from fwk_fmpd import EPS, EXP

    R1, a1 = naive_fmpd_roughness(T, F)
    R2, a2 = naive_fmpd_roughness(P, F)
    rb1, rb2 = (R1 * a1).sum() / a1.sum(), (R2 * a2).sum() / a2.sum()
    lo = min(rb1, rb2)
    rmax, tt = max(0.2, 5 * lo), max(lo, EPS)
    thr = tt ** EXP - EPS ** EXP

    def mod(r):
        x = min(max(r, EPS), rmax) ** EXP - EPS ** EXP
        return (x - thr) * 0.5 + thr if x > thr else x

    M1 = np.array([mod(r) for r in R1])
    M2 = np.array([mod(r) for r in R2])
    g1, g2 = (M1 * a1).sum() / a1.sum(), (M2 * a2).sum() / a2.sum()
    return min(1.0, 8 * abs(g1 - g2)), 8 * np.abs(M1 - M2)


def test_fmpd_naive_open_mesh_and_map():
    """Border vertices use c = pi; the per-vertex map matches the loops too."""
    V, t = small_mesh()
    P = V + np.random.default_rng(6).normal(0, 0.01, V.shape)
    ref_s, ref_m = naive_fmpd(P, V, t.triangles)
    s, m = REG.get("metric", "fmpd")()(P[None], V[None], t)
    assert s[0] == pytest.approx(ref_s, rel=1e-10)
    assert np.allclose(m[0], ref_m, rtol=1e-9, atol=1e-12)


def test_fmpd_batch_of_two_targets():
    V, t = icosphere(1)
    rng = np.random.default_rng(7)
    T = np.stack([V, V * [1.0, 1.2, 0.9]])
    P = T + rng.normal(0, 0.02, T.shape)
    s, _ = REG.get("metric", "fmpd")()(P, T, t)
    for i in range(2):
        assert s[i] == pytest.approx(naive_fmpd(P[i], T[i], t.triangles)[0], rel=1e-10)


def test_dame_ignores_non_manifold_and_flipped_edges():
    """An edge with three faces, and one whose two faces disagree in orientation, are skipped;
    moving only the vertex that creates them changes nothing that the naive loop would count."""
    V, t = icosphere(1)
    F = t.triangles.copy()
    F[0] = F[0][::-1]  # flip one face: its three edges become inconsistently oriented
    e = F[5][:2]
    extra = np.vstack([V, V[e].mean(0) + 0.3 * V[e].mean(0)])
    F = np.vstack([F, [e[0], e[1], len(V)]])  # a third face on one edge: non-manifold
    tt = Template(extra, F)
    P = extra + np.random.default_rng(8).normal(0, 0.02, extra.shape)
    s, vm = REG.get("metric", "dame")()(P[None], extra[None], tt)
    ref_s, ref_vm = naive_dame(P, extra, F)
    assert s[0] == pytest.approx(ref_s, rel=1e-10)
    assert np.allclose(vm[0], ref_vm, atol=1e-12)
    assert vm[0][len(V)] == 0  # the extra vertex has no interior manifold edge


def test_dame_visibility_none_is_the_plain_edge_mean():
    V, t = icosphere(1)
    P = V + np.random.default_rng(9).normal(0, 0.02, V.shape)
    s, vm = REG.get("metric", "dame")(visibility="none")(P[None], V[None], t)
    # with equal weights the score is the mean over edges of the masked error; a vertex's map
    # value is the mean over its edges, so the degree-weighted mean of the map equals the score
    import fwk_dame

    ang, _ = fwk_dame.oriented_dihedral(V, t)
    deg = np.bincount(t.edges.ravel(), minlength=len(V))
    assert (vm[0] * deg).sum() / deg.sum() == pytest.approx(s[0], rel=1e-10)
    assert ang.shape[1] == len(t.edges)  # a closed sphere: every edge is interior


def test_wrap_range():
    from fwk_dame import wrap

    x = np.array([-np.pi, np.pi, 3 * np.pi, 0.5, -0.5 - 2 * np.pi, 7.0])
    w = wrap(x)
    assert np.all(w > -np.pi) and np.all(w <= np.pi)
    assert np.allclose(np.cos(w), np.cos(x)) and np.allclose(np.sin(w), np.sin(x))
    assert w[0] == pytest.approx(np.pi) and w[1] == pytest.approx(np.pi)


def test_topology_structures_are_reused():
    import fwk_dame
    import fwk_fmpd

    V, t = icosphere(2)
    t2 = Template(V.copy(), t.triangles.copy())  # another object with the same topology
    assert fwk_dame._prep(t) is fwk_dame._prep(t2)
    assert fwk_fmpd._prep(t) is fwk_fmpd._prep(t2)


@pytest.mark.parametrize("name", ["dame", "fmpd"])
def test_invariant_on_a_head_sized_mesh(name):
    """Rigid motion and uniform scale on a finer, irregular mesh (float64 round-off only)."""
    from scipy.spatial.transform import Rotation

    V, t = icosphere(3)
    V = V * [1.0, 1.3, 0.9]
    rng = np.random.default_rng(10)
    P = V + rng.normal(0, 0.01, V.shape)
    R = Rotation.from_rotvec([0.4, -1.2, 2.0]).as_matrix()
    m = REG.get("metric", name)()
    s1, m1 = m(P[None], V[None], t)
    s2, m2 = m((0.01 * P @ R.T - 5)[None], (0.01 * V @ R.T - 5)[None], t)
    assert s2[0] == pytest.approx(s1[0], rel=1e-7)
    assert np.allclose(m1, m2, rtol=1e-6, atol=1e-9)


def test_as_pair_and_in_chunks():
    import numpy as np
    import pytest

    from fwk.evaluation.core import as_pair, in_chunks

    a, b = as_pair(np.ones((5, 3), np.float32), np.zeros((5, 3)))
    assert a.shape == b.shape == (1, 5, 3) and a.dtype == b.dtype == np.float64
    with pytest.raises(ValueError, match=r"\(1, 5, 3\).*\(1, 4, 3\)"):
        as_pair(np.ones((5, 3)), np.ones((4, 3)))
    P, T = np.random.default_rng(0).normal(size=(2, 7, 9, 3))
    fn = lambda p, t: (np.abs(p - t).mean((1, 2)), np.abs(p - t).mean(2))  # noqa: E731
    whole = fn(P, T)
    for size in (1, 2, 3, 7, 10):
        s, m = in_chunks(fn, P, T, size)
        np.testing.assert_array_equal(s, whole[0])
        np.testing.assert_array_equal(m, whole[1])
    s, m = in_chunks(fn, P[:0], T[:0], 2)
    assert s.shape == (0,) and m.shape == (0, 9)
