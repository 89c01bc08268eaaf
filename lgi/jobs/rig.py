"""``lgi rig``: the jaw rig (hinge and skinning weights) fitted from a dataset's jaw shapes; the rebuild-dataset
flow's rig stage calls it with the same :class:`RigOptions`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.options import REQUIRED, declared, option
from lgi.units import MM_PER_CM


@declared
@dataclass(frozen=True)
class RigOptions:
    """Options of ``lgi rig`` (:mod:`lgi.options`)."""

    __pydantic_config__ = {"extra": "forbid"}  # as a flow parameter: a misspelt key is an error

    jaw_vertices: str = option(
        REQUIRED, "vertices moving rigidly with the jaw: an inclusive range, or an index file (JSON list, text, or "
        ".npy of integers)", metavar="FIRST:LAST|FILE")
    shapes: str = option(
        "jaw*", "the jaw shapes; the hinge is fitted from the openings among them (the jaw vertices rotate about the "
        "lateral x axis), the others only get their jaw parameters (default %(default)s)", metavar="PATTERN")

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
