"""Registration of a head of any topology to a run's template, and a rig carried back onto it.

A rigger's neutral ("the scan": a scan, a sculpt, another rig) has its own vertices, polygons,
units and placement. ``register`` fits the run's template (its mean training neutral M, n
vertices, triangles T) to the scan, so that the model can predict on a neutral in its own
topology; ``Registration.carry`` brings each predicted expression back onto the scan's own
vertices. Nothing here knows a dataset: the template is arrays.

Landmarks (``read_landmarks``): a JSON file

    {"landmarks": [{"template": 1234, "scan": 5678},
                   {"template": 2345, "scan": [1.0, 2.0, 3.0]}, ...]}

each pair a template vertex id (0-based, the order of the run's ``template.obj``) and either a
scan vertex id (0-based, the scan's OBJ ``v`` order) or a 3D point in the scan's frame and units.
At least ``MIN_LANDMARKS`` (5) pairs; 5-15 well spread ones (eye corners, nose tip, mouth
corners, chin, ears) are what the fit needs. No template id or scan vertex twice, ids in range,
points finite: else one line naming the file and the entry.

1. Similarity from the landmarks (Umeyama 1991): with template landmark points a_i = M[l_i] and
   scan points b_i, minimise sum_i |s R a_i + t - b_i|^2 over rotations R (det +1), t and s > 0:
   centred A0, B0, H = B0^T A0 / k = U S V^T, D = diag(1, 1, sign det(U V^T)), R = U D V^T,
   s = tr(S D) / (|A0|^2 / k), t = mean b - s R mean a. s is the scan's size in template units.
2. Units: the factor u (one scan unit is u template units; ``--units``, else detected) is the
   named unit's ratio (mm, cm, m, um, in, ft) nearest 1/s when it lies within ``UNIT_SNAP``
   (1.5x) of it and the template's units are named, else 1/s itself (the head is then brought to
   the template's landmark size). The rigid part is then refitted with s fixed at 1/u (the same
   formulas without the scale's update), and the scan is taken into the template's frame:
   X = u R^T (V - t), in template units.
3. Non-rigid fit: ``fwk.rig.nricp.nricp_amberg``, trimesh's ``nricp_amberg`` solved 2.4x faster
   (that module says why and how; on the held-out ICT-FaceKit head the registered vertices equal
   trimesh's to 5.2e-7 cm) (Amberg, Romdhani and Vetter 2007:
   optimal-step non-rigid ICP: an affine 3x4 transform per template vertex, minimising
   alpha |(M x G) X|^2 (stiffness over the template's edges) + |W (D X - U)|^2 (closest
   target points U, weighted by a distance cut-off and by normal agreement) + beta |D_L X -
   U_L|^2 (landmarks), for a decreasing schedule of (alpha, beta)) deforms M onto X. The target
   is a point cloud: the scan's vertices plus area-uniform samples of its triangles up to
   ``TARGET_DENSITY`` points per template vertex (trimesh's closest point on faces needs the
   optional rtree, which fwk does not depend on; the samples make a coarse scan's points as
   dense as the template's). The schedule is ``STEPS`` (stated below, with what trimesh's
   default gives), ``eps`` 0 (every step runs its iterations: the default eps stopped each step
   early while the fit still improved). Result: the registered neutral Y (n, 3), template
   topology, in the template's frame and units; the model predicts on it.
4. Correspondence: each scan vertex x_j (in the template frame) gets its closest point on Y's
   surface: triangle tau_j and barycentric coordinates b_j (searched among the triangles around
   its ``NEAREST`` nearest vertices of Y), at distance d_j (the residual).
5. Fitted or not: with h the median edge length of M, a scan vertex with d_j <= ``FIT_TOLERANCE``
   h (3 h) is fitted; beyond, it is a part the template lacks (an eyeball, teeth, a longer neck,
   shoulders) and not fitted. The weight w_j = 1 up to 3h, falls linearly to 0 at 6h
   (``FADE``), 0 beyond: a scan part the template lacks stays still, with no seam where it joins.
   Template vertices farther than 3h from the scan (the scan lacks them: a neck cut off higher)
   are registered by the stiffness term alone and reported.
6. Carrying an expression (``Registration.carry``, ``fwk apply --carry barycentric``): given the
   model's expression E (n, 3) on Y (template frame), the displacement Delta = E - Y is
   interpolated barycentrically at each scan vertex and taken back to the scan's frame and units:
   V_e(j) = V(j) + w_j R (sum_k b_jk Delta[T[tau_j, k]]) / u. The default carry is Deformation
   Transfer onto the scan's triangles (``fwk.rig.carry``), anchored to this one. Measured on a
   midpoint-subdivided held-out ICT-FaceKit head rigged from 10 landmarks at the eye and mouth
   corners, nose tip, lips and chin (tests/rig/test_register.py): this carry's DAME is 2.0-2.9x
   the direct rig's, Deformation Transfer's 1.3-2.4x, L1 the same (0.8-1.2x). Through an exact
   correspondence (the registered template on the subject's own vertices) this carry gives the
   direct rig remeshed (0.6x) and Deformation Transfer still 1.1-2.2x: the registration's
   tangential error (0.25 cm mean vertex error) costs this carry most of its DAME, while
   Deformation Transfer's is mostly its own smooth field. Where the landmarks sit (these 10, 10
   random vertices, 15) moves DAME by under 0.05x.

7. Folds: a triangle of Y is *folded* when its normal points against the same triangle's on the
   template (n_Y . n_M < 0) or its area fell below ``MIN_AREA_RATIO`` of the template's
   (``folded_triangles``). The non-rigid fit's stiffness keeps a good registration free of them
   (none on the held-out ICT-FaceKit head of tests/rig/test_register.py). Landmarks given for the
   wrong places can fold it: on the rig tests' 8 x 8 grid, two corners' points swapped folded 1 of
   its 98 triangles; on the ICT-FaceKit head, with the two inner eye corners swapped, the stiffness
   held and nothing folded (step 8 names that mistake). A model predicting on a folded neutral
   bends the rig there. The count is in the summary, the report and the progress lines, with a
   warning when there are any.
8. Misplaced landmarks (``landmark_residuals``): each landmark's distance r_i from where a
   similarity (its scale free) puts its template point, against the scan landmarks' spread
   S = sqrt(mean_i |b_i - mean b|^2); the similarity is fitted to the landmarks left after
   dropping, one at a time, the farthest off while one lies beyond ``LANDMARK_OFF`` S (at least 4
   kept). A landmark with r_i > ``LANDMARK_OFF`` S is reported as likely misplaced (a warning, not
   a refusal: an unusual head may differ). Measured on four
   held-out ICT-FaceKit heads with the 10 landmarks of tests/rig/test_register.py: r_i / S at
   most 0.13 when they are right; with the two inner eye corners or the two mouth corners given
   for each other, 0.85-1.05 for the swapped pair and at most 0.13 for the others (a single fit to
   all ten: up to 0.19 for the others). Nothing else
   shows such a mistake: with the inner eye corners swapped the fit folded no triangle and left
   the scan 0.066 cm (mean) from the registered surface, its correspondence wrong around the eyes.

The registration's state is arrays only (``arrays()``, written as ``correspondence.npz``; read
with ``fwk.safeio.load_npz``).
"""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from ..data.template import METRES_PER_UNIT, Template
from ..errors import DataError
from ..evaluation.render import colour_limits, render_grid
from . import read_json_file

