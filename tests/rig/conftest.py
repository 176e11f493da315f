"""Fixtures of the rig tests: a small blendshapes run on quad grids with UVs and a UV seam, its
expressions named as ICT-FaceKit names them (DT only: seconds), and a run of the smoke rig
recipe (conditional PBS and DT on synthetic-heads)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

W = 7  # (W+1) x (W+1) vertices, W x W quads
SEAM = W // 2  # quads right of this column use a second copy of its vt: a UV seam
EXPRESSIONS = ("jawOpen", "browInnerUp_L", "browInnerUp_R", "face-x")
REPO = Path(__file__).resolve().parents[2]


def grid_obj(V, extra_v=None, extra_f=None) -> str:
    """A quad grid OBJ with vt lines, a material switch and a UV seam; ``extra_v`` / ``extra_f``
    append vertices and polygons after the grid's (a larger mesh the grid is the first part of)."""
    lines = ["mtllib head.mtl", "o head"]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in V]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in (extra_v if extra_v is not None else [])]
    lines += [f"vt {i / W:.4f} {j / W:.4f}" for j in range(W + 1) for i in range(W + 1)]
    lines += [f"vt {SEAM / W + 0.01:.4f} {j / W:.4f}" for j in range(W + 1)]  # the seam's second copies
    lines.append("usemtl skin")
    n_vt = (W + 1) ** 2
    for j in range(W):
        for i in range(W):
            a = j * (W + 1) + i
            q = [a, a + 1, a + W + 2, a + W + 1]
            t = [v if not (i >= SEAM and v % (W + 1) == SEAM) else n_vt + v // (W + 1) for v in q]
            lines.append("f " + " ".join(f"{v + 1}/{u + 1}" for v, u in zip(q, t)))
            if (i, j) == (W // 2, W // 2):
                lines.append("usemtl lips")
    for f in (extra_f if extra_f is not None else []):
        lines.append("f " + " ".join(str(v + 1) for v in f))
    return "\n".join(lines) + "\n"


def neutral(rng):
    """A bumpy grid head, randomly widened."""
    x, y = np.meshgrid(np.linspace(-1, 1, W + 1), np.linspace(-1, 1, W + 1))
    z = 0.3 * np.exp(-(x ** 2 + y ** 2)) + 0.05 * rng.standard_normal(x.shape)
    return np.stack([x.ravel() * (1 + 0.1 * rng.standard_normal()), y.ravel(), z.ravel()], 1) * 10.0


def expression(V, e):
    """A smooth, identity-dependent expression ``e`` of neutral V."""
    c = {"jawOpen": (0.0, -5.0), "browInnerUp_L": (-3.0, 5.0), "browInnerUp_R": (3.0, 5.0), "face-x": (0.0, 0.0)}[e]
    out = V.copy()
    out[:, 2] += 2.0 * np.exp(-0.04 * ((V[:, 0] - c[0]) ** 2 + (V[:, 1] - c[1]) ** 2)) * (1 + 0.1 * V[:, 2])
    return out


def _execute(recipe: dict, tmp: Path) -> Path:
    from fwk.runs import execute

    path = tmp / "recipe.yaml"
    path.write_text(yaml.safe_dump(recipe))
    return execute(str(path), runs_dir=str(tmp / "runs"), quiet=True)


@pytest.fixture(scope="session")
def grid_run(tmp_path_factory):
    """A finished blendshapes run (DT) on 8 grid heads with ICT-FaceKit-named expressions, in cm."""
    root = tmp_path_factory.mktemp("grid-heads")
    rng = np.random.default_rng(0)
    for s in range(8):
        V = neutral(rng)
        (root / f"s{s}").mkdir()
        (root / f"s{s}" / "neutral.obj").write_text(grid_obj(V))
        for e in EXPRESSIONS:
            (root / f"s{s}" / f"{e}.obj").write_text(grid_obj(expression(V, e)))
    recipe = {"name": "rig-test", "task": "blendshapes", "seed": 0,
              "dataset": {"name": "mesh-folder", "root": str(root), "units": "cm"},
              "split": {"ratios": [0.6, 0.2, 0.2]},
              "models": {"dt": {"name": "dt", "sources": 0}}, "renders": 0, "metrics": ["l1", "l2"]}
    return _execute(recipe, root)


@pytest.fixture(scope="session")
def smoke_rig_run(tmp_path_factory):
    """A run of recipes/smoke/rig.yaml (about 20 s)."""
    tmp = tmp_path_factory.mktemp("smoke-rig")
    recipe = yaml.safe_load((REPO / "recipes" / "smoke" / "rig.yaml").read_text())
    return _execute(recipe, tmp)


@pytest.fixture(scope="session")
def shippable_rig_run(tmp_path_factory):
    """recipes/smoke/rig.yaml with the shipped rig model's form (recipes/rig_ict_shipped.yaml):
    anchored on DT from the mean training subject, scaled per channel, a k sweep that stops below
    n (about 15 s)."""
    tmp = tmp_path_factory.mktemp("shippable-rig")
    recipe = yaml.safe_load((REPO / "recipes" / "smoke" / "rig.yaml").read_text())
    recipe["name"], recipe["renders"] = "smoke-rig-shippable", 0
    recipe["models"]["pbs"].update({
        "anchor": {"name": "dt", "sources": "mean"}, "ks": [0, 10, 50, 200, 500],
        "spatial": {"name": "euclidean", "scaling": "std", "granularity": "channel"},
        "differential": {"name": "dr", "scaling": "std", "granularity": "channel"}})
    return _execute(recipe, tmp)
