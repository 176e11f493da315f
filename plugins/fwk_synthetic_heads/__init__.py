"""``synthetic-heads``: procedural head-and-neck meshes, the embedded default dataset.

Nothing to download: every subject is generated from a seed. One shared triangle topology: a
latitude/azimuth grid over the head (a fan closes the crown) continued down into the neck,
whose bottom ring is an open boundary. The grid is warped so that the face is tessellated
about 3x denser than scalp and neck in each direction (as real scans are), and the vertex
count is a parameter (``n_vertices``, met to within a few per cent).

Shape of a subject (units: cm; y up, the face looks along +z):

* **base**: an ellipsoidal skull (half-width 7.6, half-height 11.5, half-depth 9.6) joined
  smoothly to a neck cylinder;
* **identity, low frequencies** (13 smooth parameters, each N(0, 1)): head width, height and
  depth, jaw width, chin protrusion, cheekbones, nose length, nose protrusion, nose width,
  brow ridge, eye-socket depth, lip fullness, mouth width; plus ``age`` in [0, 1] which sags
  the jowls and cheeks (a low-frequency effect of age);
* **identity, high frequencies**, scaled by age: forehead lines, crow's feet, nasolabial folds,
  and fine skin relief (a sum of random-phase sinusoids per subject);
* **expressions**, personalised: ``face-compression`` (the face squeezed towards its own nose
  tip, brows lowered, glabella furrows), ``mouth-wide`` (the jaw rotated about the subject's
  own jaw pivot, mouth corners stretched, nasolabial folds deepened), ``oo-brow-raise-eyes-wide``
  (lips puckered forward, brows and forehead raised, forehead wrinkles deepened). Amplitudes
  depend on the identity (jaw, lips, age...) and the wrinkles that an expression creates are
  stronger on older subjects, so an expression is never the same displacement for every head.

All features are smooth bumps and sinusoids in the (azimuth, latitude) parameter domain,
displaced along the base surface's normals; generation is vectorised over subjects
(200 identities x 4 shapes at 6k vertices take about a second) and cached by content hash.
"""
from __future__ import annotations

import numpy as np

from fwk.data import MeshCollection, Template
from fwk.errors import RecipeError
from fwk.hookspecs import hookimpl
from fwk.registry import did_you_mean

PI = np.pi
EXPRESSIONS = ("face-compression", "mouth-wide", "oo-brow-raise-eyes-wide")
IDENTITY_PARAMS = ("head_width", "head_height", "head_depth", "jaw_width", "chin", "cheekbones", "nose_length",
                   "nose_protrusion", "nose_width", "brow_ridge", "eye_sockets", "lips", "mouth_width")

# Latitude t in [0, 1]: 0 the crown, T_HEAD the base of the skull, 1 the bottom of the neck.
T_HEAD = 0.80
PHI_HEAD = 0.78 * PI
# Face band in skull latitude phi and in azimuth theta (0 = front).
FACE_PHI = (0.30 * PI, 0.76 * PI)
FACE_THETA = 0.62


def _warped(n: int, lo: float, hi: float, dens, endpoint: bool) -> np.ndarray:
    """n samples of [lo, hi] whose spacing is inversely proportional to ``dens``."""
    x = np.linspace(lo, hi, 4001)
    cdf = np.concatenate([[0.0], np.cumsum(0.5 * (dens(x[1:]) + dens(x[:-1])) * np.diff(x))])
    cdf /= cdf[-1]
    q = np.linspace(0.0, 1.0, n, endpoint=endpoint)
    return np.interp(q, cdf, x)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _band(x, lo, hi, soft):
    return _smoothstep((x - lo) / soft + 0.5) * _smoothstep((hi - x) / soft + 0.5)


