"""``synthetic-heads``: procedural head-and-neck meshes, the embedded default dataset.

Nothing to download: every subject is generated from a seed (units cm; y up, eye level at
y = 0, the face looks along +z).

Topology (shared by every subject): a grid of rows (crown -> bottom of the neck) by columns
(azimuth theta, 0 = front). The crown is one vertex closed by a fan; the bottom row is an
open boundary. Rows and columns are spaced so that the face is tessellated about 2.6x denser
in each direction than scalp and neck (>= 3x per area, as real scans are); ``n_vertices`` is
met to within a few per cent.

Base surface: lofted from three profile curves, each a monotone cubic through key levels
(crown, forehead, brow, eyes, nose base, mouth, chin, under the chin, throat, neck): the
sagittal front profile (y, z), the back profile (y, z) and the side profile (y, x). A row at
azimuth theta is the superellipse |x/X|^p + |(z - Z0)/D|^p = 1 in polar form (a point per
azimuth theta) whose exponent p varies by row (a square skull, a flat face, a V-shaped
jaw). The front rows below the chin fold back under the jaw into the neck.

Identity (16 numbers per subject):

* low frequencies, 15 smooth parameters ~ N(0, 1): head width, height, depth, face length,
  jaw width, chin, cheekbones, nose length, nose protrusion, nose width, brow ridge,
  eye-socket depth, eye spacing, lip fullness, mouth width. Features are smooth bumps and dents
  (Gaussians in the generic head's x, y cm coordinates) displaced along the subject's normals;
* ``age`` ~ U(0, 1): sags the low frequencies (jowls, cheeks pulled down, under-chin) and
  scales the high frequencies: forehead lines, crow's feet, nasolabial folds, under-eye
  bags and a fine skin relief (random-phase sinusoids per subject).

Expressions, personalised (never one displacement added to every neutral):

* ``face-compression``: the face squeezed towards the subject's own nose tip, brows lowered
  and drawn together, eyes squinting, lips pressed; glabella furrows, bunny lines and crow's
  feet deepened in proportion to age;
* ``mouth-wide``: the jaw rotated about the subject's own jaw joints by an angle that depends
  on the identity, the mouth slit opened into a cavity, the corners stretched, the nasolabial
  folds deepened (more with age);
* ``oo-brow-raise-eyes-wide``: lips puckered and pushed forward into an "o", brows and
  forehead raised with forehead wrinkles (deeper with age), upper lids raised.

Each expression has a per-subject gain (log-normal, ``gain_sd`` 0.25 by default: how strongly the
subject performed it, which nothing in the neutral tells) and identity-dependent amplitudes
(jaw, lips, cheekbones) and acts on the subject's own geometry, so the displacement differs
across subjects beyond a global scale. Generation is vectorised over subjects (200 x 4 shapes
at 6k vertices take a few seconds) and cached by content hash.
"""
from __future__ import annotations

import numpy as np

from fwk.cache import memo
from fwk.data import MeshCollection, Template, Units
from fwk.errors import RecipeError
from fwk.hookspecs import hookimpl
from fwk.registry import did_you_mean

PI = np.pi
EXPRESSIONS = ("face-compression", "mouth-wide", "oo-brow-raise-eyes-wide")
IDENTITY_PARAMS = ("head_width", "head_height", "head_depth", "face_length", "jaw_width", "chin", "cheekbones",
                   "nose_length", "nose_protrusion", "nose_width", "brow_ridge", "eye_sockets", "eye_spacing",
                   "lips", "mouth_width")
VERSION = "v2"

