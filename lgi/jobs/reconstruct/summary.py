"""The reconstruct job's summary: counts, bundle statuses, residuals, noise and jaw range, and the lines
``lgi reconstruct`` prints."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from lgi.jobs.reconstruct.outputs import OUTPUTS
from lgi.jobs.reconstruct.shot import Shot


def summarise(res, shot: Shot, out: str | Path, seconds: dict[str, float]) -> dict[str, Any]:
    """The job's summary (JSON-friendly): counts, shares of bundle statuses, residuals, noise, jaw range."""
    d = res.diagnostics
    st = d.status.to_numpy()
    proj = d.projection_mm.to_numpy()[st == "projected"]
    est = shot.solver.noise_estimate
    s: dict[str, Any] = {
        "out": str(Path(out).resolve()), "frames": len(res.frames), "markers": shot.index.n_markers,
        "vertices": shot.index.n_vertices,
        "contained_share": float((st == "contained").mean()), "projected_share": float((st == "projected").mean()),
        "neighbour_share": float((st == "neighbour").mean()), "fitted_share": float((st == "fitted").mean()),
        "missing_share": float(np.isin(st, ["missing", "bridged"]).mean()),
        "median_projection_mm": float(np.median(proj)) if proj.size else 0.0,
        "max_residual_mm": float(np.nanmax(d.residual_mm)) if np.isfinite(d.residual_mm).any() else float("nan"),
        "local_fit_share": float((d.source == "local fit").mean()),
        "noise_mm": float(res.noise), "noise_estimated": est is not None,
        "noise_estimate_mm": None if est is None else float(est.noise_mm),
        "noise_estimate_axes_mm": None if est is None else [float(v) for v in est.axis_mm],
        "noise_coherence": None if est is None else float(est.coherence),
        "seconds": seconds, "outputs": [n for n in OUTPUTS if (Path(out) / n).exists()],
    }
    if "far_share" in d and d.far_share.notna().any():
        # Bundle-frames whose weights gave way, far from the markers, to the frame's global fit (share over a half).
        s["far_field_share"] = float((d.far_share > 0.5).mean())
    if "constraint" in d and (d.constraint == "ray").any():
        r = d.ray_distance_mm.to_numpy()[(d.constraint == "ray").to_numpy()]
        s["rays_used"] = int(r.size)
        s["ray_residual_max_mm"] = float(np.nanmax(r)) if np.isfinite(r).any() else float("nan")
    if res.jaw is not None:
        s["jaw_open_deg"] = [float(res.jaw[:, 0].min()), float(res.jaw[:, 0].max())]
        s["fit_rms_mm"] = {"median": float(d.fit_rms_mm.median()), "max": float(d.fit_rms_mm.max())}
    return s


def report_lines(s: dict[str, Any]) -> list[str]:
    """The summary as the lines ``lgi reconstruct`` prints (and the flow logs)."""
    sec = s["seconds"]
    lines = []
    if "solve" in sec:
        n = s["frames"]
        lines.append(f"reconstructed {n} frames x {s['vertices']} vertices in {sec['solve']:.2f} s "
                     f"({n / max(sec['solve'], 1e-9):.0f} frames/s; index loaded in {sec['load']:.2f} s)")
    else:
        lines.append(f"reconstructed {s['frames']} frames x {s['vertices']} vertices through the reconstruct-shot "
                     "flow")
    if s["fitted_share"] > 0:
        what = ("fitted as measurements (noisy: no simplex searched)" if s["noise_mm"] > 0 else
                "met by the global fit with their natural neighbours (exact: no simplex searched)")
        lines.append(f"bundles: {s['fitted_share'] * 100:.1f} % {what}")
    lines.append(f"bundles: {s['contained_share'] * 100:.1f} % contained, {s['projected_share'] * 100:.1f} % projected "
                 f"(median distance {s['median_projection_mm']:.3f} mm), {s['missing_share'] * 100:.1f} % missing; "
                 f"max bundle residual {s['max_residual_mm']:.2e} mm")
    if not s["noise_estimated"]:
        how = "given"
    elif math.isfinite(s["noise_estimate_mm"]):
        how = f"estimated {s['noise_estimate_mm']:.3f} mm, neighbour correlation {s['noise_coherence']:.2f}"
    else:
        how = "not estimated: no marker is seen for 7 frames in a row; give --noise MM if they are not exact"
    mode = (f"measurements with {s['noise_mm']:.3f} mm noise (fitted, not interpolated)" if s["noise_mm"] > 0
            else "exact (the surface passes through every seen bundle)")
    lines.append(f"bundles treated as {mode} ({how}); local fits for {s['local_fit_share'] * 100:.1f} % of "
                 "bundle-frames")
    if "far_field_share" in s:
        lines.append(f"far field: {s['far_field_share'] * 100:.1f} % of bundle-frames gave way to the global fit "
                     "far from the markers (--far-field; their weights extrapolated worse; far_share in the "
                     "diagnostics)")
    if "rays_used" in s:
        lines.append(f"markers seen by one camera: {s['rays_used']} put on their viewing rays (the surface meets them "
                     f"within {s['ray_residual_max_mm']:.2e} mm)")
    if "jaw_open_deg" in s:
        lo, hi = s["jaw_open_deg"]
        lines.append(f"jaw: opening {lo:.1f} to {hi:.1f} deg; global fit residual median "
                     f"{s['fit_rms_mm']['median']:.3f} mm, max {s['fit_rms_mm']['max']:.3f} mm (per frame RMS)")
    lines.append(f"outputs in {s['out']}: {', '.join(n + ('/' if n == 'obj' else '') for n in s['outputs'])}")
    return lines
