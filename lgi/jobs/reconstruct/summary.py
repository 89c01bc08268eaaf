"""The reconstruct job's summary: counts, bundle statuses, residuals, noise and jaw range, and the lines
``lgi reconstruct`` prints."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.jobs.reconstruct.outputs import OUTPUTS
from lgi.jobs.reconstruct.shot import Shot


def summarise(res, shot: Shot, out: str | Path, seconds: dict[str, float]) -> dict[str, Any]:
    """The job's summary (JSON-friendly) of a whole result ``res``: :class:`ShotSummary` of one block."""
    tally = ShotSummary(shot.index.n_markers)
    tally.add(res)
    return tally.result(shot, out, seconds)


class ShotSummary:
    """The job's summary, gathered block by block (:meth:`add`) as a long take is written: counts, shares of
    bundle statuses, residuals, noise and jaw range (:meth:`result`), holding a few numbers per frame.

    Parameters
    ----------
    n_markers : int
        Rows per frame of the diagnostics.
    """

    def __init__(self, n_markers: int) -> None:
        self.n_markers = n_markers
        self.frames = 0
        self.rows = 0
        self.status: dict[str, int] = {}
        self.projections: list[np.ndarray] = []
        self.max_residual = -np.inf
        self.local_fits = 0
        self.far_rows = self.far_given = 0
        self.rays: list[np.ndarray] = []
        self.jaw_open = [np.inf, -np.inf]
        self.fit_rms: list[np.ndarray] = []
        self.noise = 0.0
        #: The frames a stopped run had written, gone on from (0: a run from the start)
        self.resumed_from = 0

    def add(self, res) -> None:
        """Count a block (a :class:`~lgi.solve.results.SequenceResult`)."""
        d = res.diagnostics
        st = d.status.to_numpy()
        names, counts = np.unique(st.astype(str), return_counts=True)
        for k, c in zip(names, counts, strict=True):
            self.status[k] = self.status.get(k, 0) + int(c)
        self.frames += len(res.frames)
        self.rows += len(st)
        self.projections.append(d.projection_mm.to_numpy()[st == "projected"])
        r = d.residual_mm.to_numpy(np.float64)
        if np.isfinite(r).any():
            self.max_residual = max(self.max_residual, float(np.nanmax(r)))
        self.local_fits += int((d.source == "local fit").sum())
        if "far_share" in d:
            share = d.far_share
            self.far_given += int(share.notna().sum())
            self.far_rows += int((share > 0.5).sum())
        if "constraint" in d:
            on = (d.constraint == "ray").to_numpy()
            if on.any():
                self.rays.append(d.ray_distance_mm.to_numpy()[on])
        self.noise = float(res.noise)
        if res.jaw is not None:
            self.jaw_open = [min(self.jaw_open[0], float(res.jaw[:, 0].min())),
                             max(self.jaw_open[1], float(res.jaw[:, 0].max()))]
            # The fit's RMS repeats on every row of its frame: one value per frame gives the rows' median. A copy:
            # a view would hold the block's whole table of numbers (9 kB per ICT frame).
            self.fit_rms.append(d.fit_rms_mm.to_numpy(np.float64).reshape(-1, self.n_markers)[:, 0].copy())

    def state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """What :meth:`restore` needs to go on counting (a run resumed after a stop): numbers, and arrays."""
        numbers = {"frames": self.frames, "rows": self.rows, "status": self.status,
                   "max_residual": None if not np.isfinite(self.max_residual) else self.max_residual,
                   "local_fits": self.local_fits, "far_rows": self.far_rows, "far_given": self.far_given,
                   "jaw_open": [None if not np.isfinite(v) else v for v in self.jaw_open], "noise": self.noise}
        join = lambda parts: np.concatenate(parts) if parts else np.zeros(0)  # noqa: E731
        return numbers, {"projections": join(self.projections), "rays": join(self.rays), "fit_rms": join(self.fit_rms)}

    def restore(self, numbers: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Counts as :meth:`state` gave them."""
        self.frames, self.rows = int(numbers["frames"]), int(numbers["rows"])
        self.status = {str(k): int(v) for k, v in numbers["status"].items()}
        self.max_residual = -np.inf if numbers["max_residual"] is None else float(numbers["max_residual"])
        self.local_fits, self.far_rows = int(numbers["local_fits"]), int(numbers["far_rows"])
        self.far_given = int(numbers["far_given"])
        lo, hi = numbers["jaw_open"]
        self.jaw_open = [np.inf if lo is None else float(lo), -np.inf if hi is None else float(hi)]
        self.noise = float(numbers["noise"])
        # An empty part adds nothing but its type to what is joined: left out, as the values' own type is kept.
        kept = lambda a: [np.asarray(a)] if np.size(a) else []  # noqa: E731
        self.projections, self.rays, self.fit_rms = (kept(arrays[k]) for k in ("projections", "rays", "fit_rms"))

    def result(self, shot: Shot, out: str | Path, seconds: dict[str, float]) -> dict[str, Any]:
        """The summary (JSON-friendly) of every block added."""
        n = max(self.rows, 1)

        def share(*names: str) -> float:
            return float(sum(self.status.get(k, 0) for k in names) / n)

        proj = np.concatenate(self.projections) if self.projections else np.zeros(0)
        est = shot.noise.estimate
        s: dict[str, Any] = {
            "out": str(Path(out).resolve()), "frames": self.frames, "markers": shot.index.n_markers,
            "vertices": shot.index.n_vertices,
            "contained_share": share("contained"), "projected_share": share("projected"),
            "neighbour_share": share("neighbour"), "fitted_share": share("fitted"),
            "missing_share": share("missing", "bridged"),
            "median_projection_mm": float(np.median(proj)) if proj.size else 0.0,
            "max_residual_mm": self.max_residual if np.isfinite(self.max_residual) else float("nan"),
            "local_fit_share": self.local_fits / n,
            "noise_mm": self.noise, "noise_estimated": est is not None,
            "noise_estimate_mm": None if est is None else float(est.noise_mm),
            "noise_estimate_axes_mm": None if est is None else [float(v) for v in est.axis_mm],
            "noise_coherence": None if est is None else float(est.coherence),
            "seconds": seconds, "outputs": [n for n in OUTPUTS if (Path(out) / n).exists()],
            "resumed_from_frame": self.resumed_from,
        }
        if self.far_given:
            # Bundle-frames whose weights gave way, far from the markers, to the frame's global fit (share over a
            # half).
            s["far_field_share"] = self.far_rows / n
        if self.rays:
            r = np.concatenate(self.rays)
            s["rays_used"] = int(r.size)
            s["ray_residual_max_mm"] = float(np.nanmax(r)) if np.isfinite(r).any() else float("nan")
        if self.fit_rms:
            rms = pd.Series(np.concatenate(self.fit_rms))
            s["jaw_open_deg"] = list(self.jaw_open)
            s["fit_rms_mm"] = {"median": float(rms.median()), "max": float(rms.max())}
        return s


def report_lines(s: dict[str, Any]) -> list[str]:
    """The summary as the lines ``lgi reconstruct`` prints (and the flow logs)."""
    sec = s["seconds"]
    lines = []
    if s.get("resumed_chunks"):
        k = s["resumed_chunks"]
        lines.append(f"resumed a stopped run of the same command: its {k['chosen']} chunks chosen and {k['finished']} "
                     f"finished (of {k['chunks']} a pass) are kept, the rest done now")
    if s.get("resumed_from_frame"):
        lines.append(f"resumed a stopped run of the same command: its {s['resumed_from_frame']} frames written are "
                     "kept, the rest solved now")
    if "solve" in sec:
        n = s["frames"] - s.get("resumed_from_frame", 0)
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
