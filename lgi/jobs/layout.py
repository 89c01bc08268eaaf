"""The layout jobs: design a marker layout by integer programming, and compare layouts on held-out shapes.

``lgi layout design`` and ``lgi layout evaluate`` call :func:`design` and :func:`evaluate` with the options objects
here. The program itself is :mod:`lgi.dataset.layout_milp`; what it optimises and why is in
``docs/layout_design.md``.

Regions (``--exclude`` for where paint cannot go, and the region errors are measured over) are given as a
comma-separated list of:

* ``auto``: the dataset's own: the synthetic actor (``info.name == "synthetic-actor"``): the eyes, the inner lips
  and the border strip the shipped layout also avoids (``scripts/make_layouts.py``); ICT FaceKit's topology
  (26,719 vertices): everything outside the narrow face area (vertices 0-6705), skin facing sideways (normal z <
  0.3, the cameras cannot see it), and the rims of the eyes and of the inner lips (face vertices within 4.5 and 3 mm
  of the eye and mouth sockets); any other mesh: vertices within 5 mm of an open edge (the holes of the eyes and the
  mouth, and the outline);
* ``none``: nothing;
* ``FIRST:LAST``: a range of vertex indices (0-based, inclusive);
* ``boundary:MM``: vertices within MM of an open mesh edge;
* a file of vertex indices (JSON list, text, or ``.npy``; as ``--rigid-vertices`` reads).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.dataset.markers import MarkerLayout, read_layout, write_layout
from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
from lgi.dataset.shapes import ShapeDataset, _match
from lgi.errors import InputError
from lgi.io.atomic import atomic_file, check_output, files_in
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: ICT FaceKit's vertex count and ranges (ABOUT.md of the data folder; see lgi.evaluation.benchsets).
ICT_N_VERTICES = 26719
ICT_FACE, ICT_NARROW_FACE = 9409, 6706
ICT_MOUTH_SOCKET, ICT_EYE_SOCKETS = (11248, 13294), (13294, 14062)
SYNTHETIC_NAME = "synthetic-actor"


# ---------------------------------------------------------------------------------------------- regions
def _is_ict(ds) -> bool:
    return ds.n_vertices == ICT_N_VERTICES


def _is_synthetic(ds) -> bool:
    return ds.info.get("name") == SYNTHETIC_NAME


def boundary_vertices(triangles: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) bool: vertices on an open edge (an edge of exactly one triangle)."""
    t = np.asarray(triangles, np.int64)
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, count = np.unique(e, axis=0, return_counts=True)
    out = np.zeros(n_vertices, bool)
    out[uniq[count == 1].ravel()] = True
    return out


def _near(points: np.ndarray, seeds: np.ndarray, radius: float) -> np.ndarray:
    """(V,) bool: points within ``radius`` of any seed point."""
    from scipy.spatial import cKDTree

    if len(seeds) == 0:
        return np.zeros(len(points), bool)
    d, _ = cKDTree(seeds).query(points, distance_upper_bound=radius)
    return np.isfinite(d)


def auto_exclusion(ds) -> tuple[np.ndarray, str]:
    """(V,) bool vertices no marker may go on for this dataset, and what they are (see the module docstring)."""
    x0 = ds.neutral
    if _is_synthetic(ds):
        from lgi.synthetic import actor as synth

        x, y = x0[:, 0], x0[:, 1]
        eye_d = np.min([np.hypot(x - ex, (y - ey) * 1.4) for ex, ey in synth.EYE_CENTERS], axis=0)
        ok = ((np.abs(x) < 7.0) & (np.abs(y) < 9.5) & (eye_d > 1.3)
              & ~((np.abs(y - synth.MOUTH_Y) < 0.25) & (np.abs(x) < synth.MOUTH_HALF_WIDTH + 0.2)))
        return ~ok, "synthetic actor: eyes, inner lips, border strip"
    if _is_ict(ds):
        from lgi.dataset.mesh import vertex_normals

        n = vertex_normals(x0, ds.triangles)
        face = np.zeros(len(x0), bool)
        face[:ICT_NARROW_FACE] = True
        eyes = _near(x0, x0[ICT_EYE_SOCKETS[0]:ICT_EYE_SOCKETS[1]], 0.45)
        lips = _near(x0, x0[ICT_MOUTH_SOCKET[0]:ICT_MOUTH_SOCKET[1]], 0.3)
        ok = face & (n[:, 2] > 0.3) & ~eyes & ~lips
        return ~ok, "ICT: outside the narrow face area, facing sideways, eye and inner-lip rims"
    return _near(x0, x0[boundary_vertices(ds.triangles, ds.n_vertices)], 0.5), "within 5 mm of an open edge"


