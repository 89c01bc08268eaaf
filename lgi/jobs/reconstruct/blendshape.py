"""``lgi reconstruct --method blendshape``: the rigged bounded blendshape fit as a reconstruction.

The baseline the benchmarks compare LGI with (:class:`lgi.evaluation.baselines.RiggedBlendshapeSolver`: the jaw
and the index's shape weights fitted together per frame, then the blend skinned), written as the reconstruct job
writes LGI's (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv`` and the asked extras), so that a review page
can show LGI against it (``lgi review --compare``).

The fit meets no bundle exactly: there is no correction, so a bundle's residual before and after are the same,
each seen bundle's status is ``fitted`` and each hidden one's ``missing``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import fields
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd

from lgi.capture.bundles import read_bundles
from lgi.errors import InputError
from lgi.jobs.reconstruct.outputs import OUTPUTS, check_outputs, write_reconstruction
from lgi.jobs.reconstruct.summary import report_lines
from lgi.progress import progress
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: Options of LGI's own solve: the blendshape fit has no use for them, and says so when they are set.
LGI_ONLY = ("noise", "smooth", "jaw_smooth", "temporal_weight", "spatial_weight", "far_field")


def check_options(options) -> None:
    """Refuse the reconstruct options that have no meaning for the blendshape fit (they shape LGI's solve)."""
    o = options
    unused = [flag for flag, on in (("--jaw FILE", o.jaw not in ("auto", "none")), ("--max-gap", o.max_gap > 0),
                                    ("--bilateral", bool(o.bilateral)), ("--observations", bool(o.observations)),
                                    ("--contours", bool(o.contours))) if on]
    if unused:
        raise InputError(f"--method blendshape fits the bundles as given: {', '.join(unused)} do not apply to it")
    defaults = {f.name: f.default for f in fields(type(o))}
    ignored = [f"--{n.replace('_', '-')}" for n in LGI_ONLY if n in defaults and getattr(o, n) != defaults[n]]
    if ignored:
        log.warning("--method blendshape: %s shape LGI's solve and are ignored by the blendshape fit",
                    ", ".join(ignored))


def fit_shot(index, positions: np.ndarray, show_progress: bool = False):
    """The rigged blendshape fit of every frame.

    Parameters
    ----------
    index : LGIIndex
    positions : (F, M, 3) float, cm
        Bundles in layout order (NaN rows: missing).

    Returns
    -------
    vertices : (F, V, 3) float32, cm
    fits : list of GlobalFitResult
        Per frame: weights, jaw (with a rig), residuals (cm), RMS.
    """
    from lgi.evaluation.baselines import RiggedBlendshapeSolver

    solver = RiggedBlendshapeSolver(index)
    prev, verts, fits = None, [], []
    for p in progress(positions, "blendshape fit", not show_progress):
        prev = solver.solve_frame(p, prev)
        verts.append(prev.vertices)
        fits.append(prev.fit)
    return np.stack(verts), fits


def diagnostics(frames: np.ndarray, markers: list[str], positions: np.ndarray, fits: list, rigged: bool
                ) -> pd.DataFrame:
    """Per frame and marker: status (fitted / missing), residual (mm; before = after: no correction), the
    frame's fit RMS (mm) and jaw, in the reconstruct job's column names."""
    n_f, n_m = len(frames), len(markers)
    seen = np.all(np.isfinite(positions), axis=2)
    resid = np.stack([f.residual for f in fits]) * MM_PER_CM
    resid = np.where(seen, resid, np.nan)
    d = {"frame": np.repeat(frames, n_m), "marker": np.tile(markers, n_f),
         "status": np.where(seen, "fitted", "missing").ravel(), "residual_before_mm": resid.ravel(),
         "residual_mm": resid.ravel(), "source": "blendshape fit",
         "fit_residual_mm": resid.ravel(), "fit_rms_mm": np.repeat([f.rms * MM_PER_CM for f in fits], n_m)}
    if rigged:
        jaw = np.stack([f.jaw for f in fits])
        for k, name in enumerate(("jaw_open_deg", "jaw_yaw_deg", "jaw_roll_deg", "jaw_forward_cm")):
            d[name] = np.repeat(jaw[:, k], n_m)
        d["jaw_source"] = np.repeat([f.jaw_source for f in fits], n_m)
    d["constraint"] = np.where(seen, "bundle", "none").ravel()
    return pd.DataFrame(d)


def reconstruct_blendshape(index_dir: str | Path, bundles: str | Path, out: str | Path, options,
                           show_progress: bool = False) -> dict[str, Any]:
    """Reconstruct a shot with the rigged blendshape fit and write it as :func:`lgi.jobs.reconstruct.reconstruct`
    does; returns the summary (:func:`lgi.jobs.reconstruct.report_lines` formats it)."""
    from lgi.index.build import LGIIndex

    check_options(options)
    check_outputs(out, (index_dir, bundles))
    t0 = time.perf_counter()
    index = LGIIndex.load(index_dir)
    b = read_bundles(bundles, index.marker_names)
    t1 = time.perf_counter()
    verts, fits = fit_shot(index, b.positions, show_progress)
    rigged = index.jaw_rig() is not None
    d = diagnostics(np.asarray(b.frames), index.marker_names, b.positions, fits, rigged)
    jaw = np.stack([f.jaw for f in fits]) if rigged else None
    res = SimpleNamespace(vertices=verts, frames=np.asarray(b.frames), diagnostics=d, jaw=jaw)
    t2 = time.perf_counter()
    write_reconstruction(out, res, index.arrays, options)
    st = d.status.to_numpy()
    r = d.residual_mm.to_numpy()
    s: dict[str, Any] = {
        "out": str(Path(out).resolve()), "frames": len(b.frames), "markers": index.n_markers,
        "vertices": index.n_vertices, "method": "blendshape", "contained_share": 0.0, "projected_share": 0.0,
        "neighbour_share": 0.0, "fitted_share": float((st == "fitted").mean()),
        "missing_share": float((st == "missing").mean()), "median_projection_mm": 0.0,
        "max_residual_mm": float(np.nanmax(r)) if np.isfinite(r).any() else float("nan"), "local_fit_share": 0.0,
        "noise_mm": 0.0, "noise_estimated": False, "noise_estimate_mm": None, "noise_estimate_axes_mm": None,
        "noise_coherence": None,
        "seconds": {"load": t1 - t0, "solve": t2 - t1, "write": time.perf_counter() - t2},
        "outputs": [n for n in OUTPUTS if (Path(out) / n).exists()],
    }
    if rigged:
        s["jaw_open_deg"] = [float(jaw[:, 0].min()), float(jaw[:, 0].max())]
        s["fit_rms_mm"] = {"median": float(d.fit_rms_mm.median()), "max": float(d.fit_rms_mm.max())}
    return s


def blendshape_report(s: dict[str, Any]) -> list[str]:
    """The lines ``lgi reconstruct --method blendshape`` prints."""
    sec = s["seconds"]
    lines = [f"reconstructed {s['frames']} frames x {s['vertices']} vertices with the rigged blendshape fit in "
             f"{sec['solve']:.2f} s (index loaded in {sec['load']:.2f} s)",
             f"bundles: {s['fitted_share'] * 100:.1f} % fitted, {s['missing_share'] * 100:.1f} % missing; no "
             f"correction: max bundle residual {s['max_residual_mm']:.3f} mm"]

    # The jaw's range and where the outputs are, as LGI's report says them.
    lines += [line for line in report_lines(s) if line.startswith(("jaw:", "outputs in"))]
    return lines