# Key levels: front (y, z), side (y, x), back (y, z), z of the side point, superellipse exponent.
_KEYS = np.array([
    # fy     fz     sy     sx     by     bz     sz     p
    [12.0, -1.0, 12.0, 0.0, 12.0, -1.0, -1.0, 2.4],   # crown
    [10.8, 4.6, 10.6, 4.6, 10.8, -6.2, -1.0, 2.4],    # top
    [8.0, 7.5, 7.6, 7.0, 7.5, -9.4, -1.0, 2.5],       # upper forehead
    [4.5, 8.9, 3.5, 7.6, 3.5, -10.3, -1.0, 2.6],      # forehead
    [1.8, 9.2, 1.0, 7.5, 0.5, -10.0, -1.0, 2.6],      # brow
    [0.0, 8.8, -0.5, 7.35, -1.5, -9.6, -0.8, 2.6],    # eyes
    [-4.0, 9.0, -3.5, 7.0, -4.5, -8.4, -0.5, 2.4],    # nose base
    [-6.5, 9.1, -6.0, 6.6, -6.5, -6.9, -0.3, 2.1],    # mouth
    [-10.0, 8.6, -8.5, 6.1, -8.0, -5.9, -0.5, 1.75],  # chin front
    [-11.8, 7.5, -10.0, 5.8, -9.0, -5.5, -0.8, 1.8],  # chin bottom
    [-12.6, 5.0, -11.0, 5.7, -9.8, -5.35, -1.0, 1.9],  # under the chin
    [-13.4, 3.0, -12.5, 5.7, -11.0, -5.25, -1.2, 2.0],  # throat
    [-16.5, 3.0, -16.0, 5.9, -15.0, -5.4, -1.2, 2.1],   # neck
    [-21.0, 3.6, -21.0, 6.6, -21.0, -5.9, -1.2, 2.2],   # neck bottom (open boundary)
])
_FACE_LEVELS = (3, 9)  # forehead .. chin bottom: the densely tessellated rows
_NECK_LEVEL = 10       # rows below the under-chin level are the neck
FACE_THETA = 0.95      # |theta| of the face's sides
DENSITY = 1.4          # face density per direction relative to scalp and neck


def _key_t() -> np.ndarray:
    """Row parameter of each key level: cumulative arc length of the front profile, in [0, 1]."""
    f = _KEYS[:, :2]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(f, axis=0), axis=1))])
    return s / s[-1]


def _profiles(t: np.ndarray) -> np.ndarray:
    """(len(t), 8) key-level columns interpolated at row parameters t (monotone cubic)."""
    from scipy.interpolate import PchipInterpolator

    return PchipInterpolator(_key_t(), _KEYS, axis=0)(t)


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


def _g(x, x0, s):
    return np.exp(-0.5 * ((x - x0) / s) ** 2)


def _grid(n_lat: int, n_az: int, density: float):
    """(theta, t) of a rows x columns grid (plus the crown vertex) and its triangles; the face
    rows and columns are ``density`` x closer together than the others."""
    kt = _key_t()
    t_face = (kt[_FACE_LEVELS[0]], kt[_FACE_LEVELS[1]])
    crown = lambda t: 0.3 + 0.7 * _smoothstep(t / 0.2)  # sparse rows near the crown
    ts = _warped(n_lat + 1, 0.0, 1.0, lambda t: (1.0 + (density - 1) * _band(t, t_face[0], t_face[1], 0.04))
                 * crown(t), endpoint=True)[1:]
    th = _warped(n_az + 1, -PI, PI, lambda x: 1.0 + (density - 1) * _band(np.abs(x), -1.0, FACE_THETA, 0.3),
                 endpoint=True)[:-1]
    th = th - th[np.argmin(np.abs(th))]  # a column exactly at the front
    TH, TT = np.meshgrid(th, ts)
    theta_v = np.concatenate([[0.0], TH.ravel()])
    t_v = np.concatenate([[0.0], TT.ravel()])
    idx = 1 + np.arange(n_lat * n_az).reshape(n_lat, n_az)
    nxt = np.roll(idx, -1, axis=1)
    tris = [np.stack([np.zeros(n_az, np.int64), idx[0], nxt[0]], 1)]  # crown fan (outward normals)
    a, b, c, d = idx[:-1], nxt[:-1], idx[1:], nxt[1:]
    tris.append(np.stack([a, d, b], -1).reshape(-1, 3))
    tris.append(np.stack([a, c, d], -1).reshape(-1, 3))
    return theta_v, t_v, np.concatenate(tris).astype(np.int64)


