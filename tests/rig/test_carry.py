"""Deformation Transfer onto a scan's triangles (fwk.rig.carry): a zero deformation gives the
scan exactly, a rotation and uniform scale is reproduced exactly on a scan lying on the
registered template, and the sparse solve equals a dense least squares built triangle by
triangle (loops, an orthonormal tangent basis, numpy's lstsq) on a tiny mesh."""
from __future__ import annotations

import numpy as np
import pytest

from fwk.errors import DataError
from fwk.rig.carry import ANCHOR_LENGTH, DeformationCarry
from fwk.rig.register import Registration, closest_points, median_edge


def _rotation(rng) -> np.ndarray:
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    return Q if np.linalg.det(Q) > 0 else -Q


def _grid(k: int, bump: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.meshgrid(np.linspace(0, 1, k), np.linspace(0, 1, k))
    V = np.stack([x.ravel(), y.ravel(), bump * np.sin(3 * x.ravel()) * np.cos(2 * y.ravel())], 1)
    F = np.array([[j * k + i, j * k + i + 1, j * k + i + k] for j in range(k - 1) for i in range(k - 1)]
                 + [[j * k + i + 1, j * k + i + k + 1, j * k + i + k] for j in range(k - 1) for i in range(k - 1)])
    return V, F


def _subdivide(V, F):
    import trimesh

    return trimesh.remesh.subdivide(V, F)


def _registration(Y, F, X, SF, rng, weight=None) -> Registration:
    """A hand-built registration: template Y (F), the scan X (template frame) with triangles SF,
    taken to a scan frame by a rotation, a unit and a translation."""
    R, u, t = _rotation(rng), 0.1, rng.standard_normal(3) * 5
    tri, bary, dist = closest_points(Y, F, X)
    w = np.ones(len(X)) if weight is None else weight
    return Registration(neutral=Y, triangles=F, scan=X @ R.T / u + t, rotation=R, translation=t, unit=u,
                        unit_name=None, triangle=tri, bary=bary, distance=dist / u, weight=w, tolerance=1.0,
                        template_missing=np.zeros(len(Y), bool), template_landmarks=np.arange(5),
                        scan_landmarks=np.zeros((5, 3)), seconds=0.0)


def test_zero_deformation_gives_the_scan_exactly():
    rng = np.random.default_rng(0)
    Y, F = _grid(6)
    X, SF = _subdivide(Y, F)
    X = X + 0.01 * rng.standard_normal(X.shape)  # off the template's surface
    reg = _registration(Y, F, X, SF, rng)
    dc = DeformationCarry(reg, SF)
    assert np.array_equal(dc.carry(Y.copy()), reg.scan) or np.allclose(dc.carry(Y.copy()), reg.scan, atol=1e-12)


@pytest.mark.parametrize("scale", [1.0, 1.3])
def test_a_rotation_and_scale_is_reproduced_exactly_on_the_template(scale):
    rng = np.random.default_rng(1)
    Y, F = _grid(7)
    X, SF = _subdivide(Y, F)
    reg = _registration(Y, F, X, SF, rng)
    A, c = scale * _rotation(rng), np.array([0.3, -0.2, 0.5])
    E = (Y - Y.mean(0)) @ A.T + c  # about the centroid, then moved
    got = DeformationCarry(reg, SF).carry(E)
    want = reg.to_scan((X - Y.mean(0)) @ A.T + c)
    assert np.allclose(got, want, atol=1e-9)
    # the barycentric carry is exact here too (the scan lies on the template); off the surface it
    # is not, and Deformation Transfer's gradients still are: only the anchor pulls it off
    X2 = X + 0.02 * rng.standard_normal(X.shape)
    reg2 = _registration(Y, F, X2, SF, rng)
    want2 = reg2.to_scan((X2 - Y.mean(0)) @ A.T + c)
    err_dt = np.abs(DeformationCarry(reg2, SF).carry(E) - want2).max()
    err_bary = np.abs(reg2.carry(E) - want2).max()
    assert err_dt < err_bary


def test_the_sharp_field_reproduces_any_expression_on_the_template_subdivided_and_permuted():
    """Each scan triangle's centroid lies in its parent template triangle, whose gradient is the
    subdivided expression's there: exact. The smooth field blends neighbours: close, not exact."""
    rng = np.random.default_rng(5)
    Y, F = _grid(6)
    X, SF = _subdivide(Y, F)
    perm = rng.permutation(len(X))
    inv = np.argsort(perm)
    X, SF = X[perm], inv[SF]
    reg = _registration(Y, F, X, SF, rng)
    E = Y + 0.05 * rng.standard_normal(Y.shape)
    want = reg.to_scan(_subdivide(E, F)[0][perm])
    assert np.allclose(DeformationCarry(reg, SF, field="sharp").carry(E), want, atol=1e-9)
    smooth = DeformationCarry(reg, SF).carry(E)
    assert not np.allclose(smooth, want, atol=1e-6)
    moved = np.linalg.norm(want - reg.scan, axis=1).mean()
    assert np.linalg.norm(smooth - want, axis=1).mean() < 0.5 * moved
    with pytest.raises(DataError, match="unknown"):
        DeformationCarry(reg, SF, field="blurry")


def _naive(reg: Registration, SF: np.ndarray, E: np.ndarray) -> np.ndarray:
    """The carry by loops: Sumner gradients per template triangle, their area-weighted mean per
    template vertex, the barycentric blend per scan vertex, the mean per scan triangle, faded, in
    the scan frame; the energy written per triangle in an orthonormal tangent basis (t1, t2):
    sum a_s sum_k |(J_s - M_s) t_k|^2 + mu sum_j m_j |d_j - c_j|^2, J_s t_k from the edges; dense
    least squares."""
    Y, Ft, V = reg.neutral, reg.triangles, reg.scan
    p = len(V)

    def frame(X, f):
        e1, e2 = X[f[1]] - X[f[0]], X[f[2]] - X[f[0]]
        n = np.cross(e1, e2)
        return np.column_stack([e1, e2, n / np.sqrt(np.linalg.norm(n))])

    Qt = [frame(E, f) @ np.linalg.inv(frame(Y, f)) for f in Ft]
    at = [0.5 * np.linalg.norm(np.cross(Y[f[1]] - Y[f[0]], Y[f[2]] - Y[f[0]])) for f in Ft]
    Qv = []
    for i in range(len(Y)):
        around = [t for t, f in enumerate(Ft) if i in f]
        Qv.append(sum(at[t] * Qt[t] for t in around) / sum(at[t] for t in around))
    Qj = [sum(reg.bary[j, k] * Qv[Ft[reg.triangle[j], k]] for k in range(3)) for j in range(p)]
    R = reg.rotation
    h = median_edge(Y, Ft) / reg.unit
    mu = 1.0 / (ANCHOR_LENGTH * h) ** 2
    mass = np.zeros(p)
    rows, rhs = [], []
    for s, f in enumerate(SF):
        e1, e2 = V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]
        n = np.cross(e1, e2)
        a = 0.5 * np.linalg.norm(n)
        for v in f:
            mass[v] += a / 3
        Q = R @ (sum(Qj[v] for v in f) / 3) @ R.T
        Q = np.eye(3) + np.mean([reg.weight[v] for v in f]) * (Q - np.eye(3))
        t1 = e1 / np.linalg.norm(e1)
        t2 = np.cross(n / np.linalg.norm(n), t1)
        for tk in (t1, t2):
            al, be = np.linalg.lstsq(np.column_stack([e1, e2]), tk, rcond=None)[0]  # tk = al e1 + be e2
            target = (Q - np.eye(3)) @ tk
            for c in range(3):  # J tk = al (d1 - d0) + be (d2 - d0), coordinate c
                row = np.zeros(3 * p)
                row[3 * f[1] + c] += al
                row[3 * f[2] + c] += be
                row[3 * f[0] + c] -= al + be
                rows.append(np.sqrt(a) * row)
                rhs.append(np.sqrt(a) * target[c])
    cbar = reg.carry(E) - V
    for j in range(p):
        for c in range(3):
            row = np.zeros(3 * p)
            row[3 * j + c] = np.sqrt(mu * mass[j])
            rows.append(row)
            rhs.append(np.sqrt(mu * mass[j]) * cbar[j, c])
    d = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0]
    return V + d.reshape(p, 3)


