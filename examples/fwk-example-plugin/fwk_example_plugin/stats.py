r"""An example third-party task: ``dataset-stats``, a summary of a dataset as the built-in tasks
would split it, written before anything is trained on it.

``fwk run`` of a recipe ``task: dataset-stats`` loads the recipe's dataset, splits it by subject
and fits the preprocessing on the training neutrals exactly as ``reconstruct`` and
``blendshapes`` do (``fwk.data.preprocess.split_and_preprocess``: ``split.json`` and
``stats/preprocess.npz``, the same split for the same ``seed`` and ``split``), and writes, per
split (train, val, test), in the dataset's own units (before centring, registration and
scaling):

* the subject count and the number of meshes (present shapes);
* the vertex, polygon and triangle counts of the template;
* the bounding-box extent: of the union of the split's meshes, E = max_{m, v} P_{m,v} -
  min_{m, v} P_{m,v} (per axis), and the mean over the split's neutrals of each one's own
  extent;
* per shape s other than the neutral, over the split's subjects that have both, the per-vertex
  displacement from the subject's neutral d_v = ||P^s_v - P^neutral_v||_2: its mean over
  subjects and vertices (1 / (S n)) sum_{i, v} d_{i,v} and its maximum max_{i, v} d_{i,v}
  (the displacement is invariant to the preprocessing's rigid motion per subject: it scales by
  its factor s alone, reported as ``scale``).

``metrics.json`` holds the figures (``ctx.write_json``), ``report.md`` the tables
(``ctx.write_text``); progress goes to the run's log (``ctx.log``). Registered through this
package's own entry point (``pyproject.toml``: ``[project.entry-points.fwk] example-stats =
"fwk_example_plugin.stats"``).
"""
from __future__ import annotations

from typing import Annotated

import numpy as np

from fwk.data.preprocess import PreprocessConfig, split_and_preprocess
from fwk.data.split import SplitConfig
from fwk.evaluation.tables import markdown_table
from fwk.hookspecs import hookimpl
from fwk.recipes import Kind, Spec, make_spec

SPLITS = ("train", "val", "test")
CHUNK = 64  # subjects read at a time (positions may be a memmap larger than memory)


def summarise(col, idx, shapes: list[str], neutral: str) -> dict:
    """The figures of one split: the subjects ``idx`` of the collection ``col`` (its own units),
    over the shapes ``shapes`` (the neutral among them)."""
    t = col.template
    j0 = col.shape_index(neutral)
    js = [col.shape_index(s) for s in shapes]
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    meshes, neutrals, extent_sum = 0, 0, np.zeros(3)
    disp = {s: {"subjects": 0, "sum": 0.0, "max": -np.inf} for s in shapes if s != neutral}
    for start in range(0, len(idx), CHUNK):
        sub = np.asarray(idx[start:start + CHUNK], dtype=np.int64)
        P = np.asarray(col.positions[sub], dtype=np.float64)      # (c, E, n, 3)
        present = np.asarray(col.present[sub])                     # (c, E)
        for s, j in zip(shapes, js):
            X = P[present[:, j], j]                                # (c', n, 3) the subjects that have s
            if not len(X):
                continue
            meshes += len(X)
            lo = np.minimum(lo, X.min(axis=(0, 1)))
            hi = np.maximum(hi, X.max(axis=(0, 1)))
            if s == neutral:
                neutrals += len(X)
                extent_sum += (X.max(axis=1) - X.min(axis=1)).sum(0)
                continue
            both = present[:, j] & present[:, j0]
            if both.any():
                d = np.linalg.norm(P[both, j] - P[both, j0], axis=-1)  # (c'', n)
                e = disp[s]
                e["subjects"] += int(both.sum())
                e["sum"] += float(d.sum())
                e["max"] = max(e["max"], float(d.max()))
    n = t.n_vertices
    return {
        "subjects": int(len(idx)),
        "meshes": int(meshes),
        "n_vertices": int(n),
        "n_faces": int(t.n_polygons),
        "n_triangles": int(len(t.triangles)),
        "extent": (hi - lo).tolist() if meshes else None,
        "neutral_extent_mean": (extent_sum / neutrals).tolist() if neutrals else None,
        "displacement": {s: {"subjects": e["subjects"],
                             "mean": e["sum"] / (e["subjects"] * n) if e["subjects"] else None,
                             "max": e["max"] if e["subjects"] else None}
                         for s, e in disp.items()},
    }


def _num(x, digits=4) -> str:
    return "–" if x is None else f"{x:.{digits}g}"