def _refine(theta, t, F, marked):
    """Red-green refinement: marked triangles (and any with two split edges) split in 4 at
    their edge midpoints (in the parameter domain), triangles with one split edge in 2."""
    E = np.sort(np.stack([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]], 1), axis=2)  # (m, 3, 2)
    m, n = len(F), len(theta)
    key = E[..., 0] * n + E[..., 1]  # (m, 3)
    red = marked.copy()
    while True:
        split = np.unique(key[red])
        n_split = np.isin(key, split).sum(1)
        grow = ~red & (n_split >= 2)
        if not grow.any():
            break
        red |= grow
    split = np.unique(key[red])
    mid = {int(k): n + i for i, k in enumerate(split)}
    a_, b_ = split // n, split % n
    theta = np.concatenate([theta, 0.5 * (theta[a_] + theta[b_])])
    t = np.concatenate([t, 0.5 * (t[a_] + t[b_])])
    out = []
    for f in range(m):
        v0, v1, v2 = F[f]
        ms = [mid.get(int(k)) for k in key[f]]  # midpoints of edges (0,1), (1,2), (2,0)
        if red[f]:
            m01, m12, m20 = ms
            out += [(v0, m01, m20), (m01, v1, m12), (m20, m12, v2), (m01, m12, m20)]
        elif ms[0] is not None:
            out += [(v0, ms[0], v2), (ms[0], v1, v2)]
        elif ms[1] is not None:
            out += [(v1, ms[1], v0), (ms[1], v2, v0)]
        elif ms[2] is not None:
            out += [(v2, ms[2], v1), (ms[2], v0, v1)]
        else:
            out.append((v0, v1, v2))
    return theta, t, np.asarray(out, dtype=np.int64)


def _face_mask(theta, t, pad=0.0):
    kt = _key_t()
    return (np.abs(theta) < FACE_THETA + pad) & (t > kt[_FACE_LEVELS[0]] - pad / 4) & (t < kt[_FACE_LEVELS[1]] + pad / 4)


def _build(n_lat: int, n_az: int):
    theta, t, F = _grid(n_lat, n_az, DENSITY)
    inside = _face_mask(theta, t)[F].all(1)
    return _refine(theta, t, F, inside)


def build_topology(n_vertices: int):
    """(theta, t) per vertex and triangles for about ``n_vertices`` vertices: a grid, denser in
    the face band, whose face triangles are then split in four (red-green refinement), so the
    face is tessellated several times denser per area than scalp and neck."""
    if n_vertices < 200:
        raise RecipeError(f"dataset.n_vertices: at least 200 vertices, got {n_vertices}")
    return _build_cached(int(n_vertices))


def _build_cached(n_vertices: int):
    def build():
        guess = n_vertices / 2.0
        for _ in range(3):  # the refinement adds a fraction of the grid's vertices: aim twice
            n_az = max(12, int(round(np.sqrt(guess * 1.25))))
            n_lat = max(8, int(round((guess - 1) / n_az)))
            res = _build(n_lat, n_az)
            guess *= n_vertices / len(res[0])
        return res

    return memo(f"{__name__}.topology", n_vertices, build, size=8)


def _loft(theta, t, sx=1.0, sy_up=1.0, sy_down=1.0, sz_back=1.0, jaw=1.0, chin_fwd=0.0):
    """(S, n, 3) base surfaces; the scale arguments are (S,) arrays (or scalars)."""
    K = _profiles(t)  # (n, 8)
    fy, fz, sy, sxx, by, bz, z0, p = K.T
    col = lambda a: np.atleast_1d(np.asarray(a, dtype=np.float64))[:, None]
    s, c = np.sin(theta), np.cos(theta)
    # jaw rows (mouth .. under the chin) take the jaw width
    kt = _key_t()
    jaw_w = _band(t, kt[7], kt[10], 0.08)
    X = sxx[None] * (col(sx) + (col(jaw) - 1.0) * jaw_w[None])
    front = c >= 0
    chin_w = _band(t, kt[7], kt[10], 0.06)
    zf = fz[None] + col(chin_fwd) * chin_w[None]
    D = np.where(front[None], zf - z0, (z0 - bz[None]) * col(sz_back))  # depth in front of / behind z0
    # the superellipse in polar form (smooth in theta): r = ((|s|/X)^p + (|c|/D)^p)^(-1/p)
    r = ((np.abs(s) / np.maximum(X, 1e-9)) ** p + (np.abs(c) / np.maximum(D, 1e-9)) ** p) ** (-1.0 / p)
    x = r * s
    z = z0 + r * c
    yy = np.where(front, fy, by)
    y = sy + (yy - sy) * c ** 2
    y = np.where(y > 0, y * col(sy_up), y * col(sy_down))
    return np.stack([x, y, np.broadcast_to(z, x.shape)], axis=-1)