def test_the_sparse_solve_equals_a_dense_least_squares():
    rng = np.random.default_rng(2)
    Y, F = _grid(5)
    X, SF = _subdivide(Y, F)
    X = X + 0.01 * rng.standard_normal(X.shape)
    reg = _registration(Y, F, X, SF, rng, weight=rng.uniform(0, 1, len(X)))
    E = Y + 0.05 * rng.standard_normal(Y.shape)
    got = DeformationCarry(reg, SF).carry(E)
    want = _naive(reg, SF, E)
    assert np.allclose(got, want, atol=1e-9), np.abs(got - want).max()
    assert not np.allclose(got, reg.carry(E), atol=1e-4)  # not the barycentric carry


def test_still_parts_degenerate_triangles_and_isolated_vertices():
    rng = np.random.default_rng(3)
    Y, F = _grid(5)
    X, SF = _subdivide(Y, F)
    E = Y + 0.05 * rng.standard_normal(Y.shape)
    # every weight 0 (the template fits nothing): the identity gradients, a zero anchor, no motion
    reg0 = _registration(Y, F, X, SF, rng, weight=np.zeros(len(X)))
    assert np.allclose(DeformationCarry(reg0, SF).carry(E), reg0.scan, atol=1e-12)
    # a degenerate triangle and an isolated vertex: no NaN; the isolated vertex has no gradient
    # term, only its anchor, so it moves exactly as the barycentric carry moves it
    X = np.concatenate([X, [[0.5, 0.5, 0.1]]])
    SF = np.concatenate([SF, [[0, 0, 1]]])
    reg = _registration(Y, F, X, SF, rng)
    got = DeformationCarry(reg, SF).carry(E)
    assert np.all(np.isfinite(got))
    assert np.allclose(got[-1], reg.carry(E)[-1], atol=1e-12)


def test_a_scan_without_triangles_is_refused_in_one_line():
    rng = np.random.default_rng(4)
    Y, F = _grid(4)
    reg = _registration(Y, F, Y.copy(), F, rng)
    with pytest.raises(DataError, match="no triangles") as e:
        DeformationCarry(reg, np.zeros((0, 3), np.int64))
    assert "\n" not in str(e.value)
