"""``ict-facekit``: identities and expressions sampled from ICT-FaceKit's FaceXModel.

ICT-FaceKit (USC ICT, MIT licence) is a light-stage face model: a generic neutral, 100
identity modes (``identityXXX.obj`` = neutral + one mode) and 53 expression blendshapes, all
26,719 vertices in 17 parts, units centimetres, y up, face along +z. This plugin reads the
``FaceXModel`` folder as published, or the ``FaceXModel.tar.xz`` archive directly.

Identities: subject s has identity weights w_s ~ N(0, sigma^2 I) (seeded) and neutral
N_s = N_0 + sum_m w_sm (I_m - N_0).

Expressions are named composites of blendshapes with weights; built in are the thesis's three:

* ``face-compression``: browDown, eyeSquint, cheekSquint, noseSneer, mouthPress (L and R) and
  mouthShrugUpper/Lower, mouthRollLower;
* ``mouth-wide``: jawOpen, mouthStretch (L, R), mouthLowerDown (L, R), mouthUpperUp (L, R);
* ``oo-brow-raise-eyes-wide``: mouthFunnel, mouthPucker, browInnerUp, browOuterUp (L, R),
  eyeWide (L, R);

more can be defined in a recipe (``expressions: {name: {blendshape: weight}}``). Every one of
ICT-FaceKit's 57 expression blendshapes (``ICT_BLENDSHAPES``: ``jawOpen``, ``eyeBlink_L``, ...;
the archive's README says 53) is an expression of its own too, the blendshape at weight 1:
``shapes`` takes their names, a list mixing them with composites, or ``all`` (every blendshape,
in ``ICT_BLENDSHAPES`` order; ``[all, mouth-wide]`` adds composites). In the face-head region
``PupilDilate_L``/``_R`` move 74-78 vertices by at most 0.005 cm (they move the eyes, outside the
region); every other blendshape moves thousands of its vertices by 0.25-4.2 cm.

Personalisation (synthetic; ICT-FaceKit's blendshapes belong to the generic face): the
expression delta D_e = sum_b a_b (B_b - N_0) is personalised for subject s as
D_{e,s}(v) = (1 + 0.1 k_e . w_s) f_{e,s}(v) J_s D_e(v) with k_e ~ N(0, I / 100), where (i) a
per-expression random direction k_e in identity space changes the amplitude with the
identity, (ii) f_{e,s}(v) = 1 + 0.2 tanh(sum_r c_{e,s,r} phi_r(v)), c_{e,s} = w_s C_e / 10, is a
smooth spatial field (Gaussian bumps phi_r at 8 seeded points of the region, a quarter of its
extent wide) that makes some parts of a face move more than others depending on the identity,
and (iii) J_s rescales the delta per axis by the ratio of the subject's face extent to the
generic face's (a wider face makes a wider expression). k_e and C_e are seeded per expression.
The points, width and extents are the region's; for ``full`` they are face-head's (the field is
evaluated on every vertex), so that full's first 11,248 vertices equal face-head's in every shape
and the parts outside move with the same personalisation as the face next to them (a blendshapes
run's ``follow: {region: full}`` relies on it). ``personalise: false`` adds D_e unchanged to every neutral.

Regions: ``face-head`` (default: the first 11,248 vertices and 11,144 quads), ``face``
(the polygons of material ``M_Face``), ``narrow-face`` (``face`` restricted to ICT's fitting
vertices), ``full`` (all 26,719 vertices, 56 connected pieces).
"""
from __future__ import annotations

import hashlib
import json
import os
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from fwk.data import MeshCollection, Template
from fwk.data.io import fan_triangulate, read_obj
from fwk.errors import DataError, RecipeError
from fwk.hookspecs import hookimpl
from fwk.registry import did_you_mean