def _normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(S, n, 3) unit area-weighted vertex normals of S meshes on one triangle list."""
    import scipy.sparse as sp

    fn = np.cross(V[:, F[:, 1]] - V[:, F[:, 0]], V[:, F[:, 2]] - V[:, F[:, 0]])  # (S, m, 3)
    m, n = len(F), V.shape[1]
    A = sp.csr_matrix((np.ones(3 * m), (F.T.ravel(), np.tile(np.arange(m), 3))), shape=(n, m))
    N = (A @ fn.transpose(1, 0, 2).reshape(m, -1)).reshape(n, len(V), 3).transpose(1, 0, 2)
    return N / np.maximum(np.linalg.norm(N, axis=-1, keepdims=True), 1e-12)


class SyntheticHeads:
    """Procedural head-and-neck meshes with personalised expressions (embedded, no files)."""

    name = "synthetic-heads"

    def __init__(self, n_subjects: int = 200, n_vertices: int = 6000, shapes: list[str] | None = None,
                 seed: int = 0, wrinkles: float = 1.0, units: Units = "cm", gain_sd: float = 0.25):
        if n_subjects < 1:
            raise RecipeError(f"dataset.n_subjects: at least 1, got {n_subjects}")
        if n_vertices < 200 or n_vertices > 200_000:
            raise RecipeError(f"dataset.n_vertices: between 200 and 200000, got {n_vertices}")
        shapes = list(shapes) if shapes else ["neutral", *EXPRESSIONS]
        for s in shapes:
            if s != "neutral" and s not in EXPRESSIONS:
                raise RecipeError(f"dataset.shapes: unknown shape {s!r}{did_you_mean(s, EXPRESSIONS)} "
                                  f"(shapes: neutral, {', '.join(EXPRESSIONS)})")
        if "neutral" not in shapes:
            shapes = ["neutral", *shapes]
        self.n_subjects, self.n_vertices, self.shapes = n_subjects, n_vertices, shapes
        if not (isinstance(gain_sd, (int, float)) and not isinstance(gain_sd, bool) and gain_sd >= 0):
            raise RecipeError(f"dataset.gain_sd: a number >= 0, got {gain_sd!r}")
        self.seed, self.wrinkles, self.units, self.gain_sd = seed, wrinkles, units, float(gain_sd)

    # ------------------------------------------------------------------ public
    def load(self, cache=None) -> MeshCollection:
        key = (self.n_subjects, self.n_vertices, tuple(self.shapes), self.seed, self.wrinkles, self.gain_sd, VERSION)
        if cache is not None:
            positions = cache.memmap_array(self.name, key, self._generate)
        else:
            positions = self._generate()
        template = self.template()
        template.vertices = np.asarray(positions[0, 0], dtype=np.float64)
        subjects = [f"s{i:04d}" for i in range(self.n_subjects)]
        return MeshCollection(template, subjects, list(self.shapes), positions, name=self.name)

    def identity_params(self) -> dict[str, np.ndarray]:
        """The identity numbers of every subject: the 15 N(0, 1) parameters and ``age`` in [0, 1]."""
        return self._draw()[0]

    def template(self) -> Template:
        theta, t, F = build_topology(self.n_vertices)
        G = _loft(theta, t)[0]
        kt = _key_t()
        face = (np.abs(theta) < FACE_THETA - 0.15) & (t > kt[_FACE_LEVELS[0]] + 0.02) & (t < kt[_FACE_LEVELS[1]] - 0.02)
        neck = t > kt[_NECK_LEVEL]
        regions = {"face": np.flatnonzero(face), "scalp": np.flatnonzero(~face & ~neck), "neck": np.flatnonzero(neck)}
        targets = {"nose_tip": (0, -3.0, 12), "nasion": (0, 0.6, 10), "chin": (0, -10.5, 10),
                   "eye_l": (3.2, -0.3, 10), "eye_r": (-3.2, -0.3, 10), "mouth_l": (2.4, -6.0, 10),
                   "mouth_r": (-2.4, -6.0, 10), "ear_l": (8, -1.5, -1.3), "ear_r": (-8, -1.5, -1.3)}
        landmarks = {}
        for k, (x, y, z) in targets.items():
            # nearest on the surface along z from the front (or x from the side for ears)
            d = (G[:, 0] - x) ** 2 + (G[:, 1] - y) ** 2 if abs(x) < 5 else (G[:, 2] - z) ** 2 + (G[:, 1] - y) ** 2
            d = d + 1e3 * (np.sign(G[:, 2 if abs(x) < 5 else 0]) != np.sign(z if abs(x) < 5 else x))
            landmarks[k] = int(np.argmin(d))
        return Template(G, F, regions=regions, landmarks=landmarks, units=self.units, name=self.name)

    # ------------------------------------------------------------------ generation
    def _draw(self):
        S = self.n_subjects
        rng = np.random.default_rng(self.seed)
        p = {k: rng.standard_normal(S) for k in IDENTITY_PARAMS}
        p["age"] = rng.uniform(0.0, 1.0, S)
        extra = {
            "phases": rng.uniform(0, 2 * PI, (S, 8)),
            "relief_k": rng.normal(0, 1, (S, 6, 3)),
            # the same draws whatever gain_sd, so that gain_sd changes only the gains
            "gain": {e: np.exp(self.gain_sd * rng.standard_normal(S)) for e in EXPRESSIONS},
        }
        return p, extra

    def _generate(self) -> np.ndarray:
        theta, t, F = build_topology(self.n_vertices)
        p, ex = self._draw()
        age = p["age"][:, None]
        col = lambda a: np.asarray(a)[:, None]
        # generic coordinates: where features are placed (cm), and the masks of the head's parts
        Gv = _loft(theta, t)[0]
        gx, gy, gz = Gv.T
        ax = np.abs(gx)
        frontw = _smoothstep((np.cos(theta) - 0.05) / 0.35)
        kt = _key_t()
        headw = 1.0 - _smoothstep((t - kt[10]) / 0.05)  # 1 on the head, 0 down the neck
        base = _loft(theta, t, 1 + 0.045 * p["head_width"], 1 + 0.04 * p["head_height"],
                     1 + 0.04 * p["face_length"], 1 + 0.04 * p["head_depth"], 1 + 0.06 * p["jaw_width"],
                     0.3 * p["chin"])
        Nb = _normals(base, F)

        d = np.zeros((self.n_subjects, len(gx)))
        # --- nose: a ridge from the nasion to the tip, alae, nostrils
        y_root = 0.6
        y_tip = col(-3.0 - 0.3 * p["nose_length"])
        prot = col(2.3 + 0.35 * p["nose_protrusion"])
        width = col(1.0 + 0.1 * p["nose_width"])
        s = np.clip((y_root - gy) / (y_root - y_tip), 0, None)
        h_up = (0.35 + (prot - 0.35) * np.clip(s, 0, 1) ** 1.4)
        h = np.where(s <= 1, h_up, prot * np.exp(-0.5 * ((gy - y_tip) / 0.42) ** 2))
        h = h * (gy < y_root + 1.0) * _smoothstep((y_root + 0.8 - gy) / 0.8)
        w = (0.5 + 0.5 * np.clip(s, 0, 1.2)) * width
        d += h * np.exp(-0.5 * (gx / w) ** 2)
        alx = col(1.45 + 0.15 * p["nose_width"])
        d += 0.75 * _g(ax, alx, 0.45) * _g(gy, y_tip - 0.6, 0.45)
        d -= 0.1 * _g(ax, alx - 0.6, 0.25) * _g(gy, y_tip - 1.0, 0.2)  # nostrils
        # --- eyes: sockets, eyeballs with lids, brow ridge
        ex_ = col(3.2 + 0.15 * p["eye_spacing"])
        d -= col(1.3 + 0.25 * p["eye_sockets"]) * _g(ax, ex_, 1.45) * _g(gy, -0.1, 1.05)
        d += 0.85 * _g(ax, ex_, 0.95) * _g(gy, -0.25, 0.6)
        d -= 0.12 * _g(ax, ex_, 0.9) * _g(gy, 0.55, 0.12)  # upper lid crease
        d -= 0.1 * _g(ax, ex_ + 0.2, 1.0) * _g(gy, -0.65, 0.08)  # lid line
        d += col(0.45 + 0.18 * p["brow_ridge"]) * _g(ax, 2.6, 1.7) * _g(gy, 1.45, 0.5)
        d += 0.25 * _g(gx, 0, 1.0) * _g(gy, 1.0, 0.7)  # glabella
        # --- cheeks, mouth, chin
        d += col(0.6 + 0.25 * p["cheekbones"]) * _g(ax, 4.7, 1.3) * _g(gy, -2.2, 1.1)
        d -= 0.25 * _g(ax, 4.3, 1.2) * _g(gy, -5.3, 1.4)
        mw = col(2.3 + 0.25 * p["mouth_width"])
        lips = col(0.55 + 0.18 * p["lips"])
        ym = -5.95
        d += lips * np.exp(-0.5 * (gx / (0.62 * mw)) ** 4) * _g(gy, ym + 0.5, 0.38)
        d += 0.95 * lips * np.exp(-0.5 * (gx / (0.58 * mw)) ** 4) * _g(gy, ym - 0.55, 0.42)
        d -= 0.35 * np.exp(-0.5 * (gx / (0.75 * mw)) ** 4) * _g(gy, ym, 0.1)  # the mouth line
        d -= 0.15 * _g(ax, mw, 0.3) * _g(gy, ym, 0.3)  # mouth corners
        d -= 0.15 * _g(gx, 0, 0.3) * _g(gy, -4.75, 0.35)  # philtrum
        d -= 0.3 * _g(gx, 0, 1.5) * _g(gy, -7.7, 0.4)  # labiomental groove
        d += col(0.45 + 0.22 * p["chin"]) * _g(gx, 0, 1.5) * _g(gy, -9.8, 0.9)
        # --- ears (on the sides) and the Adam's apple
        side = _smoothstep((np.abs(np.sin(theta)) - 0.9) / 0.08)
        d_ear = 1.9 * np.exp(-0.5 * (((gz + 1.5) / 0.9) ** 2 + ((gy + 1.4) / 1.9) ** 2) ** 2) \
            - 0.9 * _g(gz, -1.1, 0.4) * _g(gy, -1.9, 0.7)
        d += (side * d_ear)[None]
        d += 0.3 * (_g(gx, 0, 0.8) * _g(gy, -15.5, 0.8) * frontw)[None]
        # --- age: sagging (low frequency)
        jowl = _g(ax, 4.1, 1.1) * _g(gy, -9.2, 1.0)
        d += 0.45 * age * jowl
        d += 0.45 * age * _g(gx, 0, 2.2) * _g(gy, -12.3, 0.8)  # under the chin
        d += 0.18 * age * _g(ax, ex_, 0.9) * _g(gy, -1.6, 0.35)  # under-eye bags
        # --- high frequencies (wrinkles, relief), scaled by age
        a15 = age ** 1.5
        ph = ex["phases"]
        hf = np.zeros_like(d)
        fh = _band(gy, 2.7, 7.0, 0.8) * _band(gx, -4.2, 4.2, 1.2)
        hf -= 0.09 * a15 * fh * (0.5 + 0.5 * np.cos(2 * PI * (gy - 0.035 * gx ** 2) / 1.05 + col(ph[:, 0])))
        cr = np.hypot(ax - 4.6, gy + 0.2)
        ang = np.arctan2(gy + 0.2, ax - 4.6)
        crow = _g(cr, 1.1, 0.55) * (ax > 4.8)
        hf -= 0.07 * a15 * crow * (0.5 + 0.5 * np.cos(7.0 * ang + col(ph[:, 1])))
        fold_x = 1.75 + (-3.5 - gy) * 0.33
        fold = _g(ax - fold_x, 0, 0.16) * _band(gy, -7.3, -3.4, 0.5)
        hf -= (0.08 + 0.25 * age) * fold
        hf += (0.05 + 0.15 * age) * _g(ax - fold_x, 0.45, 0.35) * _band(gy, -7.3, -3.4, 0.5)  # cheek over the fold
        relief = np.zeros_like(d)
        k = ex["relief_k"] * (2 * PI / 0.7)
        for i in range(6):
            relief += np.sin(col(k[:, i, 0]) * gx + col(k[:, i, 1]) * gy + col(k[:, i, 2]) * gz + col(ph[:, 2 + i % 6]))
        hf += (0.004 + 0.012 * age) * relief / np.sqrt(6)
        d = d * frontw * headw + d * (1 - frontw) * headw * side  # facial features on the face, ears on the sides
        d += self.wrinkles * hf * frontw * headw
        neutral = base + d[..., None] * Nb
        neutral[..., 1] -= 0.5 * age * (jowl + 0.6 * _g(ax, 3.8, 1.4) * _g(gy, -4.6, 1.4)) * frontw  # sag pulls down
        Nn = _normals(neutral, F)
        out = np.empty((self.n_subjects, len(self.shapes), len(gx), 3))
        ctx = dict(gx=gx, gy=gy, gz=gz, ax=ax, frontw=frontw * headw, F=F, p=p, age=age, ph=ph, N=Nn,
                   ex_=ex_, mw=mw, y_tip=y_tip, fold_x=fold_x, theta=theta, t=t)
        for j, shape in enumerate(self.shapes):
            out[:, j] = neutral if shape == "neutral" else self._expression(shape, neutral, ex["gain"][shape], ctx)
        return out

    def _expression(self, shape, P, gain, c):
        gx, gy, gz, ax, fw, p, age, N = c["gx"], c["gy"], c["gz"], c["ax"], c["frontw"], c["p"], c["age"], c["N"]
        col = lambda a: np.asarray(a)[:, None]
        g = col(gain)
        w = self.wrinkles
        E = P.copy()
        tip_i = np.argmin(gx ** 2 + (gy + 3.0) ** 2 - 100 * (gz > 0))
        ym = -5.95
        if shape == "face-compression":
            tip = P[:, tip_i][:, None]
            k = (0.11 + 0.02 * col(p["cheekbones"])) * g
            m = fw * _band(gy, -8.5, 3.5, 3.0) * _band(gx, -6.5, 6.5, 2.5)
            E[..., 0] -= k * m * (P[..., 0] - tip[..., 0])
            E[..., 1] -= 0.7 * k * m * (P[..., 1] - tip[..., 1])
            brow = _g(ax, 2.4, 1.8) * _g(gy, 1.5, 0.9) * fw
            E[..., 1] -= 0.5 * g * brow
            E[..., 0] -= 0.25 * g * brow * np.sign(gx)
            lid = _g(ax, c["ex_"], 0.9) * _g(gy, -0.9, 0.4) * fw
            E[..., 1] += 0.3 * g * lid
            lipm = np.exp(-0.5 * (gx / (0.7 * c["mw"])) ** 4) * _g(gy, ym, 0.9) * fw
            E -= (0.25 * g * lipm)[..., None] * N
            glab = (_g(ax, 0.45, 0.13) * _g(gy, 1.1, 0.8)
                    + _g(gy, 0.0 - 0.25 * np.sin(4 * ax), 0.1) * _band(ax, 0.6, 1.6, 0.3))  # furrows, bunny lines
            crow = _g(np.hypot(ax - 4.6, gy + 0.2), 1.1, 0.6) * (ax > 4.8) * \
                (0.5 + 0.5 * np.cos(7.0 * np.arctan2(gy + 0.2, ax - 4.6) + col(c["ph"][:, 1])))
            E -= (w * (0.06 + 0.14 * age) * g * (glab + crow) * fw)[..., None] * N
        elif shape == "mouth-wide":
            angle = np.deg2rad(13.0 + 2.5 * p["jaw_width"] + 1.5 * p["chin"]) * gain
            soft = 0.6 + 3.0 * _smoothstep((ax - c["mw"]) / 2.0)  # sharp at the lips, broad over the cheeks
            jaw = fw * _smoothstep((ym + 0.25 - gy) / soft + 0.5 * (soft - 0.6) / soft) * _smoothstep((gy + 15.5) / 3.5) * \
                _smoothstep((gz + 1.0) / 4.0)
            jaw = jaw + (1 - fw) * 0  # the back of the head never moves
            joint = np.argmin((gy + 1.6) ** 2 + (gz + 0.5) ** 2 - 100 * (gx > 0))
            pivot = P[:, joint].copy()
            pivot[:, 0] = 0.0  # the subject's own jaw joints (both sides)
            rel = P - pivot[:, None]
            cs, sn = np.cos(angle)[:, None], np.sin(angle)[:, None]
            ry = cs * rel[..., 1] - sn * rel[..., 2]
            rz = sn * rel[..., 1] + cs * rel[..., 2]
            E[..., 1] += jaw * (ry + pivot[:, None, 1] - P[..., 1])
            E[..., 2] += jaw * (rz + pivot[:, None, 2] - P[..., 2])
            open_ = col(angle / np.deg2rad(13.0))
            slit = np.exp(-0.5 * (gx / (0.7 * c["mw"])) ** 4) * _g(gy, ym - 0.1, 0.35) * fw
            E -= (1.6 * open_ * slit)[..., None] * N  # the mouth opens into a cavity
            corners = _g(ax, c["mw"], 0.8) * _g(gy, ym, 0.7) * fw
            E[..., 0] += np.sign(gx) * (0.45 + 0.1 * col(p["mouth_width"])) * g * corners
            fold = _g(ax - c["fold_x"], 0, 0.18) * _band(gy, -7.3, -3.4, 0.5) * fw
            E -= (w * (0.12 + 0.2 * age) * g * fold)[..., None] * N
        elif shape == "oo-brow-raise-eyes-wide":
            mouth = _g(gx, 0, 2.0) * _g(gy, ym, 1.1) * fw
            k = 0.4 * g * (1 + 0.15 * col(p["lips"]))
            E[..., 0] -= k * mouth * P[..., 0]
            E += (0.9 * g * (1 + 0.2 * col(p["lips"])) * mouth)[..., None] * N
            hole = _g(gx, 0, 0.45) * _g(gy, ym, 0.3) * fw
            E -= (0.7 * g * hole)[..., None] * N
            brow = _g(gy, 2.0, 1.6) * _band(gx, -5.5, 5.5, 2.0) * fw * (gy > -0.3 + 0 * gx)
            E[..., 1] += 0.65 * g * brow * _smoothstep((gy + 0.3) / 0.8)
            lids = _g(ax, c["ex_"], 0.9) * _g(gy, 0.35, 0.35) * fw
            E[..., 1] += 0.35 * g * lids
            fore = _band(gy, 2.5, 7.0, 0.8) * _band(gx, -4.5, 4.5, 1.2) * fw
            lines = fore * (0.5 + 0.5 * np.cos(2 * PI * (gy - 0.035 * gx ** 2) / 1.05 + col(c["ph"][:, 0])))
            E -= (w * (0.06 + 0.14 * age) * g * lines)[..., None] * N
        return E


@hookimpl
def fwk_register_datasets():
    return [SyntheticHeads]
