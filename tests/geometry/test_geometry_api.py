"""The small geometry services others code against: edges, edge faces and masks, face areas,
vertex normals, the numpy and torch spectral projectors."""
import numpy as np
import pytest
import trimesh

import fwk.geometry as g


def grid(n=4):
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    return np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def test_edge_faces_and_masks_against_loops():
    F = np.vstack([grid(4), [[0, 1, 16]], [[0, 1, 17]]])  # edge (0, 1) gets three faces
    E = g.edges(F, 18)
    EF = g.edge_faces(F, 18)
    ref = {}
    for fi, f in enumerate(F):
        for k in range(3):
            ref.setdefault(tuple(sorted((int(f[k]), int(f[(k + 1) % 3])))), []).append(fi)
    assert len(E) == len(ref)
    for e, ef, bd, it, nm in zip(E.tolist(), EF.tolist(), g.border_edges(F, 18), g.interior_edges(F, 18),
                                 g.non_manifold_edges(F, 18)):
        faces = ref[tuple(e)]
        assert ef[0] == faces[0] and ef[1] == (faces[1] if len(faces) > 1 else -1)
        assert (bd, it, nm) == (len(faces) == 1, len(faces) == 2, len(faces) > 2)


def test_face_areas_and_vertex_normals_against_trimesh():
    m = trimesh.creation.icosphere(subdivisions=2)
    V = np.asarray(m.vertices) * [1.0, 1.4, 0.7]
    F = np.asarray(m.faces)
    t = trimesh.Trimesh(V, F, process=False)
    assert np.allclose(g.face_areas(V, F), t.area_faces, atol=1e-14)
    N = g.vertex_normals(V, F)
    # area-weighted face normals (trimesh weights by angle by default: compare to our own loop)
    ref = np.zeros_like(V)
    for f, n, a in zip(F, t.face_normals, t.area_faces):
        ref[f] += n * a
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    assert np.allclose(N, ref, atol=1e-12)
    assert np.allclose(g.vertex_normals(np.stack([V, 2 * V]), F), np.stack([N, N]), atol=1e-12)
    assert np.allclose(np.linalg.norm(N, axis=1), 1)
    assert np.all(np.einsum("ij,ij->i", N, V) > 0)  # outward on a convex closed surface


def test_projectors_numpy_and_torch_agree():
    torch = pytest.importorskip("torch")
    from fwk.geometry.spectral_torch import TorchSpectralProjector

    m = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    w, U = g.eigenbasis(V, F, 30)
    mass = g.mass_matrix(V, F).diagonal()
    P = np.random.default_rng(0).normal(size=(4, len(V), 3))
    sp_ = g.SpectralProjector(U, mass)
    low = sp_.low(P, 20)
    # against the dense X = U U^T M
    X = U[:, :20] @ (U[:, :20].T * mass)
    assert np.allclose(low, np.einsum("ij,bjk->bik", X, P), atol=1e-12)
    assert np.allclose(sp_.high(P, 20) + low, P)
    tp = TorchSpectralProjector(U, mass, dtype=torch.float64)
    Pt = torch.tensor(P, requires_grad=True)
    out = tp.low(Pt, 20)
    assert np.allclose(out.detach().numpy(), low, atol=1e-12)
    out.pow(2).sum().backward()
    assert Pt.grad is not None and torch.isfinite(Pt.grad).all()
    assert np.allclose(tp.coefficients(Pt, 0, 20).detach().numpy(), sp_.coefficients(P)[:20].reshape(20, 4, 3).transpose(1, 0, 2))
