"""The LGI index: everything built once per (dataset, marker layout) and reused for every frame.

Saved as a directory (see ``docs/indexing.md``)::

    manifest.json   format, source dataset hash, layout, options, counts
    build.json      build timings (the only file that differs between two builds of the same inputs)
    index.npz       flattened per-bundle clouds, simplices, grids, hull facets, natural-neighbour
                    weights, neighbours, bundle table, correction basis, neutral mesh
    deltas.npy      (S + 1, V, 3) float32 shape displacements, row 0 the neutral (zeros)
    pruning.csv     per bundle and shape: kept, dropped (barely moves the bundle) or merged, and motion
    bundles.csv     per bundle: points before/after, dimension, simplices by kind, natural neighbours
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import scipy.sparse as sp

from lgi.dataset.markers import MarkerLayout
from lgi.dataset.shapes import ShapeDataset
from lgi.errors import InputError
from lgi.index._grid_kernels import build_grids
from lgi.index.cloud import BundleCloud, CloudOptions, barycentric_inverse, build_cloud
from lgi.index.natural import natural_neighbour_weights
from lgi.index.smooth import SmoothInterpolator
from lgi.io.arrays import check_grouped, check_kind, check_mesh, check_offsets, check_range
from lgi.io.atomic import atomic_dir
from lgi.io.manifest import read_manifest
from lgi.io.npz import load_npy, load_npz, save_npz
from lgi.solve.jaw import JawRig, fit_shape_parameters, unskin_deltas

if TYPE_CHECKING:
    import scipy.sparse
from lgi.progress import progress
from lgi.units import MM_PER_CM

FORMAT = "lgi-index"
FORMAT_VERSION = 1
#: What an index directory holds (arrays, manifest, timings, CSV reports): a folder holding anything else is
#: not replaced by an index.
ENTRIES = ("manifest.json", "index.npz", "deltas.npy", "build.json", "*.csv")


@dataclass
class IndexOptions:
    """Build options: pruning and simplices (:class:`CloudOptions`), natural neighbours, search grid,
    alias classes (shapes of one cloud point that also lie within ``class_tol`` of each other at every
    natural neighbour share one misfit evaluation), correction stiffness."""

    cloud: CloudOptions = field(default_factory=CloudOptions)
    region_radius: float = 3.0
    nn_subdivisions: int = 3
    grid_target: float = 4.0
    grid_max_cells: int = 64
    class_tol: float = 1e-3
    ks: float = 1.0
    kb: float = 100.0

    def __post_init__(self) -> None:
        for name in ("region_radius", "grid_target", "class_tol", "ks", "kb"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.number)) or not np.isfinite(v) or v <= 0:
                flag = "--region-radius" if name == "region_radius" else name
                raise InputError(f"{flag} must be a positive number, not {v!r}")
        for name in ("nn_subdivisions", "grid_max_cells"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise InputError(f"{name} must be a whole number >= 1, not {v!r}")

    def to_json(self) -> dict:
        return {**{k: v for k, v in self.__dict__.items() if k != "cloud"}, "cloud": self.cloud.to_json()}

    @classmethod
    def from_json(cls, d: dict) -> IndexOptions:
        d = dict(d)
        cloud = d.pop("cloud", {})
        for what, given, known in (("index", d, cls.__dataclass_fields__), ("cloud", cloud,
                                                                            CloudOptions.__dataclass_fields__)):
            unknown = sorted(set(given) - set(known) - ({"cloud"} if what == "index" else set()))
            if unknown:
                raise InputError(f"unknown {what} options {unknown}; known: {sorted(set(known) - {'cloud'})}")
        return cls(cloud=CloudOptions(**cloud), **d)


def layout_hash(layout: MarkerLayout) -> str:
    h = hashlib.sha256()
    h.update(json.dumps(layout.names).encode())
    for a in (layout.triangles, layout.vertices, np.round(layout.weights, 12)):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


@dataclass
class LGIIndex:
    """A built index (arrays as described in the module docstring)."""

    manifest: dict[str, Any]
    arrays: dict[str, np.ndarray]
    deltas: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)

    # --------------------------------------------------------------- convenience views
    @property
    def marker_names(self) -> list[str]:
        return list(self.manifest["markers"])

    @property
    def shape_names(self) -> list[str]:
        """Extended shape names: index 0 is the neutral."""
        return ["neutral", *self.manifest["shapes"]]

    @property
    def n_markers(self) -> int:
        return len(self.manifest["markers"])

    @property
    def n_vertices(self) -> int:
        return int(self.arrays["neutral"].shape[0])

    def layout(self) -> MarkerLayout:
        a = self.arrays
        return MarkerLayout(self.marker_names, a["marker_triangle"], a["marker_vertices"], a["marker_weights"])

    def jaw_rig(self) -> JawRig | None:
        """The jaw rig the shapes were unskinned with, if any."""
        a = self.arrays
        return JawRig(a["jaw_pivot"], a["jaw_weights"]) if "jaw_pivot" in a else None

    def nn_weights(self) -> scipy.sparse.csr_matrix:
        a = self.arrays

        return sp.csr_matrix((a["w_data"], a["w_indices"], a["w_indptr"]), shape=(self.n_vertices, self.n_markers))

    # --------------------------------------------------------------- disk
    def save(self, directory: str | os.PathLike[str], reports: dict[str, pd.DataFrame] | None = None) -> Path:
        directory = Path(directory)
        with atomic_dir(directory, ENTRIES, "lgi index") as tmp:
            save_npz(tmp / "index.npz", **self.arrays)
            np.save(tmp / "deltas.npy", self.deltas)
            for name, df in (reports or {}).items():
                df.to_csv(tmp / name, index=False, float_format="%.6g")
            (tmp / "manifest.json").write_text(json.dumps(self.manifest, indent=1))
            # Everything above is a function of the inputs (byte-identical across builds); the timings
            # are not, so they live apart.
            (tmp / "build.json").write_text(json.dumps({"timings_s": self.timings}, indent=1))
        return directory

    @classmethod
    def load(cls, directory: str | os.PathLike[str], mmap: bool = True) -> LGIIndex:
        """Read an index directory; a damaged one (missing or inconsistent files, arrays of the wrong kind, shape
        or range) is refused with :class:`~lgi.errors.InputError` naming the file."""
        directory = Path(directory)
        mpath = directory / "manifest.json"
        manifest = read_manifest(directory, FORMAT, FORMAT_VERSION, "LGI index")
        missing = [k for k in ("markers", "shapes", "counts", "options") if k not in manifest]
        if missing:
            raise InputError(f"manifest lacks {missing} (a damaged index: rebuild it)", path=mpath)
        arrays = load_npz(directory / "index.npz", required=("neutral", "ptab", "marker_triangle", "w_indptr"))
        deltas = load_npy(directory / "deltas.npy", mmap)
        n_v = arrays["neutral"].shape[0]
        if deltas.ndim != 3 or deltas.shape[1:] != (n_v, 3) or len(deltas) != len(manifest["shapes"]) + 1:
            raise InputError(f"deltas.npy has shape {deltas.shape}; the index has {len(manifest['shapes'])} shapes "
                             f"and {n_v} vertices (a damaged index: rebuild it)", path=directory / "deltas.npy")
        if len(manifest["markers"]) != len(arrays["marker_triangle"]):
            raise InputError("manifest and index.npz disagree on the markers (a damaged index: rebuild it)",
                             path=directory)
        for name in ("neutral", "ptab"):
            if arrays[name].dtype.kind in "fiu" and not np.all(np.isfinite(arrays[name])):
                raise InputError(f"{name} holds non-finite values (built from a bad dataset?)",
                                 path=directory / "index.npz")
        check_structure(arrays, len(manifest["shapes"]) + 1, directory / "index.npz")
        build = directory / "build.json"
        try:
            timings = json.loads(build.read_text()).get("timings_s", {}) if build.is_file() else {}
        except (json.JSONDecodeError, AttributeError):
            timings = {}
        return cls(manifest, arrays, deltas, timings)


_INTS = ("dim", "pt_off", "pt_shape", "alias_off", "class_off", "alias_shape", "sx", "sx_off", "sx_kind", "hull",
         "hull_off", "grid_dims", "cell_off", "cell_start", "cell_items", "w_indptr", "w_indices", "nn_owner",
         "nb_off", "nb_idx", "corr_indptr", "corr_indices", "marker_triangle", "marker_vertices")
_FLOATS = ("origin", "basis", "pts", "tinv", "snap_radius", "grid_lo", "grid_h", "ptab", "w_data", "corr_data",
           "neutral", "marker_weights")


def check_structure(a: dict[str, np.ndarray], n_shapes: int, path: Path) -> None:
    """Refuse index arrays the compiled kernels would read out of bounds: kinds, shapes, offsets and the range
    of every index array (each marker's simplices, hull and grid cells pointing at its own points and
    simplices). ``n_shapes`` counts the neutral. Cost: a few passes over the arrays (milliseconds)."""
    check_kind(a, path, _INTS, _FLOATS)
    present = set(a)
    if "nn_distance" in present and (a["nn_distance"].dtype.kind != "f" or np.isnan(a["nn_distance"]).any()):
        # inf is a vertex no bundle's region reaches; NaN or another kind is damage
        raise InputError("nn_distance holds NaN or non-float values (a damaged index: rebuild it)", path=path)
    n_v = len(a["neutral"])
    m = len(a["marker_triangle"])
    if a["ptab"].shape != (n_shapes, m, 3):
        raise InputError(f"ptab has shape {a['ptab'].shape}, expected ({n_shapes}, {m}, 3) (a damaged index: "
                         "rebuild it)", path=path)
    check_offsets(a["w_indptr"], len(a.get("w_indices", [])), "w_indptr", path, n_v)
    if "w_indices" in present:
        check_range(a["w_indices"], 0, m, "w_indices", path)
    if {"face_vertices", "face_offsets"} <= present:
        check_mesh(a, n_v, path)
    if "marker_vertices" in present:
        check_range(a["marker_vertices"], 0, n_v, "marker_vertices", path)
    if "nn_owner" in present:
        check_range(a["nn_owner"], 0, m, "nn_owner", path, allow=-1)  # -1: no bundle's region
    if "pt_off" not in present:
        return
    n_p = len(a["pts"])
    check_offsets(a["pt_off"], n_p, "pt_off", path, m)
    check_range(a["pt_shape"], 0, n_shapes, "pt_shape", path)
    check_range(a["dim"], 0, 4, "dim", path)  # 0: every shape puts the bundle at one point
    per_marker = np.arange(m)
    k = len(a["sx"])
    check_offsets(a["sx_off"], k, "sx_off", path, m)
    check_grouped(a["sx"], np.repeat(per_marker, np.diff(a["sx_off"])), a["pt_off"], "sx", path, allow=-1)
    check_offsets(a["hull_off"], len(a["hull"]), "hull_off", path, m)
    check_grouped(a["hull"], np.repeat(per_marker, np.diff(a["hull_off"])), a["pt_off"], "hull", path, allow=-1)
    cells = np.prod(a["grid_dims"], axis=1)
    check_offsets(a["cell_off"], int(cells.sum()), "cell_off", path, m)
    if np.any(np.diff(a["cell_off"]) != cells):
        raise InputError("grid_dims and cell_off disagree (a damaged index: rebuild it)", path=path)
    check_offsets(a["cell_start"], len(a["cell_items"]), "cell_start", path, int(cells.sum()))
    cell_marker = np.repeat(per_marker, cells)
    check_grouped(a["cell_items"], np.repeat(cell_marker, np.diff(a["cell_start"])), a["sx_off"], "cell_items", path)
    check_offsets(a["alias_off"], len(a["class_off"]) - 1, "alias_off", path, n_p)
    check_offsets(a["class_off"], len(a["alias_shape"]), "class_off", path)
    check_range(a["alias_shape"], 0, n_shapes, "alias_shape", path)
    for off, idx, n in (("nb_off", "nb_idx", m), ("corr_indptr", "corr_indices", n_v)):
        if off in present:
            check_offsets(a[off], len(a[idx]), off, path, m)
            check_range(a[idx], 0, n, idx, path)
    shapes = {"tinv": (k, 3, 3), "sx_kind": (k,), "sx": (k, 4), "origin": (m, 3), "basis": (m, 3, 3),
              "snap_radius": (m,), "grid_lo": (m, 3), "grid_h": (m,), "grid_dims": (m, 3), "dim": (m,),
              "pts": (n_p, 3), "pt_shape": (n_p,)}
    for name, shape in shapes.items():
        if name in present and a[name].shape != shape:
            raise InputError(f"{name} has shape {a[name].shape}, expected {shape} (a damaged index: rebuild it)",
                             path=path)


def _alias_classes(aliases: np.ndarray, tab: np.ndarray, neighbours: np.ndarray, tol: float) -> list[list[int]]:
    """Group a point's shapes into classes that also coincide (within tol) at every natural neighbour:
    they score alike, so the solver evaluates one misfit per class. The representative stays first."""
    if len(aliases) == 1 or len(neighbours) == 0:
        return [aliases.tolist()]
    sig = tab[aliases][:, neighbours].reshape(len(aliases), -1)
    classes: list[list[int]] = []
    reps: list[int] = []
    for k, s in enumerate(aliases.tolist()):
        for ci, r in enumerate(reps):
            if np.max(np.abs(sig[k] - sig[r])) <= tol:
                classes[ci].append(s)
                break
        else:
            reps.append(k)
            classes.append([s])
    return classes


def _flatten(clouds: list[BundleCloud], tab: np.ndarray, neighbours: list[np.ndarray],
             tol: float) -> dict[str, np.ndarray]:
    m = len(clouds)
    dim = np.array([c.dim for c in clouds], np.int64)
    origin = np.stack([c.origin for c in clouds])
    basis = np.zeros((m, 3, 3))
    pts_l, shp_l, al_off, cl_off, al_l, sx_l, tinv_l, kind_l, hull_l = [], [], [0], [0], [], [], [], [], []
    pt_off = np.zeros(m + 1, np.int64)
    sx_off = np.zeros(m + 1, np.int64)
    hull_off = np.zeros(m + 1, np.int64)
    for i, c in enumerate(clouds):
        d = c.dim
        basis[i, :, :d] = c.basis
        n = len(c.points)
        p3 = np.zeros((n, 3))
        p3[:, :d] = c.points
        pts_l.append(p3)
        shp_l.append(c.point_shape)
        for a in c.aliases:
            for cls in _alias_classes(a, tab, neighbours[i], tol):
                al_l.append(np.asarray(cls))
                cl_off.append(cl_off[-1] + len(cls))
            al_off.append(len(cl_off) - 1)
        base = pt_off[i]
        s4 = np.full((len(c.simplices), 4), -1, np.int64)
        s4[:, : c.simplices.shape[1]] = c.simplices + base
        sx_l.append(s4)
        t3 = np.zeros((len(c.simplices), 3, 3))
        if d > 0:
            t3[:, :d, :d] = barycentric_inverse(c.points, c.simplices)
        tinv_l.append(t3)
        kind_l.append(c.kinds)
        h3 = np.full((len(c.hull), 3), -1, np.int64)
        h3[:, : c.hull.shape[1]] = c.hull + base
        hull_l.append(h3)
        pt_off[i + 1] = base + n
        sx_off[i + 1] = sx_off[i] + len(c.simplices)
        hull_off[i + 1] = hull_off[i] + len(c.hull)
    return {
        "dim": dim, "origin": origin, "basis": basis, "pts": np.concatenate(pts_l), "pt_off": pt_off,
        "pt_shape": np.concatenate(shp_l).astype(np.int64), "alias_off": np.asarray(al_off, np.int64),
        "class_off": np.asarray(cl_off, np.int64),
        "alias_shape": np.concatenate(al_l).astype(np.int64), "sx": np.concatenate(sx_l), "sx_off": sx_off,
        "tinv": np.concatenate(tinv_l), "sx_kind": np.concatenate(kind_l), "hull": np.concatenate(hull_l),
        "hull_off": hull_off, "snap_radius": np.array([c.report["snap_radius"] for c in clouds]),
    }


def build_index(dataset: ShapeDataset, layout: MarkerLayout, options: IndexOptions | None = None,
                show_progress: bool = True, jaw_rig: JawRig | None = None) -> tuple[LGIIndex, dict[str, pd.DataFrame]]:
    """Build the index of a dataset for a marker layout.

    Parameters
    ----------
    dataset
        Shapes (S of them) on the neutral; V vertices.
    layout
        M markers on the neutral (checked against the dataset's triangles).
    options
        See :class:`IndexOptions`.
    jaw_rig
        With a rig, every shape's jaw parameters are fitted and the shapes are stored unskinned; the
        solver then unskins each frame's bundles, indexes them and skins the result (paper section 6).

    Returns
    -------
    index : LGIIndex
    reports : dict of DataFrame
        ``pruning.csv`` (per bundle and shape) and ``bundles.csv`` (per bundle), saved with the index.
    """
    opts = options or IndexOptions()
    t0 = time.perf_counter()
    natural = natural_stage(dataset, layout, opts)
    t1 = time.perf_counter()
    clouds, reports = clouds_stage(dataset, layout, opts, natural, jaw_rig, show_progress)
    t2 = time.perf_counter()
    index = assemble_index(dataset, layout, opts, natural, clouds, jaw_rig)
    index.timings.update(natural_stage_s=t1 - t0, clouds_stage_s=t2 - t1, assemble_s=time.perf_counter() - t2,
                         total_s=time.perf_counter() - t0)
    return index, reports


#: The options the natural-neighbour stage reads (and its cache key holds).
NATURAL_FIELDS = ("region_radius", "nn_subdivisions", "ks", "kb")


def natural_stage(dataset: ShapeDataset, layout: MarkerLayout, opts: IndexOptions) -> dict[str, np.ndarray]:
    """Natural-neighbour weights, natural neighbours and the residual-correction basis.

    Depends only on the neutral mesh, the layout and the options :data:`NATURAL_FIELDS` (not on the shapes),
    so a pruning or simplex change never recomputes it. It sees only those options: reading another would
    fail here rather than leave the cached stage keyed without it.
    """
    opts = SimpleNamespace(**{k: getattr(opts, k) for k in NATURAL_FIELDS})
    # Build-time modules (scipy.sparse, csgraph, spatial): imported here so that loading an index does not.

    layout.check_mesh(dataset.triangles)
    nn = natural_neighbour_weights(dataset.neutral, dataset.face_vertices, dataset.face_offsets, dataset.uvs,
                                   dataset.face_uvs, layout.triangles, layout.weights, opts.region_radius,
                                   opts.nn_subdivisions)
    nb_off = np.zeros(len(layout) + 1, np.int64)
    nb_off[1:] = np.cumsum([len(n) for n in nn.neighbours])
    nb_idx = np.concatenate(nn.neighbours).astype(np.int64) if nb_off[-1] else np.zeros(0, np.int64)
    smooth = SmoothInterpolator(dataset.neutral, dataset.triangles, layout.vertices, layout.weights, opts.ks,
                                opts.kb)
    # Each bundle's field decays away from it (all other bundles are held at zero): keep it sparse,
    # one row per bundle. Entries below 1e-3 of the unit residual are dropped; the solver applies the
    # correction again to what that leaves, which shrinks geometrically.
    basis = smooth.basis().T
    basis[np.abs(basis) < 1e-3] = 0.0
    correction = sp.csr_matrix(basis)
    w = nn.weights.tocsr()
    w.sort_indices()
    return {
        "w_indptr": w.indptr.astype(np.int64), "w_indices": w.indices.astype(np.int64),
        "w_data": w.data.astype(np.float64), "nn_distance": nn.distance, "nn_owner": nn.owner,
        "nn_region": nn.region, "nb_off": nb_off, "nb_idx": nb_idx,
        "corr_indptr": correction.indptr.astype(np.int64), "corr_indices": correction.indices.astype(np.int64),
        "corr_data": correction.data, "uv_scale": np.array(nn.uv_scale),
        "nn_conflicts": np.array(json.dumps(nn.conflicts)),
    }


def clouds_stage(dataset: ShapeDataset, layout: MarkerLayout, opts: IndexOptions, natural: dict[str, np.ndarray],
                 jaw_rig: JawRig | None = None, show_progress: bool = False
                 ) -> tuple[dict[str, np.ndarray], dict[str, pd.DataFrame]]:
    """Point clouds (pruned), overlapping simplices and search grids of every bundle.

    Returns the flattened arrays (with the bundle table ``ptab`` and, with a rig, ``jaw_shape_params``)
    and the reports ``pruning.csv`` and ``bundles.csv``.
    """
    layout.check_mesh(dataset.triangles)
    deltas = np.asarray(dataset.deltas, np.float32)
    extra: dict[str, np.ndarray] = {}
    if jaw_rig is not None:
        if jaw_rig.weights.shape != (dataset.n_vertices,):
            raise InputError(f"jaw rig has {jaw_rig.weights.shape[0]} weights, the dataset {dataset.n_vertices} "
                             "vertices")
        jaw_params = fit_shape_parameters(jaw_rig, dataset.neutral, deltas)
        deltas = unskin_deltas(jaw_rig, dataset.neutral, deltas, jaw_params)
        extra["jaw_shape_params"] = jaw_params
    # Bundle table: every bundle's position on the neutral (row 0) and on every shape.
    tab = np.empty((dataset.n_shapes + 1, len(layout), 3))
    tab[0] = layout.evaluate(dataset.neutral)
    tab[1:] = tab[0][None] + layout.evaluate(deltas).astype(np.float64)
    rng = np.random.default_rng(opts.cloud.seed)
    clouds = [build_cloud(tab[:, i], opts.cloud, rng)
              for i in progress(range(len(layout)), "point clouds", disable=not show_progress)]
    nb_off, nb_idx = natural["nb_off"], natural["nb_idx"]
    neighbours = [nb_idx[nb_off[i]:nb_off[i + 1]] for i in range(len(layout))]
    flat = _flatten(clouds, tab, neighbours, opts.class_tol)
    lo, h, dims, cell_off, cell_start, items = build_grids(
        flat["pts"], flat["pt_off"], flat["sx"], flat["sx_off"], flat["dim"], float(opts.grid_target),
        opts.grid_max_cells)
    arrays = {**flat, "grid_lo": lo, "grid_h": h, "grid_dims": dims, "cell_off": cell_off, "cell_start": cell_start,
              "cell_items": items, "ptab": tab.astype(np.float64), **extra}
    return arrays, _reports(dataset, layout, clouds, tab, neighbours)


def _reports(dataset: ShapeDataset, layout: MarkerLayout, clouds: list[BundleCloud], tab: np.ndarray,
             neighbours: list[np.ndarray]) -> dict[str, pd.DataFrame]:
    rows = []
    for i, c in enumerate(clouds):
        motion = np.linalg.norm(tab[1:, i] - tab[0, i], axis=1)
        rep_of = {}
        dropped = set(c.aliases[0].tolist())
        for a in c.aliases:
            for s in a.tolist():
                rep_of[s] = int(a[0])
        for k in range(dataset.n_shapes):
            r = rep_of.get(k + 1, k + 1)
            if k + 1 in dropped:
                status = "dropped: barely moves this bundle (alias of the neutral point)"
            elif r != k + 1:
                status = f"merged into {dataset.names[r - 1]}"
            else:
                status = "kept"
            rows.append((layout.names[i], dataset.names[k], status, motion[k] * MM_PER_CM))
    pruning = pd.DataFrame(rows, columns=["marker", "shape", "status", "motion_mm"])
    per_bundle = pd.DataFrame({
        "marker": layout.names,
        "points_before": [dataset.n_shapes + 1] * len(layout),
        "points_after": [c.report["points"] for c in clouds],
        "dropped_static": [c.report["dropped_static"] for c in clouds],
        "merged_duplicates": [c.report["merged_duplicates"] for c in clouds],
        "dim": [c.dim for c in clouds],
        "simplices": [c.report["simplices"] for c in clouds],
        "delaunay": [c.report["by_kind"][0] for c in clouds],
        "subset_delaunay": [c.report["by_kind"][1] for c in clouds],
        "knn_fans": [c.report["by_kind"][2] for c in clouds],
        "filtered": [c.report["filtered"] for c in clouds],
        "natural_neighbours": [len(n) for n in neighbours],
    })
    return {"pruning.csv": pruning, "bundles.csv": per_bundle}


def assemble_index(dataset: ShapeDataset, layout: MarkerLayout, opts: IndexOptions, natural: dict[str, np.ndarray],
                   clouds: dict[str, np.ndarray], jaw_rig: JawRig | None = None) -> LGIIndex:
    """The index from the outputs of :func:`natural_stage` and :func:`clouds_stage`."""
    deltas = np.asarray(dataset.deltas, np.float32)
    if jaw_rig is not None:
        deltas = unskin_deltas(jaw_rig, dataset.neutral, deltas, clouds["jaw_shape_params"])
    # Shape-major: neighbouring vertices blending the same shapes read neighbouring memory.
    ext = np.zeros((dataset.n_shapes + 1, dataset.n_vertices, 3), np.float32)
    ext[1:] = deltas
    arrays = {
        **{k: v for k, v in clouds.items() if k != "jaw_shape_params"},
        **{k: v for k, v in natural.items() if k not in ("uv_scale", "nn_conflicts")},
        "neutral": dataset.neutral, "face_vertices": dataset.face_vertices, "face_offsets": dataset.face_offsets,
        "marker_triangle": layout.triangles, "marker_vertices": layout.vertices, "marker_weights": layout.weights,
    }
    if jaw_rig is not None:
        arrays["jaw_pivot"] = jaw_rig.pivot
        arrays["jaw_weights"] = jaw_rig.weights
        arrays["jaw_shape_params"] = clouds["jaw_shape_params"]
    if dataset.uvs is not None:
        arrays["uvs"] = dataset.uvs
        arrays["face_uvs"] = dataset.face_uvs
    manifest = {
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "dataset_hash": dataset.content_hash(), "layout_hash": layout_hash(layout),
        "dataset_info": {"name": dataset.info.get("name"), "units": dataset.units},
        "markers": layout.names, "shapes": dataset.names, "units": dataset.units,
        "options": opts.to_json(),
        "counts": {
            "vertices": dataset.n_vertices, "shapes": dataset.n_shapes, "markers": len(layout),
            "points": int(len(clouds["pts"])), "simplices": int(len(clouds["sx"])),
            "grid_entries": int(len(clouds["cell_items"])), "nn_region_vertices": int(natural["nn_region"].sum()),
        },
        "nn_conflicts": json.loads(str(natural["nn_conflicts"])), "uv_scale_cm": float(natural["uv_scale"]),
        "jaw": jaw_rig is not None,
    }
    return LGIIndex(manifest, arrays, ext)
