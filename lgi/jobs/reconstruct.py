"""The reconstruct job: a shot's bundles to meshes, diagnostics and optional OBJ/USD/plot outputs.

One implementation, three schedules:

- :func:`reconstruct` runs the whole shot in this process (``lgi reconstruct``);
- the reconstruct-shot flow runs the same stages as tasks: :func:`choose_chunk` over consecutive chunks
  of frames, each starting from the last choice of the chunk before (so the choice is the one a single
  pass makes), :func:`finish_chunk` over chunks in parallel (a frame's surface depends only on the
  choices in its smoothing windows), then :func:`assemble` writes the outputs;
- both write through :func:`write_reconstruction`.

Results do not depend on the schedule: any chunk size, task runner or ``--flow`` gives the same files
(tested).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.errors import InputError
from lgi.jobs import options_from_dict
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: Every entry a reconstruction writes into its output directory (see :func:`lgi.io.atomic.job_outputs`).
OUTPUTS = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "per_frame.png", "shot.usdc", "obj",
           "bundles_constrained.parquet")
#: What the output folders hold (anything else there is someone else's: the run refuses to replace it).
OUTPUT_CONTENTS = {"obj": ("frame_*.obj", "*.mtl")}


@dataclass(frozen=True)
class ReconstructOptions:
    """Options of the reconstruct job (the ``lgi reconstruct`` flags; see its ``--help``).

    Attributes
    ----------
    temporal_weight : float, mm
        Preference for the previous frame's shapes (0 = none).
    spatial_weight : float, mm
        Tie-break toward the shapes the neighbours agree on (0 = none).
    smooth : int
        Moving average of each bundle's shape weights over this many frames (1 = none).
    jaw_smooth : int or None
        Moving average of the jaw parameters (None: ``smooth``).
    noise : float (mm) or "auto"
        Bundle noise per coordinate; 0 = exact bundles.
    method : "local", "simplex" or "blendshape"
        Where a bundle's weights come from: refitted over its natural neighbours ("local"), or the paper's
        choice among the containing simplices only ("simplex"); "blendshape": no LGI, the rigged bounded
        blendshape fit of the benchmarks' baseline (:mod:`lgi.jobs.blendshape`).
    jaw : "auto", "none" or a CSV path
        With a rigged index: estimate the jaw per frame, or read it (frame, open_deg, yaw_deg, roll_deg,
        forward_cm); "none" needs an index without a rig.
    max_gap : int
        Bridge missing runs of up to this many frames (0 = off).
    bilateral : str or None
        ``SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM]``: bilateral filter of the bundles before solving.
    obj : bool
        Also write one OBJ mesh per frame, ``obj/frame_NNNNN.obj``.
    usd : bool
        Also write the animated mesh as ``shot.usdc`` (``fps`` time codes per second).
    plot : bool
        Also write ``per_frame.png``: per frame, the largest distance to the bundles before the correction and
        the bundles projected, missing or bridged.
    fps : float
        USD time codes per second.
    chunk_size : int
        Frames per task when the job runs as a flow (scheduling only: results do not depend on it).
    observations : str or None
        The tracks table of ``lgi track`` (Parquet): a marker seen by one camera where the shot has no bundle
        is put on its viewing ray, at the depth a first reconstruction without it gives, and the shot is
        reconstructed again through it (:mod:`lgi.capture.observations`).
    calib : str or None
        Stereo calibration for ``observations`` (default: the rig stored in the tracks table).
    contours : str or None
        Lip contours traced per frame and camera (CSV ``frame, camera, curve, point, x, y``, px): the lip
        region is deformed so that the mesh's inner lip edges meet them (:mod:`lgi.solve.contours`); needs
        ``observations`` (its head poses and rig).
    far_field : str
        ``START:END`` in mm of distance from the nearest marker (over the skin, UV-geodesic): beyond START
        a bundle whose weights predict the markers beyond its neighbourhood clearly worse than the frame's
        global fit gives way to that fit, wholly so beyond END; "off": the bundles' weights everywhere.
    """

    temporal_weight: float = 0.02
    spatial_weight: float = 1e-3
    smooth: int = 1
    jaw_smooth: int | None = None
    noise: float | str = "auto"
    method: str = "local"
    jaw: str = "auto"
    max_gap: int = 0
    bilateral: str | None = None
    obj: bool = False
    usd: bool = False
    plot: bool = False
    fps: float = 30.0
    chunk_size: int = 60
    observations: str | None = None
    calib: str | None = None
    contours: str | None = None
    far_field: str = "5:15"

    def __post_init__(self) -> None:
        def bad(flag: str, why: str) -> InputError:
            return InputError(f"--{flag.replace('_', '-')} {why}")

        for name in ("temporal_weight", "spatial_weight"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise bad(name, f"must be a finite number of mm >= 0, not {v!r}")
        # Upper bounds: a smoothing window past 1001 frames (33 s at 30 fps) is not smoothing any more.
        for name, least, most in (("smooth", 1, 1001), ("jaw_smooth", 1, 1001), ("max_gap", 0, 1_000_000),
                                  ("chunk_size", 1, 1_000_000)):
            v = getattr(self, name)
            if v is None and name == "jaw_smooth":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not least <= v <= most:
                raise bad(name, f"must be a whole number in [{least}, {most}], not {v!r}")
        if self.noise != "auto":
            try:
                value = float(self.noise)
            except (TypeError, ValueError):
                raise bad("noise", f"takes a number of mm or 'auto', not {self.noise!r}") from None
            if not math.isfinite(value) or value < 0:
                raise bad("noise", f"must be a finite number of mm >= 0, not {self.noise!r}")
        if self.method not in ("local", "simplex", "blendshape"):
            raise bad("method", f"takes 'local', 'simplex' or 'blendshape', not {self.method!r}")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise bad("fps", f"must be a positive number, not {self.fps!r}")
        if self.calib and not self.observations:
            raise bad("calib", "turns the observations of --observations into rays: give the tracks table too")
        if self.contours and not self.observations:
            raise bad("contours", "are seen through the head pose and cameras of the tracks table: give "
                                  "--observations too")
        self.bilateral_sigmas()
        self.far_field_cm()

    def bilateral_sigmas(self) -> tuple[float, float, float | None] | None:
        """(sigma_frames, sigma_cm, sigma_space_cm or None) of ``bilateral``, or None."""
        if not self.bilateral:
            return None
        try:
            vals = [float(v) for v in str(self.bilateral).split(":")]
            if len(vals) not in (2, 3) or not all(math.isfinite(v) and v > 0 for v in vals):
                raise ValueError
        except ValueError:
            raise InputError("--bilateral takes SIGMA_FRAMES:SIGMA_MM[:SIGMA_SPACE_MM], positive numbers, "
                             f"got {self.bilateral!r}") from None
        return vals[0], vals[1] / MM_PER_CM, vals[2] / MM_PER_CM if len(vals) == 3 else None

    def far_field_cm(self) -> tuple[float, float] | None:
        """(start, end) cm of ``far_field``, or None for "off"."""
        return parse_far_field(self.far_field)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict[str, Any] | None) -> ReconstructOptions:
        """Options from a dict (a flow's parameters); unknown keys are refused by name."""
        return options_from_dict(cls, d, "reconstruct")


def parse_far_field(text: str | None) -> tuple[float, float] | None:
    """``--far-field`` (``START:END`` mm, or "off") as (start, end) cm, or None."""
    if text is None or str(text).strip().lower() == "off":
        return None
    try:
        vals = [float(v) for v in str(text).split(":")]
        if len(vals) != 2 or not all(math.isfinite(v) for v in vals) or not 0 <= vals[0] < vals[1]:
            raise ValueError
    except ValueError:
        raise InputError("--far-field takes START:END in mm with 0 <= START < END (or off), "
                         f"got {text!r}") from None
    return vals[0] / MM_PER_CM, vals[1] / MM_PER_CM


def read_jaw_file(path: str | Path, frames: np.ndarray) -> np.ndarray:
    """(F, 4) jaw parameters for ``frames`` from a CSV with columns frame, open_deg, yaw_deg, roll_deg,
    forward_cm."""
    from lgi.io.csvio import read_table
    from lgi.solve.jaw import PARAM_NAMES

    p = Path(path)
    df = read_table(p, "jaw parameter file", ("frame", *PARAM_NAMES), numeric=("frame", *PARAM_NAMES))
    whole = df["frame"].to_numpy() == np.round(df["frame"].to_numpy())
    if not whole.all():
        r = int(np.flatnonzero(~whole)[0])
        raise InputError(f"frame {df['frame'].iloc[r]:g} is not a whole number", path=p, line=r + 2)
    df["frame"] = df["frame"].astype(np.int64)
    dup = df["frame"][df["frame"].duplicated()]
    if len(dup):
        raise InputError("frame listed twice", path=p, frame=int(dup.iloc[0]), line=int(dup.index[0]) + 2)
    # Far outside any jaw's range: degrees where radians were meant, or another file.
    for col, limit in (("open_deg", 90.0), ("yaw_deg", 45.0), ("roll_deg", 45.0), ("forward_cm", 5.0)):
        out = np.abs(df[col].to_numpy()) > limit
        if out.any():
            r = int(np.flatnonzero(out)[0])
            raise InputError(f"{col} {df[col].iloc[r]:g} is outside a jaw's range (|{col}| <= {limit:g})", path=p,
                             line=r + 2, frame=int(df["frame"].iloc[r]))
    df = df.set_index("frame")
    absent = [int(f) for f in frames if int(f) not in df.index]
    if absent:
        raise InputError(f"no jaw parameters for {len(absent)} frames", path=p, frame=absent[0])
    vals = df.loc[[int(f) for f in frames], PARAM_NAMES].to_numpy(float)
    if not np.all(np.isfinite(vals)):
        r = int(np.flatnonzero(~np.all(np.isfinite(vals), axis=1))[0])
        raise InputError("non-finite jaw parameter", path=p, frame=int(frames[r]))
    return vals


def preflight(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> int:
    """Check the inputs of a reconstruction before any work is scheduled (the index loads, the bundles name its
    markers, the jaw option suits the index, a jaw file covers every frame); returns the number of frames.

    The checks are those of preparing the shot, which is kept (:func:`prepared_shot`): the flow's chunk tasks in
    this process then start from it instead of preparing it again."""
    shot = prepared_shot(index_dir, bundles, options)
    if shot.index.jaw_rig() is not None and options.jaw == "none":
        raise InputError("the index was built with a jaw rig (its shapes are unskinned): use --jaw auto or a jaw "
                         "file, or rebuild the index without a rig", path=index_dir)
    if options.observations:
        from lgi.capture.observations import read_rays

        read_rays(options.observations, shot.index.marker_names, shot.frames,
                  np.all(np.isfinite(shot.given), axis=2), options.calib)
    return shot.n_frames  # contours: read and checked when the shot is prepared


def chunk_needs(options: ReconstructOptions, n_frames: int, lo: int, hi: int) -> tuple[int, int]:
    """The frames whose choices finishing frames lo:hi reads: its blends span the smoothing window, each blend's
    weights a window more, and the jaw its own window on top (the shot's edges clamp)."""
    o = options
    h, hj = o.smooth // 2, (o.smooth if o.jaw_smooth is None else o.jaw_smooth) // 2
    m = 2 * h + hj
    return max(0, lo - m), min(n_frames, hi + m)


class Shot:
    """A shot prepared for reconstruction: the solver on the index, the bundles in layout order with gaps
    bridged, the noise resolved and the trajectories denoised on the whole shot, the given jaw read.

    Every stage of the job starts from one (a flow's tasks share one per process: :func:`prepared_shot`).

    Parameters
    ----------
    index_dir : path
        The index directory (``lgi build``).
    bundles : path
        The bundles file (.csv or .parquet).
    options : ReconstructOptions
    """

    def __init__(self, index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> None:
        from lgi.capture.bundles import read_bundles
        from lgi.index.build import LGIIndex
        from lgi.solve.solver import LGISolver

        self.options = o = options
        self.index = index = LGIIndex.load(index_dir)
        b = read_bundles(bundles, index.marker_names)
        #: (F, M) the bundles as given (NaN: none), before any filter or bridging
        self.given = b.positions.copy()
        # Bundles that stand for a marker seen by one camera (:func:`constrain_to_rays`): their rays.
        constraints, self.constrained_file = read_constraints(bundles, b.frames, index.marker_names)
        #: (F, M) bool where a ray stands for the marker, or None; (F, M, 3) ray origins and directions, cm
        self.rays, self.ray_origin, self.ray_direction = constraints or (None, None, None)
        if o.jaw not in ("auto", "none") and index.jaw_rig() is None:
            raise InputError("--jaw FILE needs an index built with --jaw-rig", path=index_dir)
        self.given_jaw = None if o.jaw in ("auto", "none") else read_jaw_file(o.jaw, b.frames)
        sig = o.bilateral_sigmas()
        if sig is not None:
            from lgi.solve.temporal import bilateral_filter

            rest = index.layout().evaluate(index.arrays["neutral"])
            b.positions = bilateral_filter(b.positions, sig[0], sig[1], rest, sig[2])
        self.solver = s = LGISolver(index, temporal_weight=o.temporal_weight, spatial_weight=o.spatial_weight,
                                    jaw="none" if o.jaw == "none" else "auto", method=o.method,
                                    far_field=o.far_field_cm())
        self.pos, self.frames, self.bridged = s.prepare_shot(b, None, o.max_gap, o.noise)
        self.fit_pos = s.denoise(self.pos)
        if self.rays is not None:
            # A ray's point is where the surface must meet the ray: smoothed with the marker's noisy track, it
            # would leave the ray.
            self.fit_pos = np.where(self.rays[..., None], self.pos, self.fit_pos)
        self.contours = None
        if o.contours:
            from lgi.capture.observations import read_contours, read_head_poses, read_rig
            from lgi.dataset.mesh import triangulate
            from lgi.solve.contours import LipContours

            self.contour_curves = read_contours(o.contours, self.frames)
            self.head_R, self.head_t = read_head_poses(o.observations, self.frames)
            self.rig = read_rig(o.observations, o.calib)
            a = index.arrays
            self.contours = LipContours(a["neutral"], triangulate(a["face_vertices"], a["face_offsets"])[0],
                                        a["marker_vertices"], a["marker_weights"])

    def constraints(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """(F * M,) the ``constraint`` column of the diagnostics for frames lo:hi: "bundle" (a bundle was
        given), "ray" (a marker seen by one camera, on its ray) or "none" (missing; bridged if the status says
        so)."""
        hi = self.n_frames if hi is None else hi
        seen = np.all(np.isfinite(self.given[lo:hi]), axis=2)
        out = np.where(seen, "bundle", "none").astype(object)
        if self.rays is not None:
            out[self.rays[lo:hi]] = "ray"
        return out.ravel()

    @property
    def n_frames(self) -> int:
        return len(self.frames)

    def chunks(self) -> list[tuple[int, int]]:
        """(lo, hi) frame ranges of ``chunk_size`` frames."""
        n, c = self.n_frames, self.options.chunk_size
        return [(lo, min(lo + c, n)) for lo in range(0, n, c)]

    def choose(self, lo: int, hi: int, previous=None) -> list:
        """The choices (:class:`~lgi.solve.solver.FrameResult`, no vertices) of frames lo:hi, continuing from
        ``previous``, the choice of frame lo - 1."""
        jaw = None if self.given_jaw is None else self.given_jaw[lo:hi]
        return self.solver.select_sequence(self.fit_pos[lo:hi], self.frames[lo:hi], jaw, previous=previous)

    def finish(self, sels: list, lo: int, hi: int, show_progress: bool = False, first: int = 0):
        """Frames lo:hi blended, skinned and corrected (a :class:`~lgi.solve.solver.SequenceResult` of those
        frames) from the choices ``sels`` of frames ``first:first + len(sels)``, which must hold frames
        :meth:`needs` says (the whole shot's, by default)."""
        o = self.options
        a, b = first, first + len(sels)
        if a > 0 or b < self.n_frames:
            need = self.needs(lo, hi)
            if a > need[0] or b < need[1]:
                raise ValueError(f"frames {lo}:{hi} need the choices of {need[0]}:{need[1]}, given {a}:{b}")
        res = self.solver.finish_sequence(sels, self.pos[a:b], self.frames[a:b], self.bridged[a:b], o.smooth,
                                          o.jaw_smooth, show_progress, self.fit_pos[a:b], lo - a, hi - a)
        self.meet_rays(res, lo, hi)
        return res

    def needs(self, lo: int, hi: int) -> tuple[int, int]:
        """The frames whose choices finishing frames lo:hi reads (:func:`chunk_needs`)."""
        return chunk_needs(self.options, self.n_frames, lo, hi)

    def run(self, show_progress: bool = False):
        """The whole shot in this process (the solver's fastest schedule for it)."""
        o = self.options
        res = self.solver.solve_prepared(self.pos, self.frames, self.bridged, self.fit_pos, o.smooth,
                                         o.jaw_smooth, self.given_jaw, show_progress)
        self.meet_rays(res)
        return res

    def meet_rays(self, res, lo: int = 0, hi: int | None = None) -> None:
        """Correct the surfaces of frames lo:hi (``res``, in place) so that each marker that stands for a ray
        meets it: moved across the ray to its closest point, by the index's correction fields (the same that
        take a surface through its bundles: 1 at the marker, 0 at every other marker, which keep their points).
        Exact bundles already meet their rays (the ray's point is a bundle) up to the correction's truncation,
        which this removes. Noisy bundles are fitted, not interpolated, and so is a ray's point: the surface is
        moved ``noise_gain`` (0) of the way, and ``ray_distance_mm`` says how far it stays. Adds the
        diagnostics' ``constraint`` and ``ray_distance_mm`` (the surface's distance from the ray after it)
        columns."""
        hi = self.n_frames if hi is None else hi
        d = res.diagnostics
        d["constraint"] = self.constraints(lo, hi)
        dist = np.full((hi - lo, self.index.n_markers), np.nan)
        if self.rays is not None:
            solver = self.solver
            for f in np.flatnonzero(self.rays[lo:hi].any(axis=1)):
                g = lo + f
                x = res.vertices[f].astype(np.float64)
                pts = solver.layout.evaluate(x)
                on = self.rays[g]
                o, u = self.ray_origin[g, on], self.ray_direction[g, on]
                target = pts.copy()
                # Noisy bundles are fitted, not interpolated (noise_gain 0): a ray's point, from the same noisy
                # observations, is then fitted like them, and the surface is moved the same share of the way.
                closest = o + np.einsum("ij,ij->i", pts[on] - o, u)[:, None] * u
                target[on] = pts[on] + solver.noise_gain * (closest - pts[on])
                solver.correct(x, target, np.ones(len(pts), bool))
                res.vertices[f] = x
                p = solver.layout.evaluate(x)[on] - o
                dist[f, on] = np.linalg.norm(p - np.einsum("ij,ij->i", p, u)[:, None] * u, axis=1) * MM_PER_CM
        d["ray_distance_mm"] = dist.ravel()
        if self.contours is not None:
            self.meet_contours(res, lo, hi)

    def meet_contours(self, res, lo: int, hi: int) -> None:
        """Deform the lip region of frames lo:hi (``res``, in place) onto the traced lip contours
        (:meth:`lgi.solve.contours.LipContours.fit`); the diagnostics get each frame's RMS pixel distance of
        the lip edges from the curves before and after (``contour_px_before``, ``contour_px_after``), repeated
        on the frame's rows as the jaw's columns are; NaN where nothing was traced or the pose is unknown."""
        from lgi.solve.contours import ContourView

        n_m = self.index.n_markers
        px = np.full((2, hi - lo), np.nan)
        no_pose, unmatched = [], []
        for f in range(lo, hi):
            curves = self.contour_curves.get(f)
            if not curves:
                continue
            if not np.all(np.isfinite(self.head_R[f])):
                no_pose.append(int(self.frames[f]))
                continue
            views = [ContourView(self.rig.cameras[c], self.head_R[f], self.head_t[f], name, pts)
                     for c, name, pts in curves]
            x, px[0, f - lo], px[1, f - lo] = self.contours.fit(res.vertices[f - lo], views)
            if not np.isfinite(px[0, f - lo]):
                unmatched.append(int(self.frames[f]))
            res.vertices[f - lo] = x
        # A traced curve the method could not use is said, not dropped in silence (the columns stay NaN).
        if no_pose:
            log.warning("lip contours of %d frames not used: the tracks table has no head pose for them (first: "
                        "frame %d)", len(no_pose), no_pose[0])
        if unmatched:
            log.warning("lip contours of %d frames not used: no lip edge vertex projects within %.0f px of the "
                        "traced curves (first: frame %d)", len(unmatched), self.contours.gate_px, unmatched[0])
        res.diagnostics["contour_px_before"] = np.repeat(px[0], n_m)
        res.diagnostics["contour_px_after"] = np.repeat(px[1], n_m)


CONSTRAINED = "bundles_constrained.parquet"
RAY_COLUMNS = ("ray_ox", "ray_oy", "ray_oz", "ray_dx", "ray_dy", "ray_dz")


def replace_outputs(options: ReconstructOptions) -> ReconstructOptions:
    """``options`` for a first pass whose files are not the job's outputs: no OBJ, USD or plot."""
    from dataclasses import replace

    return replace(options, obj=False, usd=False, plot=False)


def read_constraints(bundles: str | Path, frames: np.ndarray, names: list[str]) -> tuple[
        tuple[np.ndarray, np.ndarray, np.ndarray] | None, Path | None]:
    """The rays of a bundles file written by :func:`constrain_to_rays` (its ``constraint`` and ``ray_*``
    columns): mask (F, M) bool, origins and unit directions (F, M, 3) cm, head frame (NaN off the rays); and
    the file. (None, None) for any other bundles file."""
    path = Path(bundles)
    if path.suffix.lower() != ".parquet":
        return None, None
    import pyarrow.parquet as pq

    if "constraint" not in pq.read_schema(str(path)).names:
        return None, None
    df = pd.read_parquet(path, columns=["frame", "marker", "constraint", *RAY_COLUMNS])
    ray = (df["constraint"] == "ray").to_numpy()
    row = {int(f): k for k, f in enumerate(frames)}
    col = {n: k for k, n in enumerate(names)}
    f = df["frame"][ray].map(row).to_numpy(np.int64)
    m = df["marker"][ray].map(col).to_numpy(np.int64)
    mask = np.zeros((len(frames), len(names)), bool)
    mask[f, m] = True
    geo = np.full((2, len(frames), len(names), 3), np.nan)
    geo[0, f, m] = df.loc[ray, list(RAY_COLUMNS[:3])].to_numpy(np.float64)
    geo[1, f, m] = df.loc[ray, list(RAY_COLUMNS[3:])].to_numpy(np.float64)
    return (mask, geo[0], geo[1]), path


def constrain_to_rays(shot: Shot, vertices: np.ndarray, out: str | Path) -> dict[str, Any]:
    """Put each marker seen by one camera (``shot.options.observations``) on its viewing ray, at the ray's point
    closest to where ``vertices`` (a reconstruction of the shot without it, (F, V, 3) float32, cm) put the
    marker; write the shot's bundles as given plus those points to ``out`` (Parquet, with a ``constraint``
    column: "bundle" or "ray"), the bundles file a second reconstruction reads. Returns counts."""
    from lgi.capture.bundles import COLUMNS
    from lgi.capture.observations import points_on_rays, read_rays
    from lgi.io.atomic import atomic_file

    o = shot.options
    seen = np.all(np.isfinite(shot.given), axis=2)
    rays = read_rays(o.observations, shot.index.marker_names, shot.frames, seen, o.calib)
    pos = shot.given.copy()
    layout = shot.index.layout()
    before = np.zeros(len(rays))
    if len(rays):
        rows = np.unique(rays.frame)
        at = np.searchsorted(rows, rays.frame)
        surface = layout.evaluate(np.asarray(vertices[rows], np.float64))[at, rays.marker]
        before = rays.distance(surface)
        pos[rays.frame, rays.marker] = points_on_rays(rays, surface)
    geo = np.full((2, *pos.shape), np.nan)
    geo[0, rays.frame, rays.marker] = rays.origin
    geo[1, rays.frame, rays.marker] = rays.direction
    f, m = np.nonzero(np.all(np.isfinite(pos), axis=2))
    kind = np.where(seen[f, m], "bundle", "ray")
    names = np.asarray(shot.index.marker_names, object)
    table = pd.DataFrame({"frame": np.asarray(shot.frames, np.int64)[f], "marker": names[m],
                          "x": pos[f, m, 0], "y": pos[f, m, 1], "z": pos[f, m, 2], "constraint": kind,
                          **{c: geo[k // 3, f, m, k % 3] for k, c in enumerate(RAY_COLUMNS)}})
    with atomic_file(out, suffix=".parquet", durable=False) as tmp:
        table[[*COLUMNS, "constraint", *RAY_COLUMNS]].to_parquet(tmp, index=False)
    if len(rays):
        log.info("%d markers seen by one camera put on their rays (%d frames); the first reconstruction was "
                 "%.3f mm from them (median, max %.3f mm)", len(rays), len(np.unique(rays.frame)),
                 float(np.median(before)) * MM_PER_CM, float(before.max()) * MM_PER_CM)
    else:
        log.warning("%s: no marker is seen by one camera alone where the shot lacks its bundle: no ray constraint",
                    o.observations)
    return {"rays": len(rays), "ray_frames": int(len(np.unique(rays.frame))),
            "ray_offset_before_mm": float(np.median(before) * MM_PER_CM) if len(rays) else 0.0}


# ------------------------------------------------------------------------------------------------ choices
def save_choices(path: str | Path, sels: list, durable: bool = True) -> None:
    """Write frames' choices to an npz, exactly (every field a later frame or the finish reads); ``durable``:
    flushed to disk before it appears (see :func:`lgi.io.atomic.atomic_file`)."""
    from lgi.io.atomic import atomic_file
    from lgi.io.npz import save_npz
    from lgi.solve.solver import _stack_slots

    a: dict[str, np.ndarray] = {}
    a["width"] = np.array([r.shapes.shape[1] for r in sels], np.int64)
    a["shapes"], a["weights"] = _stack_slots([r.shapes for r in sels], [r.weights for r in sels])
    for k in ("n_containing", "status", "projection", "score", "residual", "bundles", "simplex_shapes",
              "simplex_weights"):
        a[k] = np.stack([getattr(r, k) for r in sels])
    a["source"] = np.stack([np.asarray(r.source, object).astype(str) for r in sels])
    a["fallback"] = np.array(json.dumps([r.fallback for r in sels]))
    if sels[0].jaw is not None:
        a["jaw"] = np.stack([r.jaw for r in sels])
    if sels[0].far_share is not None:
        a["far_share"] = np.stack([r.far_share for r in sels])
    a["fit_weights"] = np.stack([r.fit.weights for r in sels])
    a["fit_residual"] = np.stack([r.fit.residual for r in sels])
    a["fit_rms"] = np.array([r.fit.rms for r in sels], np.float64)
    a["fit_jaw_source"] = np.array([r.fit.jaw_source for r in sels])
    if sels[0].fit.jaw is not None:
        a["fit_jaw"] = np.stack([r.fit.jaw for r in sels])
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, suffix=".npz", durable=durable) as tmp:
        save_npz(tmp, **a)


def load_choices(path: str | Path) -> list:
    """The choices :func:`save_choices` wrote."""
    from lgi.io.npz import load_npz
    from lgi.solve.globalfit import GlobalFitResult
    from lgi.solve.solver import FrameResult

    a = load_npz(path)
    notes = json.loads(str(a["fallback"]))
    out = []
    for f, k in enumerate(a["width"]):
        fit = GlobalFitResult(a["fit_weights"][f], a["fit_jaw"][f] if "fit_jaw" in a else None,
                              a["fit_residual"][f], float(a["fit_rms"][f]), str(a["fit_jaw_source"][f]))
        out.append(FrameResult(np.zeros((0, 3), np.float32), a["shapes"][f, :, :k], a["weights"][f, :, :k],
                               a["n_containing"][f], a["status"][f], a["projection"][f], a["score"][f],
                               a["residual"][f], notes[f], a["jaw"][f] if "jaw" in a else None, a["bundles"][f],
                               None, a["source"][f].astype(object), fit, a["simplex_shapes"][f],
                               a["simplex_weights"][f], a["far_share"][f] if "far_share" in a else None))
    return out


# ------------------------------------------------------------------------------------- flow stages
_SHOTS: dict[str, Shot] = {}
_SHOTS_LOCK = threading.Lock()


def _fingerprint(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> str:
    """What a prepared shot depends on: the index's and the bundles' (and a jaw file's) paths, sizes and
    modification times, and the options."""
    files = [Path(index_dir) / n for n in ("manifest.json", "index.npz", "deltas.npy")] + [Path(bundles)]
    if options.jaw not in ("auto", "none"):
        files.append(Path(options.jaw))
    stats = []
    for f in files:
        st = f.stat()
        stats.append([str(f.resolve()), st.st_size, st.st_mtime_ns])
    return json.dumps([stats, options.to_json()], sort_keys=True)


def prepared_shot(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> Shot:
    """The shot prepared once per process and reused by every chunk task that runs there (the index loaded,
    the bundles read, bridged and denoised, the noise estimated): a flow's tasks on Prefect's threads share one,
    each Dask worker process prepares its own. A changed input file makes a new one. The solver is only read
    while chunks are chosen and finished, so the tasks may share it."""
    key = _fingerprint(index_dir, bundles, options)
    with _SHOTS_LOCK:
        shot = _SHOTS.get(key)
        if shot is None:
            _SHOTS.clear()  # one shot at a time per process: a worker moves from shot to shot
            shot = _SHOTS[key] = Shot(index_dir, bundles, options)
    return shot


def forget_shots() -> None:
    """Drop this process's prepared shot and remembered chunk files (the next task prepares the shot again)."""
    with _SHOTS_LOCK:
        _SHOTS.clear()
        _MEMO.clear()
        _PARTS.clear()


def choose_chunk(index_dir: str, bundles: str, options: ReconstructOptions, lo: int, hi: int, out: str,
                 previous: str | None = None) -> str:
    """Choose frames lo:hi (continuing from the last choice in the ``previous`` chunk's file); write them to
    ``out`` (npz). Chained over a shot's chunks, the choices are those a single pass makes."""
    shot = prepared_shot(index_dir, bundles, options)
    prev = _recall(previous, load_choices)[-1] if previous else None
    sels = shot.choose(lo, hi, prev)
    save_choices(out, sels, durable=False)
    _remember(out, sels)
    return out


# The chunk files a process wrote, kept in memory for its own tasks that read them next (the flow's tasks on
# Prefect's threads): the files hold the same values exactly, so a task in another process (Dask) reads the
# same. Keyed by path, size and modification time, so a file written again is read again.
_MEMO: OrderedDict[str, tuple[tuple[int, int], Any]] = OrderedDict()
_MEMO_KEPT = 64


def _file_key(path: str | Path) -> tuple[int, int]:
    st = Path(path).stat()
    return st.st_size, st.st_mtime_ns


def _remember(path: str | Path, value: Any) -> None:
    with _SHOTS_LOCK:
        _MEMO[str(path)] = (_file_key(path), value)
        while len(_MEMO) > _MEMO_KEPT:
            _MEMO.popitem(last=False)


def _recall(path: str | Path, load: Callable[[str | Path], Any]) -> Any:
    """What ``path`` holds: from memory when this process wrote that very file, else ``load(path)``."""
    with _SHOTS_LOCK:
        hit = _MEMO.get(str(path))
    if hit is not None and hit[0] == _file_key(path):
        return hit[1]
    return load(path)


def finish_chunk(index_dir: str, bundles: str, options: ReconstructOptions, choices: list[str], lo: int, hi: int,
                 out: str, first: int = 0, keep: bool = False) -> str:
    """Blend, skin and correct frames lo:hi from the choice files ``choices`` (consecutive chunks from frame
    ``first``, covering :meth:`Shot.needs`; by default the whole shot's); write the part to ``out``
    (:func:`save_part`), or with ``keep`` hold it in this process's memory under that name for
    :func:`assemble` in the same process (a flow on threads: the same values, without the disk)."""
    shot = prepared_shot(index_dir, bundles, options)
    sels = [s for path in choices for s in _recall(path, load_choices)]
    res = shot.finish(sels, lo, hi, first=first)
    part = (res.vertices, res.jaw, res.diagnostics)
    if keep:
        with _SHOTS_LOCK:
            _PARTS[str(out)] = part
    else:
        save_part(out, *part)
    return out


# Finished chunks kept in memory (finish_chunk's ``keep``) until assemble takes them, or forget_parts.
_PARTS: dict[str, tuple[np.ndarray, np.ndarray | None, pd.DataFrame]] = {}


def forget_parts(folder: str | Path) -> None:
    """Drop the finished chunks kept in memory under ``folder`` (a failed or interrupted run's)."""
    prefix = str(Path(folder)) + os.sep
    with _SHOTS_LOCK:
        for k in [k for k in _PARTS if k.startswith(prefix)]:
            del _PARTS[k]


def save_part(path: str | Path, vertices: np.ndarray, jaw: np.ndarray | None, diagnostics: pd.DataFrame) -> None:
    """Write a finished chunk: its vertices ((F, V, 3) float32, cm) and the jaw used ((F, 6), if any) to
    ``path`` (npz), its rows of ``diagnostics.csv`` beside it (the same name, .parquet)."""
    from lgi.io.atomic import atomic_file
    from lgi.io.npz import save_npz

    with atomic_file(Path(path).with_suffix(".parquet"), durable=False) as tmp:
        diagnostics.to_parquet(tmp, index=False)
    with atomic_file(path, suffix=".npz", durable=False) as tmp:
        save_npz(tmp, vertices=vertices, **({} if jaw is None else {"jaw": jaw}))


def load_part(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, pd.DataFrame]:
    """The finished chunk :func:`save_part` wrote: vertices, jaw (or None) and diagnostics."""
    from lgi.io.npz import load_npz

    a = load_npz(path)
    return a["vertices"], a.get("jaw"), pd.read_parquet(Path(path).with_suffix(".parquet"))


def assemble(index_dir: str, bundles: str, options: ReconstructOptions, parts: list[str],
             out: str) -> dict[str, Any]:
    """Join the finished chunks (in frame order) into the shot's result and write it
    (:func:`write_reconstruction`); returns the summary."""
    from lgi.solve.solver import SequenceResult

    t0 = time.perf_counter()
    shot = prepared_shot(index_dir, bundles, options)
    with _SHOTS_LOCK:
        kept = [_PARTS.pop(str(path), None) for path in parts]
    p = [load_part(path) if k is None else k for path, k in zip(parts, kept, strict=True)]
    jaw = np.concatenate([x[1] for x in p]) if p[0][1] is not None else None
    diag = pd.concat([x[2] for x in p], ignore_index=True)
    res = SequenceResult(np.asarray(shot.frames), np.concatenate([x[0] for x in p]), diag, jaw,
                         shot.solver.noise, options.smooth)
    write_reconstruction(out, res, shot.index.arrays, options, shot.constrained_file)
    return summarise(res, shot, out, {"finish": time.perf_counter() - t0})


# ------------------------------------------------------------------------------------------------ outputs
def per_frame_table(diagnostics: pd.DataFrame) -> pd.DataFrame:
    """Per frame: share of bundles contained, bundles projected and missing, largest distance to the bundles
    before and after the correction (mm)."""
    d = diagnostics
    frames, inv = np.unique(d.frame.to_numpy(), return_inverse=True)
    n = np.bincount(inv)
    status = d.status.to_numpy()

    def count(mask: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=mask.astype(np.float64), minlength=len(frames))

    def worst(col: str) -> np.ndarray:
        out = np.full(len(frames), -np.inf)
        v = d[col].to_numpy(np.float64)
        ok = np.isfinite(v)
        np.maximum.at(out, inv[ok], v[ok])
        return np.where(np.isfinite(out), out, np.nan)

    return pd.DataFrame({"frame": frames, "contained": count(status == "contained") / n,
                         "projected": count(status == "projected").astype(np.int64),
                         "missing": count(np.isin(status, ["missing", "bridged"])).astype(np.int64),
                         "residual_before_mm": worst("residual_before_mm"), "residual_mm": worst("residual_mm")})


def plot_per_frame(per_frame: pd.DataFrame, path: Path) -> None:
    """The per-frame table as a two-panel PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
    ax[0].plot(per_frame.frame, per_frame.residual_before_mm, label="max distance to bundles before correction")
    ax[0].set_ylabel("mm")
    ax[0].legend(fontsize=8)
    ax[1].plot(per_frame.frame, per_frame.projected, label="bundles projected (outside the data)")
    ax[1].plot(per_frame.frame, per_frame.missing, label="bundles missing or bridged")
    ax[1].set_xlabel("frame")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_reconstruction(out: str | Path, res, arrays: dict[str, np.ndarray], options: ReconstructOptions,
                         constrained: Path | None = None) -> None:
    """The one writer of a reconstruction: ``meshes.npz`` (vertices (F, V, 3) float32 cm, frames, jaw (F, 4)
    with a rig), ``diagnostics.csv``, ``per_frame.csv`` and, as asked, ``obj/``, ``shot.usdc``,
    ``per_frame.png`` and ``bundles_constrained.parquet`` (the bundles with the rays' points: ``constrained``);
    through :func:`lgi.io.atomic.job_outputs` (an earlier run's outputs not written now are
    removed)."""
    from lgi._stages import stage as debug_stage
    from lgi.io.atomic import job_outputs
    from lgi.io.csvio import write_csv
    from lgi.io.npz import save_npz

    with job_outputs(out, OUTPUTS, OUTPUT_CONTENTS) as stage:
        debug_stage("write")
        extra = {} if res.jaw is None else {"jaw": res.jaw.astype(np.float32)}
        save_npz(stage / "meshes.npz", vertices=res.vertices, frames=res.frames, **extra)
        write_csv(res.diagnostics, stage / "diagnostics.csv")
        per_frame = per_frame_table(res.diagnostics)
        per_frame.to_csv(stage / "per_frame.csv", index=False, float_format="%.6g")
        if options.plot:
            plot_per_frame(per_frame, stage / "per_frame.png")
        if options.obj:
            from lgi.io.obj import write_obj

            (stage / "obj").mkdir()
            for f, frame in enumerate(res.frames):
                write_obj(stage / "obj" / f"frame_{int(frame):05d}.obj", res.vertices[f], arrays["face_vertices"],
                          arrays["face_offsets"], arrays.get("uvs"), arrays.get("face_uvs"))
        if constrained is not None:
            shutil.copyfile(constrained, stage / CONSTRAINED)
        if options.usd:
            from lgi.export.formats import write_usd

            write_usd(stage / "shot.usdc", res.vertices, arrays["face_vertices"], arrays["face_offsets"],
                      arrays.get("uvs"), arrays.get("face_uvs"), res.frames, fps=options.fps)


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


def check_output(out: str | Path, inputs: tuple[Any, ...] = ()) -> None:
    """Refuse, before any work, an output path that cannot become the job's directory, or whose outputs would
    replace one of the run's ``inputs`` (index, bundles, jaw file)."""
    from lgi.io.atomic import check_contents
    from lgi.io.atomic import check_output as check

    check(out, "dir")
    check_contents(out, OUTPUT_CONTENTS)
    for name in OUTPUTS:
        check(Path(out) / name, "dir" if name == "obj" else "file", inputs=inputs)


def reconstruct(index_dir: str | Path, bundles: str | Path, out: str | Path,
                options: ReconstructOptions | None = None, show_progress: bool = False) -> dict[str, Any]:
    """Reconstruct a shot in this process and write its outputs into ``out``; returns the summary
    (:func:`summarise`; :func:`report_lines` formats it).

    With ``options.observations``, twice: without the markers seen by one camera, then through their points on
    their rays (:func:`constrain_to_rays`)."""
    from lgi._stages import stage

    options = options or ReconstructOptions()
    if options.method == "blendshape":
        from lgi.jobs.blendshape import reconstruct_blendshape

        return reconstruct_blendshape(index_dir, bundles, out, options, show_progress)
    check_output(out, (index_dir, bundles, options.jaw, options.observations, options.calib, options.contours))
    t0 = time.perf_counter()
    shot = Shot(index_dir, bundles, options)
    t1 = time.perf_counter()
    stage("solve")
    res = shot.run(show_progress)
    t2 = time.perf_counter()
    if not options.observations:
        write_reconstruction(out, res, shot.index.arrays, options)
        return summarise(res, shot, out, {"load": t1 - t0, "solve": t2 - t1, "write": time.perf_counter() - t2})
    from lgi.io.atomic import make_temp_dir, sweep

    parent, prefix = Path(out).absolute().parent, f".{Path(out).name}.rays-"
    parent.mkdir(parents=True, exist_ok=True)
    sweep(parent, prefix)
    work = make_temp_dir(parent, prefix)
    try:
        counts = constrain_to_rays(shot, res.vertices, work / CONSTRAINED)
        t3 = time.perf_counter()
        shot = Shot(index_dir, work / CONSTRAINED, options)
        res = shot.run(show_progress)
        t4 = time.perf_counter()
        write_reconstruction(out, res, shot.index.arrays, options, shot.constrained_file)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    s = summarise(res, shot, out, {"load": t1 - t0, "solve": (t2 - t1) + (t4 - t3), "rays": t3 - t2,
                                   "write": time.perf_counter() - t4})
    return {**s, **counts}