def build_topology(n_vertices: int):
    """Grid parameters (theta, t per vertex) and triangles for about ``n_vertices`` vertices."""
    if n_vertices < 200:
        raise RecipeError(f"dataset.n_vertices: at least 200 vertices, got {n_vertices}")
    # the face band spans about a third of the latitudes and of the azimuths; with density 3
    # there, n_lat * n_az ~ n.
    n_az = int(round(np.sqrt(n_vertices * 1.15)))
    n_lat = max(8, int(round((n_vertices - 1) / n_az)))
    dens_theta = lambda th: 1.0 + 2.0 * _band(np.abs(th), -1.0, FACE_THETA, 0.35)
    theta = _warped(n_az, -PI, PI, dens_theta, endpoint=False)
    theta = theta - theta[np.argmin(np.abs(theta))]  # a column exactly at the front
    t_face = (FACE_PHI[0] / PHI_HEAD * T_HEAD, FACE_PHI[1] / PHI_HEAD * T_HEAD)
    dens_t = lambda t: 1.0 + 2.0 * _band(t, t_face[0], t_face[1], 0.05)
    ts = _warped(n_lat + 1, 0.0, 1.0, dens_t, endpoint=True)[1:]
    TH, TT = np.meshgrid(theta, ts)  # (n_lat, n_az)
    theta_v = np.concatenate([[0.0], TH.ravel()])
    t_v = np.concatenate([[0.0], TT.ravel()])
    idx = 1 + np.arange(n_lat * n_az).reshape(n_lat, n_az)
    nxt = np.roll(idx, -1, axis=1)
    tris = [np.stack([np.zeros(n_az, np.int64), nxt[0], idx[0]], 1)]  # crown fan
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    tris.append(np.stack([a, b, d], -1).reshape(-1, 3))
    tris.append(np.stack([a, d, c], -1).reshape(-1, 3))
    return theta_v, t_v, np.concatenate(tris).astype(np.int64)


def _base_shape(theta, t, width, height, depth):
    """(S, n, 3) base skull + neck for per-subject scale factors (S,)."""
    phi = np.where(t <= T_HEAD, t / T_HEAD * PHI_HEAD, PHI_HEAD)
    rho_h, y_h = np.sin(phi), np.cos(phi)
    s = np.clip((t - T_HEAD) / (1 - T_HEAD), 0, 1)
    neck_r = 0.56
    rho = np.where(t <= T_HEAD, rho_h, (1 - _smoothstep(s * 1.6)) * np.sin(PHI_HEAD) + _smoothstep(s * 1.6) * neck_r)
    y = np.where(t <= T_HEAD, y_h, np.cos(PHI_HEAD) - 0.75 * s)
    # the neck sits slightly behind the face
    zoff = np.where(t <= T_HEAD, 0.0, -0.18 * _smoothstep(s * 2.0))
    x = rho * np.sin(theta)
    z = rho * np.cos(theta)
    # flatten the face a little (human faces are flatter than an ellipsoid)
    front = np.clip(np.cos(theta), 0, None) ** 3 * _band(phi, 0.25 * PI, 0.8 * PI, 0.2 * PI)
    z = z - 0.06 * front
    hx = 7.6 * width[:, None]
    hy = 11.5 * height[:, None]
    hz = 9.6 * depth[:, None]
    return np.stack([hx * x, hy * y + 0 * x, hz * (z + zoff)], axis=-1)


def _normals(V, F):
    import trimesh

    return np.asarray(trimesh.Trimesh(V, F, process=False).vertex_normals)


def _feature_lat(phi):
    """Latitude coordinate in which facial features are placed: the face band is stretched
    by 1.15 about the hairline so that eyes sit at mid-height and the chin clears the skull."""
    return 0.30 * PI + (phi - 0.30 * PI) * 1.15


def _g(theta, phi, th0, ph0, sth, sph):
    return np.exp(-0.5 * (((theta - th0) / sth) ** 2 + ((phi - ph0) / sph) ** 2))


