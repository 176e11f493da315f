import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from fwk.data import Template
from fwk.plugins import get_registry
from fwk.testing.representation import RepresentationContract

DR = get_registry().get("representation", "dr")


@pytest.mark.parametrize("scaling", ["none", "std", "norm"])
class TestDRContract(RepresentationContract):
    component = DR
    # small_batch adds independent per-vertex noise (not a smooth deformation): its gradients are not
    # integrable, so DR returns the least-squares surface; exact and smooth cases are tested below
    atol = 3e-2

    @pytest.fixture(autouse=True)
    def _params(self, scaling):
        self.params = {"scaling": scaling}

    def test_channels(self):
        assert self.component.channels == 9


def sphere(sub=3):
    m = trimesh.creation.icosphere(subdivisions=sub)
    V = np.asarray(m.vertices) * [1.0, 1.2, 0.9]
    return V, Template(V, np.asarray(m.faces))


def test_similarity_transforms_round_trip_exactly():
    V, t = sphere()
    r = DR(scaling="none")
    r.fit(V[None], None, t)
    R = Rotation.from_euler("xyz", [0.4, -0.3, 1.2]).as_matrix()
    Q = 1.7 * V @ R.T + [3.0, -1.0, 2.0]
    F = r.raw_features(Q[None])
    assert np.allclose(F[0, :, :3], Rotation.from_matrix(R).as_rotvec(), atol=1e-10)  # log R everywhere
    assert np.allclose(F[0, :, 3:], [0.7, 0, 0, 0.7, 0, 0.7], atol=1e-10)  # S - I = 0.7 I
    assert np.abs(r.decode(F, target=Q[None])[0] - Q).max() < 1e-10
    # without ground truth (generation) the shape comes back rigidly registered to the reference
    X = r.decode(F)[0]
    from fwk.geometry import kabsch

    Rq, tq = kabsch(Q, V)
    assert np.abs(X - (Q @ Rq.T + tq)).max() < 1e-10


def test_smooth_deformation_within_bound():
    V, t = sphere(4)
    r = DR(scaling="none")
    r.fit(V[None], None, t)
    a = 0.3 * V[:, 1]
    Q = np.stack([V[:, 0] * np.cos(a) - V[:, 1] * np.sin(a), V[:, 0] * np.sin(a) + V[:, 1] * np.cos(a),
                  V[:, 2] * (1 + 0.1 * V[:, 0])], 1)
    X = r.decode(r.raw_features(Q[None]), target=Q[None])[0]
    # documented bound: max error below 1% of the deformation's largest displacement
    assert np.abs(X - Q).max() < 0.01 * np.abs(Q - V).max()


def test_per_sample_reference_and_flat_guard():
    # a flat grid: one-rings are planar, the normal term keeps S from collapsing
    n = 8
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    V = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    t = Template(V, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]))
    r = DR(scaling="none")
    r.fit(V[None], None, t)
    F = r.raw_features(V[None])
    assert np.all(np.isfinite(F)) and np.abs(F).max() < 1e-12
    Q = V * [1.2, 0.9, 1.0]
    F = r.raw_features(Q[None])
    S_zz = F[0, :, 8] + 1
    assert np.all(S_zz > 0.5)  # never collapses along the normal
    # relative to a per-sample reference (a subject's own neutral)
    refs = np.stack([V, V * 1.1])
    P = refs * [1.0, 1.0, 1.0] + [0, 0, 0.05] * np.sin(3 * refs[..., :1])
    G = r.raw_features(P, refs)
    assert np.abs(r.decode(G, refs, target=P) - P).max() < 1e-2


def test_modes_fail_clearly_and_factorisation_is_shared():
    from fwk.errors import RecipeError

    V, t = sphere(2)
    r = DR(scaling="none", ref="sample")
    with pytest.raises(RecipeError, match="ref"):
        r.fit(V[None], None, t)
    r.fit(V[None], V[None], t)
    with pytest.raises(RecipeError, match="per-sample"):
        r.encode(V[None])
    F = r.encode(1.1 * V[None], V)
    assert np.abs(r.decode(F, V, target=1.1 * V[None]) - 1.1 * V).max() < 1e-6  # float32 features
    e = DR(scaling="none", align="target")
    e.fit(V[None], None, t)
    with pytest.raises(RecipeError, match="target"):
        e.decode(e.encode(V[None]))
    assert e._ops is r._ops  # one factorisation per reference geometry, in memory
    with pytest.raises(RecipeError, match="align"):
        DR(align="sideways")


def test_isolated_vertex_is_guarded_never_nan():
    V, t = sphere(2)
    V2 = np.vstack([V, [[3.0, 0, 0]]])
    t2 = Template(V2, t.triangles)
    r = DR(scaling="std")
    P = np.stack([V2, 1.1 * V2])
    r.fit(P, None, t2)
    F = r.encode(P)
    assert np.all(np.isfinite(F))
    X = r.decode(F, None, P)
    # the isolated vertex is pinned to the reference, which tilts the registration slightly
    assert np.all(np.isfinite(X)) and np.abs(X[:, :-1] - P[:, :-1]).max() < 1e-2