BUILTIN_EXPRESSIONS = {
    "face-compression": {"browDown_L": 1.0, "browDown_R": 1.0, "eyeSquint_L": 1.0, "eyeSquint_R": 1.0,
                         "cheekSquint_L": 1.0, "cheekSquint_R": 1.0, "noseSneer_L": 0.8, "noseSneer_R": 0.8,
                         "mouthPress_L": 1.0, "mouthPress_R": 1.0, "mouthShrugUpper": 0.6, "mouthShrugLower": 0.6,
                         "mouthRollLower": 0.4},
    "mouth-wide": {"jawOpen": 0.9, "mouthStretch_L": 0.8, "mouthStretch_R": 0.8, "mouthLowerDown_L": 0.7,
                   "mouthLowerDown_R": 0.7, "mouthUpperUp_L": 0.5, "mouthUpperUp_R": 0.5},
    "oo-brow-raise-eyes-wide": {"mouthFunnel": 0.8, "mouthPucker": 0.8, "browInnerUp_L": 1.0, "browInnerUp_R": 1.0,
                                "browOuterUp_L": 1.0, "browOuterUp_R": 1.0, "eyeWide_L": 1.0, "eyeWide_R": 1.0},
}
#: ICT-FaceKit's expression blendshapes (FaceXModel/<name>.obj), each also an expression of weight 1
ICT_BLENDSHAPES = (
    "browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
    "cheekPuff_L", "cheekPuff_R", "cheekRaiser_L", "cheekRaiser_R", "cheekSquint_L", "cheekSquint_R",
    "eyeBlink_L", "eyeBlink_R", "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R",
    "eyeLookOut_L", "eyeLookOut_R", "eyeLookUp_L", "eyeLookUp_R", "eyeSquint_L", "eyeSquint_R",
    "eyeWide_L", "eyeWide_R", "jawForward", "jawLeft", "jawOpen", "jawRight", "mouthClose",
    "mouthDimple_L", "mouthDimple_R", "mouthFrown_L", "mouthFrown_R", "mouthFunnel", "mouthLeft",
    "mouthLowerDown_L", "mouthLowerDown_R", "mouthPress_L", "mouthPress_R", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmile_L", "mouthSmile_R",
    "mouthStretch_L", "mouthStretch_R", "mouthUpperUp_L", "mouthUpperUp_R", "noseSneer_L", "noseSneer_R",
    "PupilDilate_L", "PupilDilate_R",
)
ALL = "all"  # shapes: every blendshape
#: what the folder is and where it comes from, for error texts (a user's clone has no shared/ folder)
WHERE = ("ICT-FaceKit's FaceXModel folder (the FaceXModel folder of github.com/ICT-VGL/ICT-FaceKit, MIT "
         "licence, or its FaceXModel.tar.xz; set dataset.path or $FWK_ICT_PATH to it)")
REGIONS = ("face-head", "face", "narrow-face", "full")
FACE_HEAD = (11248, 11144)


def default_path() -> str | None:
    """$FWK_ICT_PATH, else a ``shared/data/ict-facekit`` data folder in or above the working
    directory (its FaceXModel folder, else its archive), else None."""
    env = os.environ.get("FWK_ICT_PATH")
    if env:
        return env
    for base in (Path.cwd(), *Path.cwd().parents):
        d = base / "shared" / "data" / "ict-facekit"  # name-ok: the data folder beside the repo
        if (d / "FaceXModel").exists() or (d / "FaceXModel.tar.xz").exists():
            return str(d / "FaceXModel") if (d / "FaceXModel").exists() else str(d / "FaceXModel.tar.xz")
    return None


