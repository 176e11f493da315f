"""fwk.rig.nricp against trimesh.registration.nricp_amberg (the same algorithm, another solve):
equal results on a sphere fitted to a bumped, moved copy with landmarks, with and without the
normal weighting; the normal equations' solution against a dense least squares of the stacked
system."""
import numpy as np
import pytest

from fwk.rig.nricp import nricp_amberg


def _case(seed=0, subdivisions=3):
    import trimesh

    rng = np.random.default_rng(seed)
    src = trimesh.creation.icosphere(subdivisions=subdivisions)  # 642 vertices at 3
    V, F = np.asarray(src.vertices), np.asarray(src.faces)
    bump = 1.0 + 0.15 * np.sin(3 * V[:, 0]) * np.cos(2 * V[:, 1])
    target_mesh = trimesh.Trimesh(V * bump[:, None] * [1.2, 0.9, 1.0] + [0.1, -0.2, 0.05], F, process=False)
    pts = np.concatenate([target_mesh.vertices, trimesh.sample.sample_surface(target_mesh, 600, seed=seed)[0]])
    ids = rng.choice(len(V), 8, replace=False)
    return V, F, pts, ids, np.asarray(target_mesh.vertices)[ids]


@pytest.mark.parametrize("steps", [[[0.01, 10, 0.5, 4], [0.02, 5, 0.5, 4], [0.01, 0, 0.0, 4]],
                                   [[0.05, 1.0, 0.0, 5]]])
def test_equals_trimesh(steps):
    import trimesh
    from trimesh.registration import nricp_amberg as reference

    V, F, pts, ids, lm = _case()
    want = reference(trimesh.Trimesh(V.copy(), F, process=False), trimesh.PointCloud(pts.copy()), source_landmarks=ids,
                     target_positions=lm.copy(), steps=steps, eps=0.0, use_faces=False)
    got = nricp_amberg(V, F, pts, ids, lm, steps=steps, eps=0.0)
    size = np.ptp(V, axis=0).max()
    assert np.abs(got - want).max() < 1e-4 * size  # trimesh rounds its weights and targets to float32
    assert np.abs(got - V).max() > 0.05 * size  # and it did move


def test_one_step_solves_the_stacked_least_squares():
    """One iteration without normals: X minimises |alpha (M x G) X|^2 + |W (D X - U)|^2 +
    |beta (D_L X - U_L)|^2, checked against numpy's dense least squares of the stacked system
    built edge by edge (normalised frame)."""
    import trimesh
    from scipy.spatial import cKDTree

    V, F, pts, ids, lm = _case(1, subdivisions=2)  # 162 vertices: a dense system of 648 unknowns
    alpha, beta = 0.3, 2.0
    got = nricp_amberg(V, F, pts, ids, lm, steps=[[alpha, beta, 0.0, 1]], eps=0.0)
    mesh = trimesh.Trimesh(V, F, process=False)
    c, s = mesh.centroid, mesh.scale
    Vn, T, L = (V - c) / s, (pts - c) / s, (lm - c) / s
    n = len(V)
    d, idx = cKDTree(T).query(Vn)
    w = (d <= 0.1).astype(float)
    rows = []
    for a, b in mesh.edges:  # every directed half-edge, weighted by 1 / length, G = I (gamma 1)
        r = np.zeros((4, 4 * n))
        r[:, 4 * a:4 * a + 4] = np.eye(4) / np.linalg.norm(Vn[a] - Vn[b])
        r[:, 4 * b:4 * b + 4] = -np.eye(4) / np.linalg.norm(Vn[a] - Vn[b])
        rows.append(alpha * r)
    Dd = np.zeros((n, 4 * n))
    for i in range(n):
        Dd[i, 4 * i:4 * i + 4] = [*Vn[i], 1.0]
    A = np.vstack(rows + [w[:, None] * Dd, beta * Dd[ids]])
    B = np.vstack([np.zeros((4 * len(mesh.edges), 3)), w[:, None] * T[idx], beta * L])
    X = np.linalg.lstsq(A, B, rcond=None)[0]
    assert np.allclose(got, (Dd @ X) * s + c, atol=1e-8 * s)