def measured_region(ds) -> tuple[np.ndarray, str]:
    """(V,) bool vertices the layout is designed to reconstruct and errors are measured over.

    The synthetic actor: ``|x| <= 7.5`` and ``|y| <= 10`` cm (its border strip is the side of the head, where no
    marker may go and every layout extrapolates); ICT: the face area (vertices 0-9408, as the accuracy
    benchmark); any other mesh: every vertex.
    """
    x0 = ds.neutral
    if _is_synthetic(ds):
        return (np.abs(x0[:, 0]) <= 7.5) & (np.abs(x0[:, 1]) <= 10.0), "synthetic actor: |x| <= 7.5, |y| <= 10 cm"
    if _is_ict(ds):
        m = np.zeros(len(x0), bool)
        m[:ICT_FACE] = True
        return m, "ICT face area (vertices 0-9408)"
    return np.ones(len(x0), bool), "every vertex"


def region_mask(ds, spec: str, what: str = "--exclude") -> tuple[np.ndarray, str]:
    """(V,) bool for a region spec (module docstring), and a description."""
    nv = ds.n_vertices
    mask = np.zeros(nv, bool)
    said = []
    items = [s.strip() for s in str(spec).split(",") if s.strip()]
    if not items:
        raise InputError(f"{what} is empty: give auto, none, FIRST:LAST, boundary:MM or a vertex index file")
    for item in items:
        if item == "none":
            said.append("none")
        elif item == "auto":
            m, text = auto_exclusion(ds)
            mask |= m
            said.append(text)
        elif item.startswith("boundary:"):
            try:
                mm = float(item.split(":", 1)[1])
            except ValueError:
                raise InputError(f"{what} {item!r}: boundary:MM takes a distance in mm") from None
            if not math.isfinite(mm) or mm < 0:
                raise InputError(f"{what} {item!r}: the distance must be a finite number of mm >= 0")
            mask |= _near(ds.neutral, ds.neutral[boundary_vertices(ds.triangles, nv)], mm / MM_PER_CM)
            said.append(f"within {mm:g} mm of an open edge")
        elif ":" in item and not Path(item).exists():
            try:
                lo, hi = (int(v) for v in item.split(":"))
            except ValueError:
                raise InputError(f"{what} {item!r}: not auto, none, FIRST:LAST, boundary:MM or an existing "
                                 "vertex index file") from None
            if lo < 0 or hi >= nv or hi < lo:
                raise InputError(f"{what} {item}: out of range for {nv} vertices")
            mask[lo:hi + 1] = True
            said.append(f"vertices {lo}-{hi}")
        else:
            if not Path(item).exists():
                raise InputError(f"{what} {item!r}: not auto, none, FIRST:LAST, boundary:MM or an existing vertex "
                                 "index file", path=item)
            from lgi.dataset.importing import load_vertex_indices

            idx = load_vertex_indices(item, nv)
            mask[idx] = True
            said.append(f"{len(idx)} vertices from {item}")
    return mask, "; ".join(said)