MIN_LANDMARKS = 5
#: a named unit is taken when the landmarks' size ratio lies within this factor of it
UNIT_SNAP = 1.5
#: target points per template vertex (scan vertices plus samples of its triangles)
TARGET_DENSITY = 2.0
#: nricp_amberg's schedule: (stiffness alpha, landmark weight beta, normal weight, iterations).
#: Measured on an 11,248-vertex ICT-FaceKit face-head fitted to a held-out subject (2 cores shared
#: with a training; vertex error: distance of each registered vertex from the subject's true
#: corresponding vertex): trimesh's default, [[0.01, 10, 0.5, 10], [0.02, 5, 0.5, 10], [0.03, 2.5,
#: 0.5, 10], [0.01, 0, 0, 10]] with eps 1e-4, stopped after 14 iterations (21 s), vertex error
#: 0.31 cm; the same with eps 0 (40 iterations) 61.5 s, 0.22 cm; these 4 x 6 iterations (eps 0)
#: 48.8 s, and the carried rig's L1 the same as with 40 to 0.01x of the direct rig's (these times
#: with trimesh's solve, where each iteration was one sparse LU of the 4n x 4n normal equations,
#: 1.1 s of the 1.5 s at n = 11,248; fwk.rig.nricp's solve takes 2.4x less for the registration).
#: More iterations, which that saving would pay for, do not help the rig (2026-12-04, the held-out
#: head of tests/rig/test_register.py, the same schedule with 10 and 15 iterations a step): vertex
#: error on the face 2.13 and 2.09 mm against 2.15, the transfer carry's DAME over the direct rig's
#: 2.05x / 2.43x / 1.29x and 2.04x / 2.42x / 1.29x against 2.08x / 2.43x / 1.29x (jawOpen /
#: mouthSmile_L / eyeBlink_L), in 60 and 87 s against 33 s (1 thread beside a training).
STEPS = ((0.01, 10.0, 0.5, 6), (0.02, 5.0, 0.5, 6), (0.03, 2.5, 0.5, 6), (0.01, 0.0, 0.0, 6))
EPS = 0.0
#: nricp's distance cut-off, in the template's bounding-box diagonals (trimesh's normalisation)
DISTANCE_THRESHOLD = 0.1
#: a scan vertex is fitted within this many median template edge lengths of the registered surface
FIT_TOLERANCE = 3.0
#: ... and moves with a weight falling linearly to 0 at FADE times that distance
FADE = 2.0
#: nearest registered vertices whose triangles are searched for a scan vertex's closest point
NEAREST = 8
#: a registered triangle whose area fell below this fraction of the template's counts as folded
MIN_AREA_RATIO = 1e-3
#: a landmark farther than this fraction of the landmarks' spread from the similarity's place is reported
LANDMARK_OFF = 0.3


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------- landmarks
def read_landmarks(path, n_template: int, scan_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(template ids (k,), scan points (k, 3)) of a landmark file (schema in the module
    docstring); one-line ``DataError`` naming the file for anything else."""
    path = Path(path)
    data = read_json_file(path, f"--landmarks {path}", DataError)
    items = data.get("landmarks") if isinstance(data, dict) else None
    if not isinstance(items, list):
        raise DataError(f'--landmarks {path}: expected {{"landmarks": [{{"template": ID, "scan": ID or [x, y, z]}}, '
                        f'...]}}')
    if len(items) < MIN_LANDMARKS:
        raise DataError(f"--landmarks {path}: {len(items)} landmark(s), at least {MIN_LANDMARKS} needed "
                        f"(5-15 well spread: eye corners, nose tip, mouth corners, chin)")
    V = np.asarray(scan_vertices, dtype=np.float64)
    ids, points, scan_ids = [], [], []
    for i, it in enumerate(items):
        where = f"--landmarks {path}: landmark {i + 1}"
        if not isinstance(it, dict) or set(it) != {"template", "scan"}:
            raise DataError(f'{where}: expected {{"template": ID, "scan": ID or [x, y, z]}}, got {str(it)[:80]}')
        t, s = it["template"], it["scan"]
        if not _is_int(t) or not 0 <= t < n_template:
            raise DataError(f"{where}: template vertex {str(t)[:40]} out of range (0-based ids 0..{n_template - 1})")
        if _is_int(s):
            if not 0 <= s < len(V):
                raise DataError(f"{where}: scan vertex {s} out of range (0-based ids 0..{len(V) - 1})")
            scan_ids.append(s)
            p = V[s]
        elif isinstance(s, list) and len(s) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                         for x in s):
            p = np.asarray(s, dtype=np.float64)
            if not np.all(np.isfinite(p)):
                raise DataError(f"{where}: the scan point {s} is not finite")
        else:
            raise DataError(f"{where}: scan must be a vertex id or a point [x, y, z], got {str(s)[:60]}")
        if t in ids:
            raise DataError(f"{where}: template vertex {t} is given twice")
        ids.append(int(t))
        points.append(p)
    if len(set(scan_ids)) < len(scan_ids):
        dup = next(s for s in scan_ids if scan_ids.count(s) > 1)
        raise DataError(f"--landmarks {path}: scan vertex {dup} is given twice")
    return np.asarray(ids, dtype=np.int64), np.asarray(points, dtype=np.float64)


def _is_int(x) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


# ---------------------------------------------------------------------- similarity
def similarity(A: np.ndarray, B: np.ndarray, scale: float | None = None) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising sum |s R a_i + t - b_i|^2 (Umeyama; ``scale``: s fixed)."""
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    ma, mb = A.mean(0), B.mean(0)
    A0, B0 = A - ma, B - mb
    U, S, Vt = np.linalg.svd(B0.T @ A0 / len(A))
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    var = (A0 ** 2).sum() / len(A)
    s = float(np.trace(np.diag(S) @ D) / var) if scale is None else float(scale)
    return s, R, mb - s * R @ ma


def _check_spread(P: np.ndarray, what: str) -> None:
    """Landmarks spanning a plane at least (not one point or a line)."""
    sv = np.linalg.svd(P - P.mean(0), compute_uv=False)
    if not sv[0] > 0 or sv[1] < 1e-3 * sv[0]:
        raise DataError(f"{what}: the landmarks lie on one line or point; give well spread ones")


def landmark_residuals(A: np.ndarray, B: np.ndarray, off: float = LANDMARK_OFF, keep_min: int = 4
                       ) -> tuple[np.ndarray, float, np.ndarray]:
    """(r (k,), S, indices off) of step 8: r_i = |s R a_i + t - b_i| for the similarity (scale
    free) fitted to the landmarks kept after dropping, one at a time, the one farthest off while
    any kept one lies beyond ``off`` S (at least ``keep_min`` kept), S the spread of all the b_i;
    off: the landmarks with r_i > ``off`` S. (One fit to all of them would let a swapped pair pull
    the others off too: with 6 landmarks, 0.32 S for every right one.)"""
    A, B = np.asarray(A, dtype=np.float64), np.asarray(B, dtype=np.float64)
    S = float(np.sqrt(((B - B.mean(0)) ** 2).sum(1).mean()))
    keep = np.ones(len(A), dtype=bool)
    while True:
        s, R, t = similarity(A[keep], B[keep])
        r = np.linalg.norm(s * A @ R.T + t - B, axis=1)
        worst = int(np.argmax(np.where(keep, r, -1.0)))
        if keep.sum() <= keep_min or not r[worst] > off * S:
            return r, S, np.flatnonzero(r > off * S)
        keep[worst] = False


def detect_units(s: float, template_units: str) -> tuple[float, str | None]:
    """(u, unit name or None): one scan unit is u template units, from the landmarks' size
    ratio s (scan size over template size): a named unit within ``UNIT_SNAP`` of 1/s, else 1/s."""
    if template_units in METRES_PER_UNIT:
        mine = METRES_PER_UNIT[template_units]
        best = min(METRES_PER_UNIT, key=lambda u: abs(math.log(METRES_PER_UNIT[u] / mine * s)))
        if abs(math.log(METRES_PER_UNIT[best] / mine * s)) < math.log(UNIT_SNAP):
            return METRES_PER_UNIT[best] / mine, best
    return 1.0 / s, None


# ---------------------------------------------------------------------- closest points
def _incidence(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR (indptr, triangle ids) of the triangles around each vertex."""
    v = F.reshape(-1)
    order = np.argsort(v, kind="stable")
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(indptr, v + 1, 1)
    return np.cumsum(indptr), (order // 3).astype(np.int64)


def closest_points(V: np.ndarray, F: np.ndarray, points: np.ndarray, nearest: int = NEAREST,
                   chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(triangle (p,), barycentric (p, 3), distance (p,)) of each point's closest point on the
    mesh (V, F), searched among the triangles around its ``nearest`` nearest vertices."""
    from trimesh.triangles import closest_point as tri_closest, points_to_barycentric  # trimesh: ~0.75 s import

    V, F, points = np.asarray(V, np.float64), np.asarray(F, np.int64), np.asarray(points, np.float64)
    indptr, tris = _incidence(F, len(V))
    _, nn = cKDTree(V).query(points, k=min(nearest, len(V)))
    nn = nn.reshape(len(points), -1)
    tri_out = np.zeros(len(points), dtype=np.int64)
    bary = np.zeros((len(points), 3))
    dist = np.zeros(len(points))
    for a in range(0, len(points), chunk):
        v = nn[a:a + chunk].reshape(-1)
        cnt = indptr[v + 1] - indptr[v]
        pid = np.repeat(np.repeat(np.arange(a, min(a + chunk, len(points))), nn.shape[1]), cnt)
        start = np.repeat(indptr[v], cnt)
        offs = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        cand = tris[start + offs]
        q = tri_closest(V[F[cand]], points[pid])
        d = np.linalg.norm(q - points[pid], axis=1)
        order = np.lexsort((d, pid))
        first = order[np.r_[True, pid[order][1:] != pid[order][:-1]]]
        p = pid[first]
        tri_out[p], dist[p] = cand[first], d[first]
        b = points_to_barycentric(V[F[cand[first]]], q[first])
        b = np.clip(np.nan_to_num(b, nan=1.0 / 3), 0.0, None)
        bary[p] = b / np.maximum(b.sum(1, keepdims=True), 1e-300)
    return tri_out, bary, dist


# ---------------------------------------------------------------------- registration
@dataclass
class Registration:
    """A scan registered to a template (see the module docstring): the registered neutral Y in
    the template's frame and units, the scan's correspondence and the similarity between them."""

    neutral: np.ndarray          # (n, 3) Y: template topology, template frame and units
    triangles: np.ndarray        # (m, 3) the template's
    scan: np.ndarray             # (p, 3) the scan's vertices, its own frame and units
    rotation: np.ndarray         # (3, 3) R: scan = R Y / u + t
    translation: np.ndarray      # (3,) t
    unit: float                  # u: one scan unit is u template units
    unit_name: str | None        # the detected or given unit, when named
    triangle: np.ndarray         # (p,) each scan vertex's closest triangle of Y
    bary: np.ndarray             # (p, 3) its barycentric coordinates
    distance: np.ndarray         # (p,) the residual, scan units
    weight: np.ndarray           # (p,) w_j
    tolerance: float             # FIT_TOLERANCE h, scan units
    template_missing: np.ndarray  # (n,) bool: template vertices farther than the tolerance from the scan
    template_landmarks: np.ndarray
    scan_landmarks: np.ndarray
    seconds: float
    folded: np.ndarray | None = None  # (m,) bool: triangles of Y folded against the template's (step 7)
    landmark_residual: np.ndarray | None = None  # (k,) r_i, scan units (step 8)
    landmark_spread: float | None = None         # S, scan units

    @property
    def landmarks_off(self) -> np.ndarray:
        """Indices (into the landmark file's order) of the landmarks likely misplaced (step 8)."""
        if self.landmark_residual is None or not self.landmark_spread:
            return np.zeros(0, dtype=np.int64)
        return np.flatnonzero(self.landmark_residual > LANDMARK_OFF * self.landmark_spread)

    @property
    def fitted(self) -> np.ndarray:
        return self.distance <= self.tolerance

    def to_scan(self, Y: np.ndarray) -> np.ndarray:
        """Template-frame positions (..., 3) in the scan's frame and units."""
        return np.asarray(Y) @ self.rotation.T / self.unit + self.translation

    def carry(self, expression: np.ndarray) -> np.ndarray:
        """The scan's vertices (p, 3) moved by an expression (n, 3) of the registered neutral
        (template frame): V + w R (sum_k b_k Delta[T[tau, k]]) / u."""
        delta = np.asarray(expression, dtype=np.float64) - self.neutral
        corners = self.triangles[self.triangle]                        # (p, 3)
        d = np.einsum("pk,pkc->pc", self.bary, delta[corners])         # (p, 3) template frame
        return self.scan + self.weight[:, None] * (d @ self.rotation.T) / self.unit

    def summary(self) -> dict:
        fit = self.fitted
        d = self.distance
        return {"scan_vertices": int(len(d)), "fitted": int(fit.sum()), "not_fitted": int((~fit).sum()),
                "still": int((self.weight == 0).sum()),
                "residual_mean": float(d[fit].mean()) if fit.any() else float("nan"),
                "residual_max": float(d[fit].max()) if fit.any() else float("nan"),
                "residual_mean_all": float(d.mean()), "residual_max_all": float(d.max()),
                "tolerance": float(self.tolerance), "template_missing": int(self.template_missing.sum()),
                "folded": int(self.folded.sum()) if self.folded is not None else 0,
                "landmarks_off": [int(i) for i in self.landmarks_off],
                "landmark_residual_max": (float(self.landmark_residual.max()) if self.landmark_residual is not None
                                          else float("nan")),
                "unit": float(self.unit), "unit_name": self.unit_name, "seconds": float(self.seconds)}

    def arrays(self) -> dict:
        """Arrays only (``correspondence.npz``)."""
        return {"triangle": self.triangle, "bary": self.bary, "distance": self.distance, "weight": self.weight,
                "fitted": self.fitted, "rotation": self.rotation, "translation": self.translation,
                "unit": np.float64(self.unit), "neutral_template_frame": self.neutral,
                "neutral": self.to_scan(self.neutral), "template_triangles": self.triangles,
                "template_missing": self.template_missing, "template_landmarks": self.template_landmarks,
                "scan_landmarks": self.scan_landmarks, "tolerance": np.float64(self.tolerance),
                **({"folded": self.folded} if self.folded is not None else {}),
                **({"landmark_residual": self.landmark_residual} if self.landmark_residual is not None else {})}


def render_residual(reg: Registration, scan_triangles: np.ndarray, path, unit: str) -> Path:
    """``path`` (PNG): the scan, taken into the template's frame (where the head looks along +z,
    y up), from the front and the side, coloured by its residual ``reg.distance`` (scan units,
    ``unit`` names them) on one colour bar from 0 to the 99th percentile
    (``fwk.evaluation.render.colour_limits``); a larger residual saturates, its bar end marked ≥."""
    X = (reg.scan - reg.translation) @ reg.rotation * reg.unit
    clim = colour_limits([reg.distance])
    bar = f"residual ({unit})"
    cells = [[{"V": X, "scalars": reg.distance, "clim": clim, "bar": bar, "cmap": "inferno", "label": label,
               "view": view} for label, view in (("front", "front"), ("side", "side"))]]
    return render_grid(cells, Template(X, scan_triangles), path)


def folded_triangles(template: np.ndarray, registered: np.ndarray, triangles: np.ndarray,
                     min_area_ratio: float = MIN_AREA_RATIO) -> np.ndarray:
    """(m,) bool: the triangles of ``registered`` (the template's topology, in its frame: normals
    are compared as they are, so the two must not be rotated against each other) whose
    normal points against the template's (n_Y . n_M < 0) or whose area fell below
    ``min_area_ratio`` of the template's. A triangle degenerate on the template is not judged."""
    def cross(V):
        V = np.asarray(V, dtype=np.float64)
        return np.cross(V[triangles[:, 1]] - V[triangles[:, 0]], V[triangles[:, 2]] - V[triangles[:, 0]])

    triangles = np.asarray(triangles, dtype=np.int64)
    cm, cy = cross(template), cross(registered)
    am, ay = np.linalg.norm(cm, axis=1), np.linalg.norm(cy, axis=1)
    judged = am > 1e-12 * max(float(am.max(initial=0.0)), 1e-300)
    return judged & (((cm * cy).sum(1) < 0) | (ay < min_area_ratio * am))


def median_edge(V: np.ndarray, F: np.ndarray) -> float:
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    return float(np.median(np.linalg.norm(V[e[:, 0]] - V[e[:, 1]], axis=1)))


def register(template: np.ndarray, triangles: np.ndarray, scan: np.ndarray, scan_triangles: np.ndarray,
             template_ids: np.ndarray, scan_points: np.ndarray, units: float | None = None,
             template_units: str = "unit", steps=STEPS, say=_stderr, fit=None) -> Registration:
    """Register ``template`` (n, 3; ``triangles``) to ``scan`` (p, 3; ``scan_triangles``) with
    landmark pairs (template vertex ids, scan points); ``units``: one scan unit in template
    units (None: detected); ``say``: progress lines (None: silent); ``fit``: the non-rigid fit,
    ``fwk.rig.nricp.nricp_amberg`` when None (``"trimesh"``: trimesh's own, which
    ``benchmarks/register.py`` times beside it)."""
    from trimesh import Trimesh  # ~0.75 s import, only here
    from trimesh.sample import sample_surface

    from .nricp import nricp_amberg

    t0 = time.perf_counter()
    M = np.asarray(template, dtype=np.float64)
    F = np.asarray(triangles, dtype=np.int64)
    V = np.asarray(scan, dtype=np.float64)
    SF = np.asarray(scan_triangles, dtype=np.int64)
    ids = np.asarray(template_ids, dtype=np.int64)
    B = np.asarray(scan_points, dtype=np.float64)
    if len(ids) < MIN_LANDMARKS:
        raise DataError(f"landmarks: {len(ids)}, at least {MIN_LANDMARKS} needed")
    if not np.all(np.isfinite(V)):
        raise DataError("the scan's vertex positions contain NaN or infinite values")
    _check_spread(M[ids], "landmarks (template side)")
    _check_spread(B, "landmarks (scan side)")
    s0, R, t = similarity(M[ids], B)
    lm_res, lm_spread, _ = landmark_residuals(M[ids], B)  # step 8, scan units
    if units is None:
        u, name = detect_units(s0, template_units)
    else:
        u, name = float(units), None
    s, R, t = similarity(M[ids], B, scale=1.0 / u)
    X = (V - t) @ R * u          # the scan in the template frame: u R^T (V - t)
    XL = (B - t) @ R * u
    h = median_edge(M, F)
    if say:
        say(f"fwk register: similarity from {len(ids)} landmarks: scale {s0:.4g} scan units per template unit, "
            f"so one scan unit = {u:.4g} template units{f' ({name})' if name else ''}; landmark residual "
            f"{np.linalg.norm(M[ids] - XL, axis=1).mean():.3g} template units (rigid)")
    # target: scan vertices plus samples of its triangles, up to TARGET_DENSITY points per template vertex
    extra = int(TARGET_DENSITY * len(M)) - len(X)
    pts = X
    if extra > 0 and len(SF):
        smp, _ = sample_surface(Trimesh(X, SF, process=False), extra, seed=0)
        pts = np.concatenate([X, smp])
    if say:
        say(f"fwk register: non-rigid fit (nricp_amberg, {sum(int(st[3]) for st in steps)} iterations) of the "
            f"template's {len(M)} vertices to {len(pts)} scan points ...")
    if fit == "trimesh":
        from trimesh import PointCloud
        from trimesh.registration import nricp_amberg as trimesh_nricp

        Y = np.asarray(trimesh_nricp(Trimesh(M.copy(), F, process=False), PointCloud(pts.copy()), source_landmarks=ids,
                                     target_positions=XL.copy(), steps=[list(st) for st in steps], eps=EPS,
                                     distance_threshold=DISTANCE_THRESHOLD, use_faces=False), dtype=np.float64)
    else:
        Y = nricp_amberg(M, F, pts, ids, XL, steps=[list(st) for st in steps], eps=EPS,
                         distance_threshold=DISTANCE_THRESHOLD)
    t_fit = time.perf_counter() - t0
    tri, bary, dist = closest_points(Y, F, X)
    tol = FIT_TOLERANCE * h
    w = np.clip((FADE * tol - dist) / ((FADE - 1.0) * tol), 0.0, 1.0)
    d_tpl, _ = cKDTree(pts).query(Y)
    seconds = time.perf_counter() - t0
    reg = Registration(neutral=Y, triangles=F, scan=V, rotation=R, translation=t, unit=u, unit_name=name,
                       triangle=tri, bary=bary, distance=dist / u, weight=w, tolerance=tol / u,
                       template_missing=d_tpl > tol, template_landmarks=ids, scan_landmarks=B, seconds=seconds,
                       folded=folded_triangles(M, Y, F), landmark_residual=lm_res, landmark_spread=lm_spread)
    if say:
        sm = reg.summary()
        say(f"fwk register: fitted in {t_fit:.1f} s, correspondence {seconds - t_fit:.1f} s: residual mean "
            f"{sm['residual_mean']:.3g}, max {sm['residual_max']:.3g} scan units over {sm['fitted']} fitted scan "
            f"vertices; {sm['not_fitted']} not fitted (> {tol / u:.3g}), {sm['template_missing']} template vertices "
            f"without scan; {sm['folded']} triangles folded")
        off = reg.landmarks_off
        ok = np.delete(lm_res, off)
        for i in off:
            say(f"fwk register: warning: landmark {i + 1} (template vertex {ids[i]}) lies {lm_res[i]:.3g} scan units "
                f"from where the other landmarks place it ({lm_res[i] / lm_spread:.2f} of their spread; the others "
                f"{ok.min() if len(ok) else 0:.3g}-{ok.max() if len(ok) else 0:.3g}): likely given for another place "
                f"(the other side?); check the landmark file")
        if sm["folded"]:
            say(f"fwk register: warning: {sm['folded']} of the registered template's {len(F)} triangles are folded "
                f"(turned over or collapsed against the template's): check the landmarks (a pair given for the "
                f"wrong side, a point off the head); the rig bends where they are (`folded` in correspondence.npz)")
    return reg
