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
            W[key] = W.get(key, 0.0) + 0.5 / math.tan(a)
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
            w = min(max(w, 0.001), 1000)
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
