"""The index jobs: fit a jaw rig, build an index, verify it (paper 7.1).

``lgi rig`` / ``lgi build`` / ``lgi verify`` and the rebuild-dataset flow's stages call these functions with
the same options objects (:class:`~lgi.index.build.IndexOptions` for the build).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.errors import InputError
from lgi.units import MM_PER_CM


# ---------------------------------------------------------------------------------------------- build
def build(dataset_dir: str | Path, markers: str | Path, out: str | Path, options=None,
          jaw_rig: str | Path | None = None, show_progress: bool = False) -> dict[str, Any]:
    """``lgi build``: the index of a dataset for a marker layout (options: :class:`~lgi.index.build.IndexOptions`)
    saved to ``out``; returns a summary (:func:`build_report`)."""
    from lgi.dataset.markers import read_layout
    from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
    from lgi.dataset.shapes import ShapeDataset
    from lgi.index.build import ENTRIES, build_index
    from lgi.io.atomic import check_output, files_in

    check_output(out, "dir", inputs=[dataset_dir, markers, jaw_rig, *files_in(dataset_dir, DATASET_ENTRIES)],
                 owned=ENTRIES, what="lgi index")
    t0 = time.perf_counter()
    ds = ShapeDataset.load(dataset_dir)
    layout = read_layout(markers, ds.triangles)
    rig = None
    if jaw_rig:
        from lgi.solve.jaw import JawRig

        rig = JawRig.load(jaw_rig, ds.n_vertices)
    index, reports = build_index(ds, layout, options, show_progress=show_progress, jaw_rig=rig)
    index.save(out, reports)
    per = reports["bundles.csv"]
    return {"path": str(Path(out).resolve()), "counts": index.manifest["counts"], "seconds": time.perf_counter() - t0,
            "points_before": int(per.points_before.iloc[0]), "points_after_median": float(per.points_after.median()),
            "points_after_min": int(per.points_after.min()), "points_after_max": int(per.points_after.max()),
            "simplices_median": float(per.simplices.median()), "warnings": list(index.manifest["nn_conflicts"])}


def build_report(s: dict[str, Any]) -> list[str]:
    c = s["counts"]
    return [f"index of {c['shapes']} shapes x {c['markers']} markers built in {s['seconds']:.1f} s",
            f"points per bundle: {s['points_before']} before, {s['points_after_median']:.0f} median after pruning "
            f"({s['points_after_min']}-{s['points_after_max']}); simplices: {c['simplices']} "
            f"({s['simplices_median']:.0f} median per bundle)",
            *(f"warning: {msg}" for msg in s["warnings"]),
            f"index: {s['path']}  (reports: bundles.csv, pruning.csv)"]


# --------------------------------------------------------------------------------------------- verify
@dataclass(frozen=True)
class VerifyOptions:
    """Options of ``lgi verify``: RMS ``tolerance`` (mm) over the marked region, the ``shapes`` to check (shell
    patterns; None: all), the solver's ``spatial_weight`` (mm)."""

    tolerance: float = 0.01
    shapes: str | None = None
    spatial_weight: float = 1e-3

    def __post_init__(self) -> None:
        for name in ("tolerance", "spatial_weight"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise InputError(f"--{name.replace('_', '-')} must be a finite number of mm >= 0, not {v!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def verify(index_dir: str | Path, options: VerifyOptions | None = None,
           show_progress: bool = False) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Every selected dataset shape reconstructed from its own bundles: the per-shape table
    (:func:`lgi.evaluation.verify.verify_index`) and a summary whose ``passed`` is the verdict."""
    from lgi.evaluation.verify import verify_index
    from lgi.index.build import LGIIndex
    from lgi.solve.solver import LGISolver

    o = options or VerifyOptions()
    index = LGIIndex.load(index_dir)
    table = verify_index(index, LGISolver(index, spatial_weight=o.spatial_weight), o.shapes,
                         show_progress=show_progress)
    if len(table) == 0:
        raise InputError(f"no shape matches {o.shapes!r}", path=index_dir)
    # A non-finite error fails the check (NaN > tolerance is false, so compare the other way round).
    bad = ~(table.rms_mm <= o.tolerance)
    unseen = table[(table.rms_all_mm > o.tolerance) & ~bad]
    k = int(np.nan_to_num(table.rms_mm.to_numpy(float), nan=np.inf).argmax())  # a NaN is the worst
    summary = {"shapes": len(table), "worst_rms_mm": float(table.rms_mm.max()),
               "worst_shape": str(table["shape"].iloc[k]),
               "worst_max_mm": float(table.max_mm.max()), "worst_rms_all_mm": float(table.rms_all_mm.max()),
               "max_residual_mm": float(table.residual_mm.max()), "tolerance_mm": o.tolerance,
               "failed": int(bad.sum()), "passed": bool(not bad.any()),
               "region_vertices": int(index.arrays["nn_region"].sum()),
               "unseen_outside_region": unseen["shape"].tolist(),
               "non_finite": table["shape"][~np.isfinite(table.rms_mm)].tolist()}
    return table, summary


def verify_report(table: pd.DataFrame, s: dict[str, Any]) -> list[str]:
    lines = [table.to_string(index=False, float_format=lambda v: f"{v:.5f}"),
             f"{s['shapes']} shapes, marked region ({s['region_vertices']} vertices): worst RMS "
             f"{s['worst_rms_mm']:.5f} mm ({s['worst_shape']}), worst max {s['worst_max_mm']:.4f} mm; whole mesh: "
             f"worst RMS {s['worst_rms_all_mm']:.5f} mm; largest bundle residual {s['max_residual_mm']:.2e} mm"]
    if s["unseen_outside_region"]:
        lines.append(f"{len(s['unseen_outside_region'])} shapes move vertices outside the marked region that no marker "
                     f"sees (whole-mesh RMS above tolerance), e.g. {', '.join(s['unseen_outside_region'][:3])}")
    if s["non_finite"]:
        lines.append(f"non-finite errors for {len(s['non_finite'])} shapes (e.g. {', '.join(s['non_finite'][:3])}): "
                     "the index holds non-finite values")
    verdict = f"FAILED for {s['failed']}" if not s["passed"] else "passed"
    lines.append(f"tolerance {s['tolerance_mm']} mm RMS over the marked region: {verdict}")
    return lines


# ------------------------------------------------------------------------------------------------ rig
@dataclass(frozen=True)
class RigOptions:
    """Options of ``lgi rig``: ``jaw_vertices`` (``FIRST:LAST`` inclusive, or an index file) moving rigidly
    with the jaw, and ``shapes``, the shell pattern of the jaw shapes."""

    __pydantic_config__ = {"extra": "forbid"}  # as a flow parameter: a misspelt key is an error

    jaw_vertices: str
    shapes: str = "jaw*"

    def vertex_indices(self, n_vertices: int) -> np.ndarray:
        """(J,) int64 jaw vertices, checked against the mesh."""
        spec = self.jaw_vertices
        if ":" in spec and not Path(spec).exists():
            try:
                lo, hi = (int(v) for v in spec.split(":"))
            except ValueError:
                raise InputError(f"--jaw-vertices takes FIRST:LAST or a file, got {spec!r}") from None
            if lo < 0 or hi >= n_vertices or hi < lo:
                raise InputError(f"--jaw-vertices {spec}: out of range for {n_vertices} vertices")
            jv = np.arange(lo, hi + 1)
        else:
            from lgi.dataset.importing import load_vertex_indices

            jv = load_vertex_indices(spec, n_vertices)
        if len(np.unique(jv)) < 3:
            raise InputError(f"--jaw-vertices {spec}: {len(np.unique(jv))} vertices; a rigid jaw motion needs at "
                             "least 3 (the lower teeth, typically hundreds)")
        return jv


def fit_jaw_rig(dataset_dir: str | Path, out: str | Path, options: RigOptions) -> dict[str, Any]:
    """``lgi rig``: fit the jaw hinge and skinning weights and save the rig npz; returns a summary
    (:func:`rig_report`)."""
    import logging

    from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
    from lgi.dataset.shapes import ShapeDataset
    from lgi.io.atomic import check_output, files_in
    from lgi.solve.jaw import PARAM_NAMES, fit_rig

    check_output(out, "file", inputs=[dataset_dir, *files_in(dataset_dir, DATASET_ENTRIES)])
    ds = ShapeDataset.load(dataset_dir)
    jv = options.vertex_indices(ds.n_vertices)
    sel = ds.select(include=options.shapes)
    if sel.n_shapes == 0:
        raise InputError(f"no shape matches {options.shapes!r}", path=dataset_dir)
    # fit_rig logs its warnings; they are in the report, so keep Python's last-resort handler from printing them
    # a second time (handlers an application set up still get them).
    jaw_log = logging.getLogger("lgi.solve.jaw")
    quiet = logging.NullHandler()
    jaw_log.addHandler(quiet)
    jaw_log.propagate = False
    try:
        rig, params = fit_rig(ds.neutral, sel.deltas, jv, ds.triangles, names=sel.names)
    finally:
        jaw_log.removeHandler(quiet)
        jaw_log.propagate = True
    if not np.all(np.isfinite(rig.pivot)) or not np.all(np.isfinite(params)):
        raise InputError("the jaw rig fit gave non-finite values: check --jaw-vertices and the jaw shapes",
                         path=dataset_dir)
    rep = rig.fit_report
    rig.save(out)
    shapes = []
    for name, th in zip(sel.names, params, strict=True):
        fit = rig.skin(ds.neutral, th) - ds.neutral
        err = np.linalg.norm(fit - sel.deltas[sel.index(name)], axis=1)[rig.weights > 0.5]
        shapes.append({"shape": name, **{n: float(v) for n, v in zip(PARAM_NAMES, th, strict=True)},
                       "skin_rms_mm": float(np.sqrt(np.mean(err**2)) * MM_PER_CM)})
    return {"path": str(Path(out).resolve()), "n_shapes": sel.n_shapes, "jaw_vertices": len(jv), "units": ds.units,
            "pivot": [float(v) for v in rig.pivot], "weighted_vertices": int((rig.weights > 0.5).sum()),
            "joint_slides": bool(rep.joint_slides), "used": list(rep.used), "widest": rep.widest,
            "centroid": [float(v) for v in rep.centroid],
            "openings": {n: {"deg": float(rep.angles_deg[n]), "slide_mm": float(rep.slides[n] * MM_PER_CM),
                             "residual_mm": float(rep.residual_rms[n] * MM_PER_CM)} for n in rep.used},
            "skipped": dict(rep.skipped), "shapes": shapes, "warnings": list(rep.warnings)}


def rig_report(s: dict[str, Any]) -> list[str]:
    from lgi.solve.jaw import PARAM_NAMES

    used = s["used"]
    plural = "s" if len(used) > 1 else ""
    how = "pivot and slides solved jointly" if s["joint_slides"] else f"pivot as the rotation{plural}' fixed point"
    pivot = np.asarray(s["pivot"])
    lines = [f"jaw rig from {s['n_shapes']} shapes and {s['jaw_vertices']} jaw vertices: pivot "
             f"{np.round(pivot, 3).tolist()} {s['units']}; {s['weighted_vertices']} vertices with weight > 0.5",
             f"hinge from {len(used)} opening shape{plural}: {', '.join(used)} ({how}); weights from {s['widest']}",
             f"  pivot ({', '.join(f'{v * MM_PER_CM:.2f}' for v in pivot)}) mm, "
             f"{np.linalg.norm(pivot - np.asarray(s['centroid'])) * MM_PER_CM:.1f} mm from the jaw vertices' centroid"]
    for name, o in s["openings"].items():
        lines.append(f"  opening {name}: {o['deg']:.2f} deg, slide {o['slide_mm']:.2f} mm, hinge residual "
                     f"{o['residual_mm']:.3f} mm RMS")
    lines += [f"  skipped {name}: {why}" for name, why in s["skipped"].items()]
    for row in s["shapes"]:
        vals = ", ".join(f"{n} {row[n]:.3g}" for n in PARAM_NAMES)
        lines.append(f"  {row['shape']}: {vals}; skinning reproduces it to {row['skin_rms_mm']:.2f} mm RMS on the jaw")
    lines += [f"warning: {msg}" for msg in s["warnings"]]
    lines.append(f"rig: {s['path']}")
    return lines