class ICTFaceKit:
    """ICT-FaceKit identities (sampled) with personalised expressions: each blendshape, and composites."""

    name = "ict-facekit"

    def __init__(self, path: str | None = None, region: str = "face-head", n_subjects: int = 200,
                 sigma: float = 1.0, shapes: list[str] | str | None = None,
                 expressions: dict[str, dict[str, float]] | None = None, personalise: bool = True, seed: int = 0):
        if region not in REGIONS:
            raise RecipeError(f"dataset.region: unknown region {region!r}{did_you_mean(region, REGIONS)} "
                              f"(regions: {', '.join(REGIONS)})")
        self.path = path or default_path()
        self.region, self.n_subjects, self.sigma = region, n_subjects, sigma
        self.expressions = {**{b: {b: 1.0} for b in ICT_BLENDSHAPES}, **BUILTIN_EXPRESSIONS, **(expressions or {})}
        if isinstance(shapes, str):
            shapes = [shapes]
        self.shapes = []
        for s in (list(shapes) if shapes else ["neutral", *BUILTIN_EXPRESSIONS]):
            for x in (ICT_BLENDSHAPES if s == ALL else [s]):
                if x != "neutral" and x not in self.expressions:
                    raise RecipeError(f"dataset.shapes: unknown expression {x!r}"
                                      f"{did_you_mean(x, [*self.expressions, ALL])} (a blendshape of ICT-FaceKit, "
                                      f"a composite ({', '.join(BUILTIN_EXPRESSIONS)}, or `expressions:`) or {ALL})")
                if x not in self.shapes:
                    self.shapes.append(x)
        if "neutral" not in self.shapes:
            self.shapes.insert(0, "neutral")
        self.personalise, self.seed = personalise, seed

    # --------------------------------------------------------------------- files
    def _folder(self) -> Path:
        if self.path is None:
            raise DataError(f"dataset.path: not given and $FWK_ICT_PATH not set; give {WHERE}")
        p = Path(self.path)
        if p.is_dir():
            if not (p / "generic_neutral_mesh.obj").exists():
                raise DataError(f"dataset.path: {p} has no generic_neutral_mesh.obj: not {WHERE}")
            return p
        if p.is_file() and p.name.endswith((".tar.xz", ".tar", ".tar.gz")):
            st = p.stat()
            tag = hashlib.sha256(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()).hexdigest()[:16]
            out = Path(tempfile.gettempdir()) / f"fwk-ict-{tag}"  # stable across processes
            if not (out / "FaceXModel" / ".complete").exists():
                tmp = Path(tempfile.mkdtemp(dir=out.parent if out.parent.exists() else None))
                with tarfile.open(p) as tf:
                    tf.extractall(tmp, filter="data")
                out.mkdir(parents=True, exist_ok=True)
                (tmp / "FaceXModel").rename(out / "FaceXModel") if not (out / "FaceXModel").exists() else None
                (out / "FaceXModel" / ".complete").touch()
            return out / "FaceXModel"
        raise DataError(f"dataset.path: {p} does not exist; give {WHERE}")

    def _read_all(self, folder: Path, names: list[str], cache) -> np.ndarray:
        def build():
            out = np.empty((len(names), 26719, 3))
            for i, n in enumerate(names):
                V, _ = read_obj(folder / f"{n}.obj", units="cm")
                if len(V) != out.shape[1]:
                    raise DataError(f"{folder / (n + '.obj')}: {len(V)} vertices, expected {out.shape[1]}")
                out[i] = V
            return out

        if cache is None:
            return build()
        stamp = [(n, (folder / f"{n}.obj").stat().st_size) for n in names]
        return cache.memmap_array(self.name, (str(folder.resolve()), stamp), build)

    def _region(self, t: Template, folder: Path):
        off = t.poly_offsets
        if self.region == "full":
            keep_poly = np.arange(t.n_polygons)
        elif self.region == "face-head":
            keep_poly = np.arange(FACE_HEAD[1])
        else:
            names = [(pos, line.split(" ", 1)[1]) for pos, line in t.obj_extra if line.startswith("usemtl")]
            starts = [p for p, _ in names] + [t.n_polygons]
            keep_poly = np.concatenate([np.arange(starts[i], starts[i + 1]) for i, (_, n) in enumerate(names)
                                        if n.strip() == "M_Face"])
            if self.region == "narrow-face":
                fit = set(json.loads((folder / "vertex_indices.json").read_text())["idx_to_fitting_verts"])
                ok = [p for p in keep_poly if all(v in fit for v in t.poly_vertices[off[p]:off[p + 1]])]
                keep_poly = np.asarray(ok, dtype=np.int64)
        corners = np.concatenate([np.arange(off[p], off[p + 1]) for p in keep_poly])
        verts = np.unique(t.poly_vertices[corners]) if self.region not in ("full", "face-head") else \
            np.arange(t.n_vertices if self.region == "full" else FACE_HEAD[0])
        remap = -np.ones(t.n_vertices, dtype=np.int64)
        remap[verts] = np.arange(len(verts))
        pv = remap[t.poly_vertices[corners]]
        if (pv < 0).any():
            raise DataError(f"ict-facekit: region {self.region} polygons use vertices outside the region")
        sizes = np.diff(off)[keep_poly]
        new_off = np.concatenate([[0], np.cumsum(sizes)])
        uv_corners = t.poly_uvs[corners] if t.poly_uvs is not None else None
        extra = [(pos, line) for pos, line in t.obj_extra if pos == 0 and line.startswith("mtllib")]
        if self.region != "full":
            extra.append((0, "usemtl M_Face"))
        else:
            extra = list(t.obj_extra)
        sub = Template(t.vertices[verts], fan_triangulate(pv, new_off), pv, new_off, t.uvs, uv_corners, extra,
                       units="cm", name=f"ict-facekit-{self.region}", uv_lines=t.uv_lines)
        return verts, sub

    def _personalised(self, D, N0, W, neutrals, ext0, j, ref=slice(None)):
        """(S, n, 3) the expression delta D personalised per identity (synthetic model, see the
        module docstring): amplitude a_s = 1 + 0.1 k_e . w_s, a smooth spatial field
        f_s(v) = 1 + 0.2 tanh(sum_r c_sr phi_r(v)) with c_s = w_s C_e / 10 and phi_r Gaussian
        bumps (width a quarter of the region's extent) at R = 8 seeded points of the region,
        and J_s the per-axis ratio of the subject's extent to the generic neutral's."""
        rng = np.random.default_rng([self.seed, j, 17])
        k = rng.normal(size=100) / 10.0  # |k| ~ 1
        amp = 1.0 + 0.1 * (W @ k)  # about 1 +- 0.1 sigma
        centres = N0[ref][rng.choice(len(N0[ref]), 8, replace=False)]
        width = 0.25 * float(np.linalg.norm(ext0))
        phi = np.exp(-0.5 * ((N0[None] - centres[:, None]) ** 2).sum(-1) / width ** 2)  # (8, n)
        C = rng.normal(size=(100, 8))
        field = 1.0 + 0.2 * np.tanh((W @ C / 10.0) @ phi)  # (S, n)
        J = self._extent / ext0  # (S, 3)
        return (amp[:, None] * field)[..., None] * D[None] * J[:, None, :]

    # ---------------------------------------------------------------------- load
    def load(self, cache=None) -> MeshCollection:
        folder = self._folder()
        V0, t_full = read_obj(folder / "generic_neutral_mesh.obj", units="cm")
        blend = sorted({b for e in self.shapes if e != "neutral" for b in self.expressions[e]})
        for b in blend:
            if not (folder / f"{b}.obj").exists():
                raise DataError(f"{folder / (b + '.obj')}: blendshape used by an expression does not exist "
                                f"(is {folder} {WHERE}?)")
        ids = [f"identity{i:03d}" for i in range(100)]
        data = self._read_all(folder, ids + blend, cache)
        verts, template = self._region(t_full, folder)
        N0 = V0[verts]
        modes = np.asarray(data[:100])[:, verts] - N0
        rng = np.random.default_rng(self.seed)
        W = rng.normal(0.0, self.sigma, (self.n_subjects, 100))
        neutrals = N0 + (W @ modes.reshape(100, -1)).reshape(self.n_subjects, len(verts), 3)  # BLAS, not einsum
        out = np.empty((self.n_subjects, len(self.shapes), len(verts), 3))
        out[:, 0] = neutrals
        # the personalisation's reference vertices: the region's own, but for ``full`` the
        # face-head's, so that full's first 11,248 vertices are face-head's exactly (the face a
        # face-head model learned, continued onto the teeth, eyes, ...: a blendshapes run's follow:)
        ref = slice(0, FACE_HEAD[0]) if self.region == "full" else slice(None)
        ext0 = N0[ref].max(0) - N0[ref].min(0)
        self._extent = neutrals[:, ref].max(1) - neutrals[:, ref].min(1)
        for j, e in enumerate(self.shapes[1:], start=1):
            D = np.zeros_like(N0)
            for b, a in self.expressions[e].items():
                D += a * (np.asarray(data[100 + blend.index(b)])[verts] - N0)
            if self.personalise:
                out[:, j] = neutrals + self._personalised(D, N0, W, neutrals, ext0, j, ref)
            else:
                out[:, j] = neutrals + D
        template.vertices = neutrals[0].copy()
        subjects = [f"ict{i:04d}" for i in range(self.n_subjects)]
        return MeshCollection(template, subjects, list(self.shapes), out, name=self.name)


@hookimpl
def fwk_register_datasets():
    return [ICTFaceKit]