class DatasetStats:
    """Per-split dataset summary: subjects, mesh size, bounding boxes, displacement from the neutral.

    Args:
        dataset: the dataset to summarise (any registered dataset).
        split: the split by subject, as every built-in task's (ratios, seed; default the
            recipe's seed and 85:5:10).
        preprocess: the preprocessing fitted on the training neutrals (only its ``scale`` is
            reported: evaluation-space units per dataset unit).
        shapes: the shapes to summarise (default: every shape of the dataset; the neutral is
            always among them).
        neutral: the shape displacements are measured from.
    """

    name = "dataset-stats"

    def __init__(self, dataset: Annotated[Spec, Kind("dataset")] = "synthetic-heads",
                 split: SplitConfig | None = None, preprocess: PreprocessConfig | None = None,
                 shapes: list[str] | None = None, neutral: str = "neutral"):
        self.dataset = make_spec("dataset", dataset, "dataset")  # a name given from Python, too
        self.split = split or SplitConfig()
        self.preprocess = preprocess or PreprocessConfig()
        self.shapes, self.neutral = (list(shapes) if shapes else None), neutral

    def run(self, ctx) -> None:
        ctx.log(f"loading dataset {self.dataset.name}")
        col = ctx.build("dataset", self.dataset).load(ctx.cache)
        col.shape_index(self.neutral)  # a DataError naming the dataset's shapes
        shapes = [self.neutral, *(s for s in (self.shapes or col.shape_names) if s != self.neutral)]
        for s in shapes:
            col.shape_index(s)
        split, pre, _, _ = split_and_preprocess(col, self.split, self.preprocess, ctx.seed, ctx, self.neutral)
        index = {s: i for i, s in enumerate(col.subjects)}
        units = col.units
        ctx.log(f"{len(col.subjects)} subjects ({', '.join(f'{k} {len(v)}' for k, v in split.items())}), "
                f"{col.template.n_vertices} vertices, shapes {', '.join(shapes)}, units {units}")
        splits = {}
        for name in ctx.progress(SPLITS, desc="splits"):
            idx = np.array([index[s] for s in split[name]], dtype=np.int64)
            splits[name] = summarise(col, idx, shapes, self.neutral)
            e = splits[name]["extent"]
            ctx.log(f"{name}: {len(idx)} subject{'' if len(idx) == 1 else 's'}, {splits[name]['meshes']} meshes"
                    + (f", extent {' x '.join(_num(x) for x in e)} {units}" if e else ""))
        results = {
            "dataset": {"name": self.dataset.name, "n_vertices": col.template.n_vertices,
                        "n_faces": col.template.n_polygons, "n_triangles": len(col.template.triangles),
                        "units": units, "subjects": {k: len(v) for k, v in split.items()}, "shapes": shapes,
                        "neutral": self.neutral, "scale": float(pre.scale)},
            "splits": splits,
        }
        ctx.write_json("metrics.json", results)
        ctx.write_text("report.md", self.report(results))
        ctx.log(f"wrote {ctx.run_dir / 'metrics.json'} and {ctx.run_dir / 'report.md'}")

    @staticmethod
    def report(results: dict) -> str:
        """report.md: one table of the splits, one of the displacements per shape and split."""
        ds, splits = results["dataset"], results["splits"]
        u = ds["units"]
        rows = []
        for name, s in splits.items():
            ext, nex = s["extent"] or [None] * 3, s["neutral_extent_mean"] or [None] * 3
            rows.append([name, s["subjects"], s["meshes"], s["n_vertices"], s["n_faces"], s["n_triangles"],
                         " x ".join(_num(x) for x in ext), " x ".join(_num(x) for x in nex)])
        table = markdown_table(rows, ["split", "subjects", "meshes", "vertices", "faces", "triangles",
                                      "extent x y z", "neutral extent x y z (mean)"],
                               units={"extent x y z": u, "neutral extent x y z (mean)": u})
        drows = []
        for shape in ds["shapes"][1:]:
            for name, s in splits.items():
                d = s["displacement"][shape]
                drows.append([shape, name, d["subjects"], _num(d["mean"]), _num(d["max"])])
        parts = [f"# Dataset statistics: {ds['name']}", "",
                 f"{ds['n_vertices']} vertices, {ds['n_faces']} faces ({ds['n_triangles']} triangles), "
                 f"shapes {', '.join(ds['shapes'])}; every figure in the dataset's units ({u}), before "
                 f"preprocessing (whose scale, fitted on the training neutrals, is {ds['scale']:.6g} per {u}).",
                 "", "## Splits", "", table, ""]
        if drows:
            parts += ["## Displacement from the neutral", "",
                      "Per-vertex distance ||P_shape - P_neutral|| over the subjects that have both: the mean "
                      "over subjects and vertices, and the maximum.", "",
                      markdown_table(drows, ["shape", "split", "subjects", "mean", "max"],
                                     units={"mean": u, "max": u}), ""]
        return "\n".join(parts)


@hookimpl
def fwk_register_tasks():
    return [DatasetStats]