class SyntheticHeads:
    """Procedural head-and-neck meshes with personalised expressions (embedded, no files)."""

    name = "synthetic-heads"

    def __init__(self, n_subjects: int = 200, n_vertices: int = 6000, shapes: list[str] | None = None,
                 seed: int = 0, wrinkles: float = 1.0, units: str = "cm"):
        if n_subjects < 1:
            raise RecipeError(f"dataset.n_subjects: at least 1, got {n_subjects}")
        shapes = list(shapes) if shapes else ["neutral", *EXPRESSIONS]
        for s in shapes:
            if s != "neutral" and s not in EXPRESSIONS:
                raise RecipeError(f"dataset.shapes: unknown shape {s!r}{did_you_mean(s, EXPRESSIONS)} "
                                  f"(shapes: neutral, {', '.join(EXPRESSIONS)})")
        if "neutral" not in shapes:
            shapes = ["neutral", *shapes]
        self.n_subjects, self.n_vertices, self.shapes = n_subjects, n_vertices, shapes
        self.seed, self.wrinkles, self.units = seed, wrinkles, units

    def load(self, cache=None) -> MeshCollection:
        key = (self.n_subjects, self.n_vertices, tuple(self.shapes), self.seed, self.wrinkles, "v1")
        if cache is not None:
            positions = cache.memmap_array("synthetic-heads", key, self._generate)
        else:
            positions = self._generate()
        template = self.template()
        template.vertices = np.asarray(positions[0, 0], dtype=np.float64)
        subjects = [f"s{i:04d}" for i in range(self.n_subjects)]
        return MeshCollection(template, subjects, list(self.shapes), positions, name=self.name)

    def template(self) -> Template:
        theta, t, F = build_topology(self.n_vertices)
        phi = np.where(t <= T_HEAD, t / T_HEAD * PHI_HEAD, PHI_HEAD)
        face = (np.abs(theta) < FACE_THETA) & (phi > FACE_PHI[0]) & (phi < FACE_PHI[1])
        neck = t > T_HEAD
        regions = {"face": np.flatnonzero(face), "neck": np.flatnonzero(neck), "scalp": np.flatnonzero(~face & ~neck)}
        fl = _feature_lat(phi)

        def nearest(th, ph):
            return int(np.argmin((theta - th) ** 2 + (fl - ph) ** 2 + 10 * neck))
        landmarks = {"nose_tip": nearest(0, 0.555 * PI), "chin": nearest(0, 0.715 * PI),
                     "eye_l": nearest(0.24, 0.475 * PI), "eye_r": nearest(-0.24, 0.475 * PI),
                     "mouth_l": nearest(0.17, 0.63 * PI), "mouth_r": nearest(-0.17, 0.63 * PI)}
        base = _base_shape(theta, t, np.ones(1), np.ones(1), np.ones(1))[0]
        return Template(base, F, regions=regions, landmarks=landmarks, units=self.units, name=self.name)

    # ------------------------------------------------------------------ generation
    def _generate(self) -> np.ndarray:
        theta, t, F = build_topology(self.n_vertices)
        S = self.n_subjects
        rng = np.random.default_rng(self.seed)
        p = {k: rng.standard_normal(S) for k in IDENTITY_PARAMS}
        age = rng.uniform(0.0, 1.0, S)
        phases = rng.uniform(0, 2 * PI, (S, 6))
        freqs = rng.uniform(25, 45, (S, 6, 2)) * rng.choice([-1, 1], (S, 6, 2))
        expr_gain = {e: np.exp(0.25 * rng.standard_normal(S)) for e in EXPRESSIONS}

        phi = np.where(t <= T_HEAD, t / T_HEAD * PHI_HEAD, PHI_HEAD)
        head = (t <= T_HEAD).astype(float)
        base0 = _base_shape(theta, t, np.ones(1), np.ones(1), np.ones(1))[0]
        N0 = _normals(base0, F)  # displacement directions (outward)
        th, ph = theta[None], _feature_lat(phi)[None]
        col = lambda a: a[:, None]

        # ---- identity: low frequencies (cm along the normal)
        B = _base_shape(theta, t, 1 + 0.05 * p["head_width"], 1 + 0.04 * p["head_height"], 1 + 0.04 * p["head_depth"])
        d = np.zeros((S, len(theta)))
        d += (0.9 + 0.25 * col(p["nose_protrusion"])) * _g(th, ph, 0, 0.545 * PI + 0.01 * col(p["nose_length"]), 0.085 + 0.015 * col(p["nose_width"]), 0.05 + 0.008 * col(p["nose_length"]))
        d += 1.2 * _g(th, ph, 0, 0.505 * PI, 0.05, 0.07)  # nasal bridge
        d += 0.35 * _g(np.abs(th), ph, 0.11 + 0.01 * col(p["nose_width"]), 0.565 * PI, 0.05, 0.03)  # alae
        d -= (0.55 + 0.12 * col(p["eye_sockets"])) * _g(np.abs(th), ph, 0.25, 0.475 * PI, 0.13, 0.045)
        d += (0.45 + 0.12 * col(p["brow_ridge"])) * _g(np.abs(th), ph, 0.2, 0.43 * PI, 0.24, 0.03)
        d += (0.45 + 0.15 * col(p["cheekbones"])) * _g(np.abs(th), ph, 0.42, 0.525 * PI, 0.15, 0.05)
        lips = 0.35 + 0.08 * col(p["lips"])
        mw = 0.11 + 0.015 * col(p["mouth_width"])
        d += lips * _g(th, ph, 0, 0.612 * PI, mw, 0.016)  # upper lip
        d += 0.9 * lips * _g(th, ph, 0, 0.648 * PI, mw * 0.9, 0.018)  # lower lip
        d -= 0.2 * _g(th, ph, 0, 0.63 * PI, mw * 1.1, 0.006)  # mouth line
        d -= 0.12 * _g(th, ph, 0, 0.675 * PI, 0.07, 0.012)  # labiomental groove
        d += (0.55 + 0.2 * col(p["chin"])) * _g(th, ph, 0, 0.715 * PI, 0.12, 0.03)
        d += (0.25 + 0.2 * col(p["jaw_width"])) * _g(np.abs(th), ph, 0.75, 0.70 * PI, 0.25, 0.05)
        d += 0.45 * _g(np.abs(th), ph, PI / 2, 0.52 * PI, 0.07, 0.07)  # ears
        # the lower face and jaw stand forward and down of the skull's ellipsoid
        d += (0.9 + 0.2 * col(p["jaw_width"])) * _g(th, ph, 0, 0.64 * PI, 0.45, 0.1)
        d += 0.6 * _g(th, ph, 0, 0.75 * PI, 0.35, 0.03)  # under the chin
        d += 0.5 * _g(th, ph, 0, 0.36 * PI, 0.5, 0.06)  # forehead
        d -= 0.3 * _g(th, ph, 0, 0.60 * PI, 0.035, 0.02)  # philtrum
        # age: sagging jowls and cheeks (low frequency), also pulls downward (below)
        sag = col(age) * _g(np.abs(th), ph, 0.45, 0.66 * PI, 0.18, 0.05)
        d += 0.35 * sag
        d *= head

        # ---- identity: high frequencies (wrinkles and skin relief), scaled by age
        w = self.wrinkles
        forehead = _band(ph, 0.31 * PI, 0.40 * PI, 0.03 * PI) * _band(th, -0.45, 0.45, 0.15)
        hf = -0.06 * col(age) ** 1.5 * forehead * (0.5 + 0.5 * np.cos(ph * 38.0 + col(phases[:, 0])))
        crow = _g(np.abs(th), ph, 0.46, 0.48 * PI, 0.06, 0.05)
        ang = np.arctan2(ph - 0.48 * PI, np.abs(th) - 0.40)
        hf += -0.05 * col(age) ** 1.5 * crow * (0.5 + 0.5 * np.cos(9.0 * ang + col(phases[:, 1])))
        fold_centre = 0.11 + 0.55 * (ph - 0.57 * PI)  # a line from the alae to the mouth corners
        fold = np.exp(-0.5 * ((np.abs(th) - fold_centre) / 0.018) ** 2) * _band(ph, 0.57 * PI, 0.65 * PI, 0.02 * PI)
        hf += -(0.08 + 0.22 * col(age)) * fold
        relief = np.zeros_like(d)
        for k in range(6):
            relief += np.sin(freqs[:, k, 0:1] * th + freqs[:, k, 1:2] * ph + col(phases[:, k]))
        hf += (0.004 + 0.01 * col(age)) * relief / np.sqrt(6)
        d += w * hf * head

        neutral = B + d[..., None] * N0[None]
        neutral[..., 1] -= 0.4 * sag  # sag pulls down as well as out
        out = np.empty((S, len(self.shapes), len(theta), 3))
        for j, shape in enumerate(self.shapes):
            out[:, j] = neutral if shape == "neutral" else self._expression(shape, neutral, th, ph, N0, head, p, age,
                                                                            expr_gain[shape], phases, w)
        return out

    def _expression(self, shape, P, th, ph, N0, head, p, age, gain, phases, w):
        col = lambda a: a[:, None]
        E = P.copy()
        face = _band(ph, 0.32 * PI, 0.78 * PI, 0.04 * PI) * np.clip(np.cos(th), 0, None) ** 2 * head
        nose_i = np.argmin((th[0] - 0) ** 2 + (ph[0] - 0.555 * PI) ** 2)
        nose = P[:, nose_i]  # each subject's own nose tip
        if shape == "face-compression":
            k = (0.10 + 0.02 * col(p["cheekbones"])) * col(gain)
            rel = P - nose[:, None]
            E[..., 0] -= (k * face) * rel[..., 0]
            E[..., 1] -= (0.8 * k * face) * rel[..., 1]
            brow = _g(np.abs(th), ph, 0.2, 0.43 * PI, 0.25, 0.04)
            E[..., 1] -= 0.35 * col(gain) * brow
            E += (0.15 * col(gain) * _g(th, ph, 0, 0.63 * PI, 0.15, 0.03))[..., None] * N0  # lips pressed out
            glab = _g(th, ph, 0, 0.44 * PI, 0.07, 0.03) * (0.5 + 0.5 * np.cos(th * 70.0 + col(phases[:, 2])))
            crow = _g(np.abs(th), ph, 0.46, 0.48 * PI, 0.07, 0.05) * (0.5 + 0.5 * np.cos(ph * 60.0))
            E -= (w * (0.05 + 0.1 * col(age)) * col(gain) * (glab + crow))[..., None] * N0
        elif shape == "mouth-wide":
            angle = np.deg2rad(10.0 + 2.0 * p["jaw_width"]) * gain
            # the jaw: from the mouth line down to under the chin, fading out towards neck and ears
            jaw = _band(ph, 0.635 * PI, 0.80 * PI, 0.06 * PI) * _band(np.abs(th), -1.0, 0.9, 0.5) * head
            # pivot: the subject's own jaw joint, in front of the ears at mouth height
            ear_i = np.argmin((np.abs(th[0]) - PI / 2) ** 2 + (ph[0] - 0.55 * PI) ** 2)
            pivot = P[:, ear_i].copy()
            pivot[:, 0] = 0
            rel = P - pivot[:, None]
            c, s = np.cos(angle)[:, None], np.sin(angle)[:, None]
            ry = c * rel[..., 1] - s * rel[..., 2]
            rz = s * rel[..., 1] + c * rel[..., 2]
            E[..., 1] = P[..., 1] + jaw * (ry + pivot[:, None, 1] - P[..., 1])
            E[..., 2] = P[..., 2] + jaw * (rz + pivot[:, None, 2] - P[..., 2])
            corners = _g(np.abs(th), ph, 0.17, 0.63 * PI, 0.06, 0.03)
            E[..., 0] += np.sign(th) * (0.5 + 0.1 * col(p["mouth_width"])) * col(gain) * corners
            fold_centre = 0.11 + 0.55 * (ph - 0.57 * PI)
            fold = np.exp(-0.5 * ((np.abs(th) - fold_centre) / 0.02) ** 2) * _band(ph, 0.57 * PI, 0.66 * PI, 0.02 * PI)
            E -= (w * (0.15 + 0.2 * col(age)) * col(gain) * fold)[..., None] * N0
        elif shape == "oo-brow-raise-eyes-wide":
            mouth = _g(th, ph, 0, 0.63 * PI, 0.2, 0.04) * head
            k = 0.35 * col(gain) * (1 + 0.15 * col(p["lips"]))
            E[..., 0] -= k * mouth * P[..., 0]
            E += (0.8 * col(gain) * (1 + 0.2 * col(p["lips"])) * mouth)[..., None] * N0
            brow = _band(ph, 0.28 * PI, 0.47 * PI, 0.05 * PI) * _band(th, -0.7, 0.7, 0.2) * head
            E[..., 1] += 0.6 * col(gain) * brow
            lids = _g(np.abs(th), ph, 0.25, 0.465 * PI, 0.1, 0.02)
            E[..., 1] += 0.2 * col(gain) * lids
            fore = _band(ph, 0.30 * PI, 0.41 * PI, 0.03 * PI) * _band(th, -0.5, 0.5, 0.15)
            lines = fore * (0.5 + 0.5 * np.cos(ph * 45.0 + col(phases[:, 3])))
            E -= (w * (0.05 + 0.15 * col(age)) * col(gain) * lines * head)[..., None] * N0
        return E


@hookimpl
def fwk_register_datasets():
    return [SyntheticHeads]