def held_out_names(names: list[str], pattern: str | None) -> list[str]:
    """Shape names held out by ``pattern``: shell patterns (comma-separated), ``every5`` (every fifth shape in the
    dataset's order from the third: 20 % of the shapes, spread over the dataset whatever its naming), ``auto`` or
    ``none``/None.

    ``auto``: when every one of the accuracy benchmark's held-out ICT shapes
    (:data:`lgi.evaluation.accuracy.ICT_HELD_OUT`: mouthFunnel, mouthSmile_L, browInnerUp_R, cheekPuff_R,
    noseSneer_L, jawLeft) is in the dataset, those (``every5`` would hold out ICT's ``mouthClose``, a corrective
    meant only with ``jawOpen`` that no other shape resembles, whose error then is most of the total); otherwise
    ``every5``.
    """
    from lgi.evaluation.accuracy import ICT_HELD_OUT

    p = "" if pattern is None else pattern.strip()
    if p in ("", "none"):
        return []
    if p == "auto" and set(ICT_HELD_OUT) <= set(names):
        return [n for n in names if n in ICT_HELD_OUT]
    if p in ("auto", "every5"):
        return [n for i, n in enumerate(names) if i % 5 == 2]
    return [n for n in names if _match(n, p, False)]


# ---------------------------------------------------------------------------------------------- design
def _positive(name: str, v: Any, allow_zero: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0 or (
            v == 0 and not allow_zero):
        raise InputError(f"--{name.replace('_', '-')} must be a finite number {'>=' if allow_zero else '>'} 0, "
                         f"not {v!r}")


@dataclass(frozen=True)
class DesignOptions:
    """Options of ``lgi layout design``.

    ``count`` markers at least ``min_spacing`` mm apart, in mirror pairs with ``symmetric``, nowhere in
    ``exclude`` (region spec, module docstring), designed for the dataset's shapes minus ``held_out`` (patterns,
    as ``lgi layout evaluate --held-out``; default none: a layout meant for evaluation is designed without the
    shapes it is evaluated on). ``epsilon``: Zell's relative-displacement threshold of the per-shape cover (0: off);
    ``time_limit``: seconds for the solver.
    """

    count: int
    min_spacing: float = 8.0
    symmetric: bool = False
    exclude: str = "auto"
    held_out: str | None = None
    epsilon: float = 0.5
    time_limit: float = 60.0

    def __post_init__(self) -> None:
        if isinstance(self.count, bool) or not isinstance(self.count, (int, np.integer)) or self.count < 1:
            raise InputError(f"--count must be a whole number >= 1, not {self.count!r}")
        _positive("min_spacing", self.min_spacing, allow_zero=True)
        _positive("time_limit", self.time_limit)
        if isinstance(self.epsilon, bool) or not isinstance(self.epsilon, (int, float)) or not 0 <= self.epsilon <= 1:
            raise InputError(f"--epsilon must be a number in [0, 1], not {self.epsilon!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _marker_names(x0: np.ndarray, chosen: np.ndarray, partner: np.ndarray, plane: float) -> list[str]:
    """Names in reading order (top to bottom, then the actor's left to right): ``m000``...; in a symmetric layout
    a pair shares its number (``p07_L``, ``p07_R``; ``L`` is +x, the actor's left) and midline markers are
    ``c03``."""
    p = x0[chosen]
    order = np.lexsort((-p[:, 0], -np.round(p[:, 1] / 0.5)))
    names = [""] * len(chosen)
    if partner.size == 0 or (partner < 0).all():
        for k, i in enumerate(order):
            names[i] = f"m{k:03d}"
        return names
    n_pair = n_mid = 0
    for i in order:
        if names[i]:
            continue
        j = int(partner[i])
        if j == i:
            n_mid += 1
            names[i] = f"c{n_mid:02d}"
        else:
            n_pair += 1
            left, right = (i, j) if p[i, 0] >= p[j, 0] else (j, i)
            names[left], names[right] = f"p{n_pair:02d}_L", f"p{n_pair:02d}_R"
    return names


def design_dataset(ds, options: DesignOptions, time_limit: float | None = None):
    """Design a layout for a loaded dataset: ``(layout, result, excluded description, held-out names)``
    (:class:`~lgi.dataset.layout_milp.DesignResult`); no files."""
    from lgi.dataset import layout_milp as LM
    o = options
    held = held_out_names(ds.names, o.held_out)
    train = ds.select(exclude=",".join(held)) if held else ds
    if train.n_shapes == 0:
        raise InputError("every shape is held out: nothing to design the layout for")
    excluded, said = region_mask(ds, o.exclude)
    region, _ = measured_region(ds)
    problem = LM.DesignProblem(ds.neutral, train.deltas, ~excluded, region, list(train.names))
    res = LM.design_layout_milp(problem, ds.triangles, LM.DesignOptions(
        count=int(o.count), min_spacing=o.min_spacing / MM_PER_CM, symmetric=o.symmetric, epsilon=o.epsilon,
        time_limit=o.time_limit if time_limit is None else time_limit))
    names = _marker_names(ds.neutral, res.vertices, res.partner, res.info["plane"])
    layout = vertex_layout(names, res.vertices, ds.triangles)
    mid = np.flatnonzero(res.partner == np.arange(len(res.vertices)))
    if mid.size:
        # A midline marker's vertex may lie off the plane (no vertex on it): move the marker to the nearest point of
        # the surface on the plane (where an edge crosses it), so that the layout is exactly symmetric.
        from scipy.spatial import cKDTree

        t = np.asarray(ds.triangles, np.int64)
        x0, c = ds.neutral, res.info["plane"]
        corner = np.stack([np.repeat(np.arange(len(t)), 3), np.tile([0, 1, 2], len(t)), np.tile([1, 2, 0], len(t))], 1)
        xa, xb = x0[t[corner[:, 0], corner[:, 1]], 0] - c, x0[t[corner[:, 0], corner[:, 2]], 0] - c
        cross = (xa * xb <= 0) & (xa != xb)
        corner, xa, xb = corner[cross], xa[cross], xb[cross]
        u = xa / (xa - xb)  # where along the edge x = c
        pa, pb = x0[t[corner[:, 0], corner[:, 1]]], x0[t[corner[:, 0], corner[:, 2]]]
        pts = (1 - u)[:, None] * pa + u[:, None] * pb
        pts[:, 0] = c
        _, k = cKDTree(pts).query(x0[res.vertices[mid]])
        w = np.zeros((mid.size, 3))
        w[np.arange(mid.size), corner[k, 1]] = 1 - u[k]
        w[np.arange(mid.size), corner[k, 2]] += u[k]
        layout.triangles[mid], layout.vertices[mid], layout.weights[mid] = corner[k, 0], t[corner[k, 0]], w
    return layout, res, said, held


def vertex_layout(names: list[str], vertices: np.ndarray, triangles: np.ndarray):
    """A :class:`~lgi.dataset.markers.MarkerLayout` with each marker on a vertex (a triangle incident to it, weight 1
    at that corner). Not by closest point: where the mesh has coincident vertices (the synthetic actor's lip slit)
    that could attach a marker to the other side's vertex."""
    t = np.asarray(triangles, np.int64)
    tri_of = np.full(int(t.max()) + 1, -1, np.int64)
    tri_of[t.ravel()] = np.repeat(np.arange(len(t)), 3)
    ti = tri_of[np.asarray(vertices, np.int64)]
    w = (t[ti] == np.asarray(vertices)[:, None]).astype(np.float64)
    return MarkerLayout(list(names), ti, t[ti], w)


def design(dataset_dir: str | Path, out: str | Path, options: DesignOptions) -> dict[str, Any]:
    """``lgi layout design``: write the designed layout (markers CSV, as :func:`~lgi.dataset.markers.write_layout`,
    with neutral positions) to ``out``; returns a summary (:func:`design_report`)."""
    given = [i.strip() for i in str(options.exclude).split(",") if i.strip() and Path(i.strip()).exists()]
    check_output(out, "file", inputs=[dataset_dir, *files_in(dataset_dir, DATASET_ENTRIES), *given])
    t0 = time.perf_counter()
    ds = ShapeDataset.load(dataset_dir)
    layout, res, said, held = design_dataset(ds, options)
    if res.info["status"] != 0:
        # The time limit stopped HiGHS: the layout is the best found, not proven best within the gap asked for.
        log.warning("the solver stopped before proving the layout (%s; gap %.2f %%): raise --time-limit for a "
                    "better one", res.info["message"], 100 * res.info["gap"])
    if res.info["uncovered_shapes"]:
        log.warning("no allowed candidate moves >= epsilon of the largest motion in %d shapes (%s): they have no "
                    "representative marker", len(res.info["uncovered_shapes"]),
                    ", ".join(res.info["uncovered_shapes"][:5]))
    write_layout(out, layout, neutral=ds.neutral)
    p = layout.evaluate(ds.neutral)
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return {"path": str(Path(out).resolve()), "count": len(layout), "excluded": said, "held_out": held,
            "shapes": ds.n_shapes - len(held), "min_distance_mm": float(d.min() * MM_PER_CM) if len(p) > 1 else None,
            "symmetric": options.symmetric, "seconds": time.perf_counter() - t0, **res.info}


def design_report(s: dict[str, Any]) -> list[str]:
    gap = f", gap {s['gap']:.2%}" if s["status"] != 0 or s["gap"] > 0 else ""
    lines = [f"{s['count']} markers designed for {s['shapes']} shapes"
             + (f" ({len(s['held_out'])} held out: {', '.join(s['held_out'])})" if s["held_out"] else "")
             + (f", in mirror pairs about x = {s['plane']:.3f}" if s["symmetric"] else ""),
             f"excluded: {s['excluded']}",
             f"program: {s['candidates']} candidates, {s['targets']} covered vertices x {len(s['levels'])} levels, "
             f"{s['variables']} variables, {s['constraints']} constraints ({s['conflicts']} spacing conflicts)",
             f"HiGHS: {s['message']} in {s['solve_s']:.2f} s{gap} (setup {s['setup_s']:.2f} s)",
             f"closest markers {s['min_distance_mm']:.1f} mm apart" if s["min_distance_mm"] is not None else ""]
    lines.append(f"markers: {s['path']}")
    return [line for line in lines if line]


# ---------------------------------------------------------------------------------------------- evaluate
@dataclass(frozen=True)
class EvaluateOptions:
    """Options of ``lgi layout evaluate``: the ``held_out`` shapes (patterns, ``auto`` or ``none``; see
    :func:`held_out_names`) and an optional ``out`` CSV of the per-shape errors."""

    held_out: str = "auto"
    out: str | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _stats(err_mm: np.ndarray) -> dict[str, float]:
    return {"rms_mm": float(np.sqrt(np.mean(err_mm**2))), "p95_mm": float(np.percentile(err_mm, 95)),
            "max_mm": float(err_mm.max())}


def heldout_errors(ds, layout, held: list[str], region: np.ndarray, index_options=None,
                   methods: tuple[str, ...] = ("lgi", "blendshape")) -> pd.DataFrame:
    """Held-out errors of a layout: the index built on ``ds`` minus ``held``, each held-out shape reconstructed from
    its own bundles.

    Parameters
    ----------
    ds : ShapeDataset
    layout : MarkerLayout
    held : list of str
        Held-out shape names (at least one).
    region : (V,) bool
        Vertices measured.
    methods
        ``lgi`` (default solver options, every frame an independent pose) and/or ``blendshape``
        (:class:`~lgi.evaluation.baselines.BlendshapeSolver` on the same training shapes and markers).

    Returns
    -------
    DataFrame
        One row per method and shape, and a row per method with shape ``ALL`` (over every held-out vertex error):
        ``method, shape, rms_mm, p95_mm, max_mm``.
    """
    from lgi.evaluation.baselines import BlendshapeSolver
    from lgi.index.build import build_index
    from lgi.solve.solver import LGISolver

    train = ds.select(exclude=",".join(held))
    test = ds.take([ds.index(n) for n in held])
    truth = ds.neutral[None] + np.asarray(test.deltas, np.float64)  # (F, V, 3) cm
    bundles = layout.evaluate(truth)
    rows = []
    for method in methods:
        if method == "lgi":
            index, _ = build_index(train, layout, index_options, show_progress=False)
            solver = LGISolver(index)
        else:
            solver = BlendshapeSolver(train, layout)
        rec = np.stack([np.asarray(solver.solve_frame(b).vertices, np.float64) for b in bundles])
        err = np.linalg.norm(rec[:, region] - truth[:, region], axis=2) * MM_PER_CM  # (F, R) mm
        rows += [{"method": method, "shape": n, **_stats(e)} for n, e in zip(held, err, strict=True)]
        rows.append({"method": method, "shape": "ALL", **_stats(err.ravel())})
    return pd.DataFrame(rows)


def evaluate(dataset_dir: str | Path, markers: str | Path, options: EvaluateOptions | None = None
             ) -> tuple[pd.DataFrame, dict[str, Any]]:
    """``lgi layout evaluate``: the per-shape table (:func:`heldout_errors`) and a summary; writes the table to
    ``options.out`` when given."""
    o = options or EvaluateOptions()
    if o.out:
        check_output(o.out, "file", inputs=[dataset_dir, markers, *files_in(dataset_dir, DATASET_ENTRIES)])
    t0 = time.perf_counter()
    ds = ShapeDataset.load(dataset_dir)
    layout = read_layout(markers, ds.triangles)
    held = held_out_names(ds.names, o.held_out)
    if not held:
        raise InputError(f"--held-out {o.held_out!r} matches no shape of the dataset ({ds.n_shapes} shapes, e.g. "
                         f"{', '.join(ds.names[:3])})", path=dataset_dir)
    if len(held) == ds.n_shapes:
        raise InputError(f"--held-out {o.held_out!r} holds out every shape: nothing is left to build the index from",
                         path=dataset_dir)
    region, said = measured_region(ds)
    table = heldout_errors(ds, layout, held, region)
    if o.out:
        with atomic_file(o.out) as tmp:
            table.to_csv(tmp, index=False, float_format="%.6g")
    allrow = table[table["shape"] == "ALL"].set_index("method")
    return table, {"markers": len(layout), "held_out": held, "train_shapes": ds.n_shapes - len(held),
                   "region": said, "region_vertices": int(region.sum()), "out": o.out,
                   "all": allrow.to_dict(orient="index"), "seconds": time.perf_counter() - t0}


def evaluate_report(table: pd.DataFrame, s: dict[str, Any]) -> list[str]:
    wide = table.pivot(index="shape", columns="method", values="rms_mm")
    order = [n for n in s["held_out"]] + ["ALL"]
    wide = wide.reindex(order)
    lines = [f"{s['markers']} markers; index of {s['train_shapes']} shapes; {len(s['held_out'])} held-out shapes "
             f"reconstructed from their own bundles; errors over {s['region']} ({s['region_vertices']} vertices), mm",
             "held-out RMS per shape (mm):",
             wide.to_string(float_format=lambda v: f"{v:.4f}"),
             "", "method       RMS      p95      max  (mm, every held-out vertex)"]
    for m, r in s["all"].items():
        lines.append(f"{m:<10} {r['rms_mm']:8.4f} {r['p95_mm']:8.4f} {r['max_mm']:8.3f}")
    if s["out"]:
        lines.append(f"table: {Path(s['out']).resolve()}")
    return lines
