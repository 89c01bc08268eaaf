"""A shot prepared for reconstruction (:class:`Shot`): the solver on the index, the bundles read, bridged and
denoised, the given jaw; the stages it runs (choose, finish, the whole shot) and the corrections after them
(rays, lip contours); and the bundles file of a second pass, with markers seen by one camera put on their rays
(:func:`constrain_to_rays`)."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.capture.bundles import COLUMNS, read_bundles
from lgi.capture.observations import points_on_rays, read_rays
from lgi.errors import InputError
from lgi.io.atomic import atomic_file
from lgi.io.stored import ScratchArray, StoredArray
from lgi.jobs.reconstruct.options import ReconstructOptions, read_jaw_file
from lgi.jobs.reconstruct.rays import RAY_COLUMNS, read_constraints
from lgi.memory import release_free_memory
from lgi.solve.streamed import all_rows, frame_blocks
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)


def chunk_needs(options: ReconstructOptions, n_frames: int, lo: int, hi: int) -> tuple[int, int]:
    """The frames whose choices finishing frames lo:hi reads (:func:`lgi.solve.finish.smoothing_reach`; the
    shot's edges clamp)."""
    from lgi.solve.finish import smoothing_reach

    m = smoothing_reach(options.smooth, options.jaw_smooth)
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
        from lgi.index.build import LGIIndex
        from lgi.solve.solver import LGISolver

        self.options = o = options
        self.index = index = LGIIndex.load(index_dir)
        b = read_bundles(bundles, index.marker_names, on_disk=True)
        if not isinstance(b.positions, StoredArray):
            b.positions = ScratchArray.of(b.positions)
        #: (F, M, 3) the bundles as given (NaN: none), before any filter or bridging, on disk
        self.given = b.positions
        #: (F, M) bool: the marker has a bundle in the frame
        self.seen = all_rows(self.given, lambda p: np.all(np.isfinite(p), axis=2))
        release_free_memory()  # the reader's tables
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
            b.positions = bilateral_filter(np.asarray(b.positions), sig[0], sig[1], rest, sig[2])
        s = LGISolver(index, temporal_weight=o.temporal_weight, spatial_weight=o.spatial_weight,
                      jaw="none" if o.jaw == "none" else "auto", method=o.method, far_field=o.far_field_cm())
        # The shot's per-frame arrays wait on disk, and its blocks read them by range: a long take's would not fit
        # in memory (ICT's 108 markers: 2.6 kB per frame each).
        pos, self.frames, self.bridged, noise = s.prepare_shot(b, None, o.max_gap, o.noise)
        del b
        fit_pos, noise = s.denoise(pos, noise)
        #: the bundles' noise (:class:`~lgi.solve.noise.ShotNoise`: given or estimated, and what smoothing left)
        self.noise = noise
        #: the solver of this shot's noise (:meth:`~lgi.solve.solver.LGISolver.with_noise`)
        self.solver = s.with_noise(noise)
        if not isinstance(pos, StoredArray):
            pos = ScratchArray.of(pos)
            fit_pos = pos if fit_pos is pos else fit_pos
        #: (F, M, 3) cm, the bundles in layout order with gaps bridged (:meth:`LGISolver.prepare_shot`)
        self.pos = pos
        if not isinstance(fit_pos, StoredArray):
            fit_pos = ScratchArray.of(fit_pos)
        if self.rays is not None:
            # A ray's point is where the surface must meet the ray: smoothed with the marker's noisy track, it
            # would leave the ray.
            fit_pos = self._rays_unsmoothed(fit_pos)
        #: (F, M, 3) cm, the positions the frames are fitted to (denoised; ``pos`` itself for exact bundles)
        self.fit_pos = fit_pos
        del pos, fit_pos
        release_free_memory()
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

    def _rays_unsmoothed(self, fit_pos: StoredArray) -> StoredArray:
        """``fit_pos`` with each ray's bundle as given (``pos``), a block at a time."""
        if fit_pos is self.pos:
            return fit_pos
        out = ScratchArray(fit_pos.shape, np.float64)
        for lo, hi in frame_blocks(self.n_frames):
            out.write(lo, np.where(self.rays[lo:hi, :, None], self.pos[lo:hi], fit_pos[lo:hi]))
        return out

    def constraints(self, lo: int = 0, hi: int | None = None) -> np.ndarray:
        """(F * M,) the ``constraint`` column of the diagnostics for frames lo:hi: "bundle" (a bundle was
        given), "ray" (a marker seen by one camera, on its ray) or "none" (missing; bridged if the status says
        so)."""
        hi = self.n_frames if hi is None else hi
        out = np.where(self.seen[lo:hi], "bundle", "none").astype(object)
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
        left = self.noise.left
        return self.solver.select_sequence(self.fit_pos[lo:hi], self.frames[lo:hi], jaw, previous=previous,
                                           left=None if left is None else left[lo:hi])

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
        left = self.noise.left
        res = self.solver.finish_sequence(sels, self.pos[a:b], self.frames[a:b], self.bridged[a:b], o.smooth,
                                          o.jaw_smooth, show_progress, self.fit_pos[a:b], lo - a, hi - a,
                                          None if left is None else left[a:b])
        self.meet_rays(res, lo, hi)
        return res

    def needs(self, lo: int, hi: int) -> tuple[int, int]:
        """The frames whose choices finishing frames lo:hi reads (:func:`chunk_needs`)."""
        return chunk_needs(self.options, self.n_frames, lo, hi)

    def run(self, show_progress: bool = False):
        """The whole shot in this process, as one result (:meth:`stream` in one block)."""
        from lgi.solve.results import join_results

        parts = list(self.stream(max(self.n_frames, 1), show_progress))
        return parts[0] if len(parts) == 1 else join_results(parts)

    def stream(self, block: int, show_progress: bool = False) -> Iterator[Any]:
        """The whole shot in this process in blocks of ``block`` frames, in order: each a
        :class:`~lgi.solve.results.SequenceResult` of its frames, the bits of the shot solved at once
        (:meth:`lgi.solve.solver.LGISolver.stream_prepared`, the solver's fastest schedule), with the rays and
        contours met. Only a block's surfaces are held."""
        for res, _ in self.stream_from(block, show_progress):
            yield res

    def stream_from(self, block: int, show_progress: bool = False, start: int = 0,
                    carried: tuple[int, list] | None = None) -> Iterator[tuple[Any, tuple[int, list]]]:
        """:meth:`stream` from frame ``start`` on, each block with what the next one reads of it
        (:meth:`lgi.solve.solver.LGISolver.stream_from`): a stopped run resumes from its last written block."""
        o = self.options
        for lo, hi, res, carry in self.solver.stream_from(self.pos, self.frames, self.bridged, self.fit_pos, o.smooth,
                                                          o.jaw_smooth, self.given_jaw, show_progress, block, start,
                                                          carried):
            self.meet_rays(res, lo, hi)
            yield res, carry

    def meet_rays(self, res, lo: int = 0, hi: int | None = None) -> None:
        """Correct the surfaces of frames lo:hi (``res``, in place) so that each marker that stands for a ray
        meets it: moved across the ray to its closest point, by the index's correction fields (the same that
        take a surface through its bundles: 1 at the marker, 0 at every other marker, which keep their points).
        Exact bundles already meet their rays (the ray's point is a bundle) up to the correction's truncation,
        which this removes. Noisy bundles are fitted, not interpolated, and so is a ray's point: the surface is
        moved ``ray_gain`` (0) of the way, and ``ray_distance_mm`` says how far it stays. Adds the
        diagnostics' ``constraint`` and ``ray_distance_mm`` (the surface's distance from the ray after it)
        columns."""
        hi = self.n_frames if hi is None else hi
        d = res.diagnostics
        d["constraint"] = self.constraints(lo, hi)
        dist = np.full((hi - lo, self.index.n_markers), np.nan)
        if self.rays is not None:
            for f in np.flatnonzero(self.rays[lo:hi].any(axis=1)):
                g = lo + f
                x = res.vertices[f].astype(np.float64)
                on = self.rays[g]
                dist[f, on] = self.solver.meet_rays(x, on, self.ray_origin[g, on], self.ray_direction[g, on])
                res.vertices[f] = x
        d["ray_distance_mm"] = dist.ravel()
        if self.contours is not None:
            self.meet_contours(res, lo, hi)

    def meet_contours(self, res, lo: int, hi: int) -> None:
        """Deform the lip region of frames lo:hi (``res``, in place) onto the traced lip contours
        (:meth:`lgi.solve.contours.LipContours.fit`); the diagnostics get each frame's RMS pixel distance of
        the lip edges from the curves before and after (``contour_px_before``, ``contour_px_after``), repeated
        on the frame's rows as the jaw's columns are; NaN where nothing was traced or the pose is unknown."""
        n_m = self.index.n_markers
        px, no_pose, unmatched = self.contours.fit_frames(
            res.vertices, [self.contour_curves.get(f) for f in range(lo, hi)], self.rig.cameras, self.head_R[lo:hi],
            self.head_t[lo:hi])
        no_pose = [int(self.frames[lo + f]) for f in no_pose]
        unmatched = [int(self.frames[lo + f]) for f in unmatched]
        # A traced curve the method could not use is said, not dropped in silence (the columns stay NaN).
        if no_pose:
            log.warning("lip contours of %d frames not used: the tracks table has no head pose for them (first: "
                        "frame %d)", len(no_pose), no_pose[0])
        if unmatched:
            log.warning("lip contours of %d frames not used: no lip edge vertex projects within %.0f px of the "
                        "traced curves (first: frame %d)", len(unmatched), self.contours.gate_px, unmatched[0])
        res.diagnostics["contour_px_before"] = np.repeat(px[0], n_m)
        res.diagnostics["contour_px_after"] = np.repeat(px[1], n_m)


def constrain_to_rays(shot: Shot, vertices: np.ndarray, out: str | Path) -> dict[str, Any]:
    """Put each marker seen by one camera (``shot.options.observations``) on its viewing ray, at the ray's point
    closest to where ``vertices`` (a reconstruction of the shot without it, (F, V, 3) float32, cm) put the
    marker; write the shot's bundles as given plus those points to ``out`` (Parquet, with a ``constraint``
    column: "bundle" or "ray"), the bundles file a second reconstruction reads. Returns counts."""
    o = shot.options
    seen = shot.seen
    rays = read_rays(o.observations, shot.index.marker_names, shot.frames, seen, o.calib)
    pos = np.array(shot.given)
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
