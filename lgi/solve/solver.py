"""Per-frame reconstruction by local geometric indexing.

For every bundle the solver finds the simplices of its point cloud that contain it; each gives convex
barycentric weights over shapes, a candidate local surface through the bundle. It keeps the candidate
whose blend of shapes best fits the bundle's natural neighbours (RMS distance, plus a preference for
shapes shared with the previous frame's choice). A bundle outside its cloud is projected onto the
cloud's hull, the candidate chosen by the same criterion with its own distance included. Every vertex
then mixes the bundles' shape weights with its natural-neighbour weights. Where a bundle was projected
(or an alias shape replaced a merged point), the remaining bundle residuals are interpolated smoothly
(:mod:`lgi.index.smooth`) so the surface passes through every seen bundle.

A bundle missing from a frame takes its previous frame's choice, or else that of its nearest seen
natural neighbour (or nearest seen bundle); the diagnostics say which.

The solver composes the stages a frame goes through, each in its own module: the noise treatment
(:mod:`lgi.solve.noise`), the choice of each bundle's weights (:mod:`lgi.solve.selection`), the surface
(:mod:`lgi.solve.surface`) and the sequence's finish and diagnostics (:mod:`lgi.solve.finish`).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import warnings
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np
import scipy.sparse
from threadpoolctl import threadpool_limits

from lgi.capture.bundles import Bundles
from lgi.errors import InputError
from lgi.index.build import LGIIndex
from lgi.io.stored import ScratchArray, StoredArray
from lgi.solve._blend_kernels import BundleReach
from lgi.solve._select_kernels import OWN_WEIGHT, IndexArrays
from lgi.solve.finish import Finishing, slot_labels
from lgi.solve.globalfit import GlobalFit
from lgi.solve.noise import NoiseHandling, ShotNoise
from lgi.solve.results import FITTED, STATUS, FrameResult, SequenceResult, join_results
from lgi.solve.selection import LOCAL_MIN_MISFIT, Selection
from lgi.solve.settings import FAR_FIELD, SolverSettings
from lgi.solve.streamed import all_rows, frame_blocks
from lgi.solve.surface import FAR_MARGIN, Surface, _FarField
from lgi.solve.temporal import bridge_gaps, bridged_blocks
from lgi.threads import one_blas_thread

__all__ = ["FAR_FIELD", "FAR_MARGIN", "FITTED", "LOCAL_MIN_MISFIT", "STATUS", "FrameResult", "LGISolver",
           "PreparedShot", "SequenceResult", "ShotNoise", "slot_labels"]

log = logging.getLogger(__name__)


class PreparedShot(NamedTuple):
    """A shot made ready to solve (:meth:`LGISolver.prepare_shot`)."""

    #: (F, M, 3) cm, the bundles in layout order with gaps bridged (NaN: missing)
    positions: np.ndarray
    #: (F,) frame numbers
    frames: np.ndarray
    #: (F, M) bool, the positions bridged over a gap
    bridged: np.ndarray
    #: the bundles' noise, given, estimated or from their covariances
    noise: ShotNoise


class LGISolver(NoiseHandling, Selection, Surface, Finishing):
    """Reconstruct frames of bundles with a built :class:`~lgi.index.build.LGIIndex`.

    The solver is the index's arrays made ready once, and the stages that read them; it does not change after
    it is made. A shot's noise is a value (:class:`~lgi.solve.noise.ShotNoise`) that :meth:`prepare_shot` and
    :meth:`denoise` return, and :meth:`with_noise` gives the solver of it (the arrays shared), so what a call
    does never depends on an earlier shot.

    Parameters
    ----------
    index
        The built index.
    settings
        How frames are chosen and blended (default: :class:`~lgi.solve.settings.SolverSettings`' defaults).
    **changes
        Settings to change from ``settings``, by name (``LGISolver(index, method="simplex")``).
    """

    def __init__(self, index: LGIIndex, settings: SolverSettings | None = None, **changes: Any) -> None:
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(SolverSettings)})
        if unknown:
            raise TypeError(f"LGISolver got unknown settings {unknown}")
        self.settings = st = dataclasses.replace(settings or SolverSettings(), **changes)
        if st.method not in ("local", "simplex"):
            raise InputError(f"unknown method {st.method!r}: use 'local' or 'simplex'")
        self.method = st.method
        self.local_prior = float(st.local_prior)
        self.index = index
        a = index.arrays
        self._a = a
        self.temporal_weight = float(st.temporal_weight)
        self.alias_min_weight = float(st.alias_min_weight)
        self.correct_residuals = st.correct_residuals
        self.tolerance = float(st.tolerance)
        self.n_project = int(st.n_project)
        self.spatial_weight = float(st.spatial_weight)
        self.top_k = int(st.top_k)
        self._n_ext = len(index.manifest["shapes"]) + 1
        self._no_agree = np.zeros((1, 1))
        self._no_shapes = np.zeros((index.n_markers, 4), np.int64)
        self._no_lam = np.zeros((index.n_markers, 4))
        self._scan = np.full((index.n_markers, self.top_k), -2, np.int64)
        self._no_scores = np.zeros((index.n_markers, self.top_k))
        self._no_first = np.zeros(index.n_markers)
        self.layout = index.layout()
        self._x0 = np.asarray(a["neutral"], np.float64)
        self._deltas = np.ascontiguousarray(index.deltas)  # read once: the blend touches all of it every frame
        self._deltas_flat = self._deltas.reshape(len(self._deltas), -1)  # a view: rows of 3V for blend_uniform
        # (V,) each vertex's total natural-neighbour weight (1 where bundles reach, 0 elsewhere), for uniform blends
        self._w_sum = np.add.reduceat(np.r_[a["w_data"], 0.0], a["w_indptr"][:-1]) * (np.diff(a["w_indptr"]) > 0)
        # The natural-neighbour weights by bundle (CSC), for blending each bundle's own weights over the vertices
        # it reaches (:func:`lgi.solve._blend_kernels.blend_on_base`).
        csc = scipy.sparse.csr_matrix((a["w_data"], a["w_indices"], a["w_indptr"]),
                                      shape=(len(self._x0), index.n_markers)).tocsc()
        csc.sort_indices()
        self._reach = BundleReach(csc.indptr.astype(np.int64), csc.indices.astype(np.int64),
                                  csc.data.astype(np.float64))
        self._no_ramp = np.zeros(len(self._x0))
        self.far_field = None if st.far_field is None else (float(st.far_field[0]), float(st.far_field[1]))
        self._far = _FarField(a, index.n_markers, self.far_field)
        nb_off, nb_idx = a["nb_off"], a["nb_idx"]
        self._neighbours = [nb_idx[nb_off[i]:nb_off[i + 1]] for i in range(index.n_markers)]
        self._rest = a["ptab"][0]
        self.rig = index.jaw_rig()
        if self.rig is not None and st.jaw == "none":
            raise InputError("the index was built with a jaw rig (its shapes are unskinned): use jaw 'auto' or "
                             "given parameters, or rebuild the index without a rig")
        self._bundle_w = None
        if self.rig is not None:
            self._skin_w = np.ascontiguousarray(self.rig.weights, np.float64)
            self._bundle_w = self.layout.evaluate(self.rig.weights[:, None])[:, 0]
        #: the bundles' noise the stages read (:class:`~lgi.solve.noise.ShotNoise`; a shot's: :meth:`with_noise`)
        self.shot_noise = ShotNoise.uniform(st.noise, index.n_markers)
        self.global_fit = GlobalFit(a["ptab"], self.rig, self._bundle_w, gain=self.shot_noise.join_gain)
        if self.rig is not None and not self.global_fit.jaw_observable:
            log.warning("%s", self.global_fit.jaw_note)
        self._basis = self.global_fit.basis
        # Each bundle with its natural neighbours, as flat (bundle, row) pairs for vectorised misfits.
        counts = np.diff(nb_off)
        self._pair_i = np.concatenate([np.arange(index.n_markers), np.repeat(np.arange(index.n_markers), counts)])
        self._pair_j = np.concatenate([np.arange(index.n_markers), nb_idx]).astype(np.int64)
        self._pair_w = np.concatenate([np.full(index.n_markers, OWN_WEIGHT), np.ones(len(nb_idx))])
        own = np.repeat(np.arange(index.n_markers), counts)
        self._nb_pairs = np.stack([own, nb_idx], 1)[own < nb_idx]
        # Each bundle's second ring of natural neighbours: where its own weights are tried beyond the bundles
        # they were fitted to.
        ring_i, ring_j = [], []
        for i in range(index.n_markers):
            first = set(self._neighbours[i].tolist())
            second = set()
            for j in first:
                second.update(self._neighbours[j].tolist())
            second -= first | {i}
            ring_i += [i] * len(second)
            ring_j += sorted(second)
        self._ring_i = np.asarray(ring_i, np.int64)
        self._ring_j = np.asarray(ring_j, np.int64)
        # A bundle off a flat cloud's plane by less than the flatness tolerance is still inside it.
        self._dist_tol = float(index.manifest["options"]["cloud"]["flat_tol"])
        self._ix = IndexArrays(a["dim"], a["origin"], a["basis"], a["pts"], a["pt_off"], a["pt_shape"], a["alias_off"],
                               a["class_off"], a["alias_shape"], a["sx"], a["tinv"], a["hull"], a["hull_off"],
                               a["grid_lo"], a["grid_h"], a["grid_dims"], a["cell_off"], a["cell_start"],
                               a["cell_items"], a["ptab"], a["nb_off"], a["nb_idx"], a["snap_radius"])

    def with_noise(self, noise: ShotNoise | float | np.ndarray) -> LGISolver:
        """This solver for bundles with this noise (a :class:`~lgi.solve.noise.ShotNoise`, as :meth:`prepare_shot`
        and :meth:`denoise` return it, or mm per coordinate, or (3,) per axis, the same for every marker). The
        index's arrays are shared; this solver is unchanged."""
        if not isinstance(noise, ShotNoise):
            noise = ShotNoise.uniform(noise, self.index.n_markers)
        out = copy.copy(self)
        out.shot_noise = noise
        out.global_fit = self.global_fit.with_gain(noise.join_gain)
        return out

    @property
    def noise(self) -> float:
        """mm per coordinate: the bundles' noise this solver fits (0: exact, the surface through every bundle)."""
        return self.shot_noise.level

    @one_blas_thread
    def solve_frame(self, bundles: np.ndarray, previous: FrameResult | None = None,
                    jaw: np.ndarray | None = None) -> FrameResult:
        """Reconstruct one frame.

        Parameters
        ----------
        bundles : (M, 3) float, cm
            Bundle positions in layout order; rows of NaN are missing markers.
        previous
            The previous frame's result (temporal preference and missing-marker fallback).
        jaw : (4,) float, optional
            The frame's jaw parameters when known (tracked jaw); estimated from the bundles otherwise.
            Used only with an index built with a jaw rig.
        """
        sel = self.select_frame(bundles, previous, jaw)
        return self.blend_frame(sel, *self.blend_slots(sel), sel.jaw)

    @one_blas_thread
    def solve_sequence(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None,
                       show_progress: bool = False, smooth: int = 1, jaw_smooth: int | None = None,
                       jaw: np.ndarray | None = None, max_gap: int = 0,
                       noise: float | str | None = "auto") -> SequenceResult:
        """Reconstruct frames in order, carrying each frame's choice into the next.

        Parameters
        ----------
        bundles
            A :class:`~lgi.capture.bundles.Bundles` (markers matched by name) or an (F, M, 3) array in layout order.
        frames
            Frame numbers for an array input (default 0..F-1).
        smooth : int
            Window (frames, odd) of the central moving average of each bundle's shape weights (paper 7.5);
            1 = none. With a jaw rig the weights are those of the unskinned shapes, so the jaw is not
            smoothed with them. The residual correction is averaged over the same window: each frame's
            blend is moved by the averaged bundle residuals, so bundle noise is not put straight back
            (the diagnostics' ``residual_mm`` says how far the result is from the raw bundles;
            ``residual_before_mm`` is the blend's distance before correction).
        jaw_smooth : int, optional
            Window of the moving average of the jaw parameters (default: ``smooth``).
        jaw : (F, 4) float, optional
            Given jaw parameters per frame (a tracked jaw) instead of estimating them.
        max_gap : int
            Missing runs of a marker up to this many frames are bridged by interpolating its trajectory.
        noise : float (mm), "auto" or None
            The bundles' noise (see the class): "auto" estimates it from the shot's trajectories
            (:func:`lgi.solve.temporal.estimate_noise`; logged, and in ``SequenceResult.noise``), or taken from the
            bundles' covariances when a :class:`~lgi.capture.bundles.Bundles` carries them; None keeps the
            solver's. Noisy trajectories are first smoothed marker by marker
            (:func:`lgi.solve.temporal.denoise_trajectories`, the window chosen by Stein's unbiased risk estimate).
        """
        pos, frames, bridged, shot_noise = self.prepare_shot(bundles, frames, max_gap, noise)
        fit_pos, shot_noise = self.denoise(pos, shot_noise)
        return self.with_noise(shot_noise).solve_prepared(pos, frames, bridged, fit_pos, smooth, jaw_smooth, jaw,
                                                          show_progress)

    @one_blas_thread
    def solve_prepared(self, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray, fit_pos: np.ndarray,
                       smooth: int = 1, jaw_smooth: int | None = None, jaw: np.ndarray | None = None,
                       show_progress: bool = False) -> SequenceResult:
        """:meth:`solve_sequence` of a shot already prepared (:meth:`prepare_shot`, :meth:`denoise`), by the solver
        of its noise (:meth:`with_noise`)."""
        parts = [r for _, _, r in self.stream_prepared(pos, frames, bridged, fit_pos, smooth, jaw_smooth, jaw,
                                                         show_progress, max(len(pos), 1))]
        return parts[0] if len(parts) == 1 else join_results(parts)

    def stream_prepared(self, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray, fit_pos: np.ndarray,
                        smooth: int = 1, jaw_smooth: int | None = None, jaw: np.ndarray | None = None,
                        show_progress: bool = False, block: int = 256) -> Iterator[tuple[int, int, SequenceResult]]:
        """:meth:`solve_prepared` in blocks of ``block`` frames: yields ``(lo, hi, result of frames lo:hi)`` in
        order, the same bits as the whole shot, while holding one block's surfaces (and the choices its smoothing
        reaches) at a time: a long take's memory does not grow with its length."""
        for lo, hi, res, _ in self.stream_from(pos, frames, bridged, fit_pos, smooth, jaw_smooth, jaw, show_progress,
                                               block):
            yield lo, hi, res

    def stream_from(self, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray, fit_pos: np.ndarray,
                    smooth: int = 1, jaw_smooth: int | None = None, jaw: np.ndarray | None = None,
                    show_progress: bool = False, block: int = 256, start: int = 0,
                    carried: tuple[int, list] | None = None
                    ) -> Iterator[tuple[int, int, SequenceResult, tuple[int, list]]]:
        """:meth:`stream_prepared` from frame ``start`` (a multiple of ``block``), each block with what the next
        one reads of it: ``(first, choices)``, the choices (:class:`FrameResult`) of frames ``first`` on. Given back
        as ``carried`` with the next block's ``start``, a run stopped after any block goes on with the same bits."""
        if jaw is not None and len(jaw) != len(pos):
            raise InputError(f"{len(jaw)} jaw parameter rows for {len(pos)} frames")
        if start % block or (start and carried is None):
            raise ValueError(f"a stream resumes at a block's first frame with the choices carried, not at {start}")
        with threadpool_limits(limits=1, user_api="blas"):
            if smooth <= 1 and (jaw_smooth is None or jaw_smooth <= 1 or self.rig is None):
                # Without smoothing each frame can be blended as soon as it is chosen: the choice of the next
                # frame runs beside it, each thread with the one-thread kernels.
                yield from self._stream_unsmoothed(fit_pos, pos, frames, bridged, jaw, show_progress, block, start,
                                                   carried)
            else:
                yield from self._stream_smoothed(fit_pos, pos, frames, bridged, smooth, jaw_smooth, jaw,
                                                 show_progress, block, start, carried)

    @one_blas_thread
    def prepare_shot(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None, max_gap: int = 0,
                     noise: float | str | None = "auto") -> PreparedShot:
        """A shot's positions (F, M, 3) in layout order, frame numbers, bridged mask (F, M) and noise: ``noise``
        (mm) or "auto", resolved (:meth:`resolve_noise`) on the positions as given, or the bundles' covariances
        where they carry them; None keeps the solver's. Gaps are bridged (up to
        ``max_gap`` frames) unless the frames are independent poses rather than a performance: interpolating
        a marker between two unrelated poses would invent a position (a warning says so).

        Bundles read onto disk in the index's marker order (:func:`~lgi.capture.bundles.read_bundles` with
        ``on_disk``) are prepared a block of frames at a time, and the positions returned are on disk too
        (:class:`~lgi.io.stored.ScratchArray`): the same values, in memory that does not grow with the shot."""
        if isinstance(bundles, Bundles) and isinstance(bundles.positions, StoredArray) \
                and bundles.markers == list(self.index.marker_names):
            # Read in the index's marker order onto disk (a long take's): used as it is, a block at a time.
            raw, frames = bundles.positions, np.asarray(bundles.frames)
        else:
            raw, frames, _ = self.prepare(bundles, frames, 0)
        cov = bundles.covariance if isinstance(bundles, Bundles) else None
        if noise == "auto" and cov is not None and all_rows(cov, lambda c: np.isfinite(c).any(axis=(1, 2, 3))).any():
            # The bundles carry their covariances (``lgi track``): the noise is theirs, marker by marker.
            col = {n: i for i, n in enumerate(bundles.markers)}
            per_marker, given = _marker_medians(cov, [col.get(n) for n in self.index.marker_names])
            seen = all_rows(raw, lambda p: np.isfinite(p).all(axis=2))
            bare = seen.any(axis=0) & ~given
            if bare.any():
                names = [self.index.marker_names[i] for i in np.flatnonzero(bare)]
                log.warning("%d markers have positions but no covariance in any frame (%s): they take the median "
                            "marker's noise", len(names), ", ".join(names[:5]) + (" ..." if len(names) > 5 else ""))
            shot_noise = self.noise_from_covariance(per_marker)
            log.info("bundle noise from the bundles' covariances: x %.4f, y %.4f, z %.4f mm (median marker)",
                     *shot_noise.axes)
        elif noise is not None:
            shot_noise = self.resolve_noise(raw, noise)
            if shot_noise.frame_fits is not None:
                shot_noise = dataclasses.replace(shot_noise,
                                                 frame_fits=(np.asarray(frames), *shot_noise.frame_fits[1:]))
        else:
            shot_noise = self.shot_noise
        if max_gap > 0 and shot_noise.independent_poses and not all_rows(raw, lambda p: np.isfinite(p).all(axis=(1, 2))
                                                                   ).all():
            log.warning("missing markers are not bridged: the frames change like independent poses")
            max_gap = 0
        if not isinstance(raw, StoredArray):
            pos, bridged = bridge_gaps(raw, max_gap)
            return PreparedShot(pos, frames, bridged, shot_noise)
        if max_gap <= 0:  # nothing to bridge: the positions on disk are read as they are
            return PreparedShot(raw, frames, np.zeros(raw.shape[:2], bool), shot_noise)
        # A long take's bridged positions go to disk a block at a time.
        pos = ScratchArray(raw.shape, np.float64)
        bridged = np.zeros(raw.shape[:2], bool)
        for lo, hi, filled, was in bridged_blocks(raw, max_gap):
            pos.write(lo, filled)
            bridged[lo:hi] = was
        return PreparedShot(pos, frames, bridged, shot_noise)

    def prepare(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None,
                max_gap: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (F, M, 3) in layout order with short gaps bridged, frame numbers, bridged mask (F, M)."""
        if isinstance(bundles, Bundles):
            pos = self.align(bundles)
            frames = bundles.frames
        else:
            pos = np.asarray(bundles, np.float64)
            frames = np.arange(len(pos)) if frames is None else np.asarray(frames)
        pos, bridged = bridge_gaps(pos, max_gap)
        return pos, np.asarray(frames), bridged

    def align(self, bundles: Bundles) -> np.ndarray:
        """(F, M, 3) positions of a bundles file in this index's marker order (unknown markers rejected)."""
        col = {n: i for i, n in enumerate(bundles.markers)}
        unknown = [n for n in bundles.markers if n not in set(self.index.marker_names)]
        if unknown:
            raise InputError(f"markers not in the index: {unknown[:5]}", marker=unknown[0])
        pos = np.full((len(bundles.frames), self.index.n_markers, 3), np.nan)
        for i, n in enumerate(self.index.marker_names):
            if n in col:
                pos[:, i] = bundles.positions[:, col[n]]
        return pos


#: Markers whose covariances are gathered over the shot at a time (:func:`_marker_medians`): 2.6 MB each per
#: 36,000 frames.
MEDIAN_MARKERS = 16


def _marker_medians(cov, columns: list[int | None]) -> tuple[np.ndarray, np.ndarray]:
    """Each marker's median covariance over the frames (NaN ignored; numpy's ``nanmedian``), and whether any frame
    gives it whole, from ``cov`` (F, K, 3, 3) cm^2 (an array or a :class:`~lgi.io.stored.StoredArray`) whose
    column ``columns[m]`` is marker m (None: not in the file). A few markers' columns at a time: a long take's
    covariances are not held whole.

    Returns
    -------
    (M, 3, 3) float64, cm^2
    (M,) bool
    """

    out = np.full((len(columns), 3, 3), np.nan)
    given = np.zeros(len(columns), bool)
    have = [m for m, c in enumerate(columns) if c is not None]
    for g in range(0, len(have), MEDIAN_MARKERS):
        ms = have[g:g + MEDIAN_MARKERS]
        src = [columns[m] for m in ms]
        part = np.concatenate([np.asarray(cov[lo:hi], np.float64)[:, src] for lo, hi in frame_blocks(len(cov))])
        with warnings.catch_warnings():  # a marker never given: all NaN, filled by the median marker's
            warnings.simplefilter("ignore", RuntimeWarning)
            out[ms] = np.nanmedian(part, axis=0)
        given[ms] = np.isfinite(part).all(axis=(2, 3)).any(axis=0)
    return out, given
