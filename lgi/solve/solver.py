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
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd
import scipy.sparse

from lgi.capture.bundles import Bundles
from lgi.errors import InputError
from lgi.index.build import LGIIndex
from lgi.progress import progress
from lgi.solve._blend_kernels import add_correction, add_correction_serial, blend, blend_on_base, blend_uniform
from lgi.solve._jaw_kernels import skin_points
from lgi.solve._select_kernels import (
    BORROWED,
    CONTAINED,
    MISSING,
    OWN_WEIGHT,
    PROJECTED,
    agreement,
    local_fits,
    local_fits_serial,
    solve_bundles,
    solve_bundles_serial,
)
from lgi.solve.globalfit import GlobalFit, GlobalFitResult, join_gain
from lgi.solve.jaw import PARAM_NAMES, jaw_matrix, smooth_parameters
from lgi.solve.temporal import NoiseEstimate, denoise_trajectories, estimate_noise, sg_matrix
from lgi.threads import one_blas_thread
from lgi.units import MM_PER_CM

# With noisy bundles (noise > 0): the share of the remaining bundle residual the correction removes (none:
# what remains after the fit is mostly the noise).
NOISE_GAIN = 0.0
# A bundle keeps the global weights where they fit it and its neighbours within this RMS (cm; 1 micrometre).
LOCAL_MIN_MISFIT = 1e-4
# Estimated noise below this (mm) is treated as none.
NOISE_FLOOR = 0.05
# Far field (cm of UV-geodesic distance to the nearest bundle): up to the first value every vertex mixes the
# bundles' own weights; beyond the second it takes the frame's global fit; in between a smooth ramp.
FAR_FIELD = (0.5, 1.5)
# A bundle's weights give way to the global fit in the far field where they predict the bundles beyond their
# neighbourhood this many times worse (RMS) than the global fit does (measured on captured-scan datasets: 1
# left the rigged session 12 % above its local-only error, 4 within 5 %, with the scans' extrapolation caught).
FAR_MARGIN = 2.0

log = logging.getLogger(__name__)

# FITTED: a bundle given the global weights without a simplex search: a noisy one (its cloud would be matched
# to the noise), or an exact one that the global fit already meets with its natural neighbours (within
# LOCAL_MIN_MISFIT). The search is the costliest step of a frame.
FITTED = 4
STATUS = {CONTAINED: "contained", PROJECTED: "projected", MISSING: "missing", BORROWED: "neighbour",
          FITTED: "fitted"}


@dataclass
class FrameResult:
    """One reconstructed frame.

    Attributes
    ----------
    vertices : (V, 3) float32, cm
    shapes : (M, 4) int64
        Chosen shapes per bundle (extended index: 0 neutral, k + 1 dataset shape k).
    weights : (M, 4) float64
        Their convex barycentric weights.
    n_containing : (M,) int64
        Simplices that contained the bundle (-1: not searched, noisy bundles).
    status : (M,) int64
        0 contained, 1 projected, 2 missing, 3 neighbour (took a natural neighbour's mixture), 4 fitted
        (noisy bundles: the global fit's weights, no simplex searched; ``projection`` NaN).
    projection : (M,) float64, cm
        Distance from the bundle to where its chosen blend puts it before correction: to its cloud's
        volume when projected, to the neighbour's mixture when borrowed, 0 (or the snap offset) when
        contained.
    score : (M,) float64, cm
        RMS neighbour misfit of the chosen candidate.
    residual : (M,) float64, cm
        Distance from each seen bundle to the reconstructed surface point (NaN if missing).
    fallback : list of str
        For missing bundles: where their choice came from.
    jaw : (4,) float64 or None
        Jaw parameters of the frame (open, yaw, roll in degrees; forward in cm) when the index has a rig.
    bundles : (M, 3) float64 or None
        The bundle positions the frame was solved for.
    residual_before : (M,) float64 or None, cm
        Distance from each bundle to the blended (and, with a rig, skinned) surface before the smooth
        correction: what temporal smoothing or a projection left to correct.
    source : (M,) object or None
        Where each bundle's weights came from: "local fit" or "simplex".
    fit : GlobalFitResult or None
        The frame's global fit (jaw and weights of all shapes) the local fits started from.
    simplex_shapes, simplex_weights : (M, 4) int64 and float64, or None
        The simplex choice of every bundle (carried to the next frame's temporal preference).
    far_share : (M,) float64 or None
        How far each bundle's weights are trusted away from the bundles, as a share given to the global
        fit in the far field (0: the bundle's own geometry extrapolates as well as the global fit, 1: far
        worse; :meth:`LGISolver.far_shares`). None: 1 for every bundle.
    """

    vertices: np.ndarray
    shapes: np.ndarray
    weights: np.ndarray
    n_containing: np.ndarray
    status: np.ndarray
    projection: np.ndarray
    score: np.ndarray
    residual: np.ndarray
    fallback: list[str]
    jaw: np.ndarray | None = None
    bundles: np.ndarray | None = None
    residual_before: np.ndarray | None = None
    source: np.ndarray | None = None
    fit: GlobalFitResult | None = None
    simplex_shapes: np.ndarray | None = None
    simplex_weights: np.ndarray | None = None
    far_share: np.ndarray | None = None


@dataclass
class SequenceResult:
    """A reconstructed sequence: vertices (F, V, 3) float32 cm, frame numbers, per-bundle diagnostics,
    the jaw parameters used (F, 4) when the index has a rig, and each bundle's distance (F, M) cm to the
    blend before the correction (``before``) and to the final surface (``after``; NaN where missing)."""

    frames: np.ndarray
    vertices: np.ndarray
    diagnostics: pd.DataFrame
    jaw: np.ndarray | None = None
    noise: float = 0.0
    smooth: int = 1
    before: np.ndarray | None = None
    after: np.ndarray | None = None


class LGISolver:
    """Reconstruct frames of bundles with a built :class:`~lgi.index.build.LGIIndex`.

    Parameters
    ----------
    index
        The built index.
    temporal_weight : float, mm
        Added to a candidate's score per unit share of its shapes not used by the previous frame's
        choice for the bundle (0 disables; used by :meth:`solve_sequence`).
    alias_min_weight : float
        A candidate's corner tries the shapes merged into its cloud point when its weight is at least this.
    correct_residuals : bool
        Interpolate remaining bundle residuals smoothly so the surface passes through every bundle.
    tolerance : float
        Barycentric tolerance of the containment test.
    n_project : int
        Hull facets tried when projecting a bundle.
    top_k : int
        Containing simplices are pre-screened by their neighbour misfit; this many distinct ones get the
        full score (alias sweep, temporal and agreement terms).
    jaw : "auto" or "none"
        With an index built with a jaw rig: "auto" estimates each frame's jaw parameters from the bundles
        that move with the jaw (or takes them from ``solve_frame(jaw=...)``); "none" is refused for such
        an index (its shapes are unskinned).
    spatial_weight : float, mm
        Weight of a second pass preferring shapes chosen by the bundle's natural neighbours and by the
        whole frame in the first pass; the second pass also lets a bundle take a neighbour's first-pass
        mixture when that keeps the bundle within its snap radius (a bundle that barely moves cannot
        tell its shapes apart, its neighbours can). The default weight is a tie-break: it decides only
        between candidates whose misfits differ by less than about a micrometre. 0 disables
        the second pass.
    method : "local" or "simplex"
        "local" (default): every frame first gets a global fit (bounded shape weights, and the jaw with a
        rig, :class:`~lgi.solve.globalfit.GlobalFit`); then each bundle's weights are refitted locally to the
        bundle and its natural neighbours over the shapes the global fit uses and the shapes of the
        bundle's best containing simplex (so additive combinations outside the cloud's hull are
        reachable), and the simplex candidate is kept where it fits the neighbourhood better.
        "simplex": the paper's choice among containing simplices only (the jaw from the global fit).
    local_prior : float, cm^2
        Ridge of the local fits toward the global weights, per unit weight squared.
    noise : float, mm
        Standard deviation of the bundles' measurement noise per coordinate. 0: the bundles are exact and
        the surface passes through every one of them. Above 0 the bundles are measurements: a sequence's
        trajectories are smoothed first (:meth:`denoise`), every bundle takes the global fit's weights
        (measured: at 0.3 mm the local refits fit the noise, not the face, on every benchmark set) and
        the surface is not pulled onto the bundles.
    far_field : (float, float) or None, cm
        Vertices farther than the first distance from every bundle (UV-geodesic, the natural-neighbour
        metric) blend toward the frame's global fit, reached at the second distance (a smoothstep ramp),
        as far as their bundles' weights predict the bundles beyond their neighbourhood worse than the
        global fit (:meth:`far_shares`). A bundle's local geometry is fitted to the bundle and its natural
        neighbours only; carried past them it can extrapolate, while the global fit is held by every bundle
        (measured on captured datasets: ``docs/indexing.md`` 0b). The global fit's share is not taken
        through the bundles by the residual correction, which only extrapolates that far. Bundles' own
        triangles never blend, so the surface still passes through them. None: the bundles' weights
        everywhere (the paper's blend).
    """

    def __init__(self, index: LGIIndex, temporal_weight: float = 0.0, alias_min_weight: float = 0.1,
                 correct_residuals: bool = True, tolerance: float = 1e-9, n_project: int = 3,
                 spatial_weight: float = 1e-3, top_k: int = 4, jaw: str = "auto", method: str = "local",
                 local_prior: float = 1e-6, noise: float = 0.0,
                 far_field: tuple[float, float] | None = FAR_FIELD) -> None:
        if method not in ("local", "simplex"):
            raise InputError(f"unknown method {method!r}: use 'local' or 'simplex'")
        self.method = method
        self.local_prior = float(local_prior)
        self.noise_estimate: NoiseEstimate | None = None
        self.independent_poses = False
        self.index = index
        a = index.arrays
        self._a = a
        self.temporal_weight = float(temporal_weight)
        self.alias_min_weight = float(alias_min_weight)
        self.correct_residuals = correct_residuals
        self.tolerance = float(tolerance)
        self.n_project = int(n_project)
        self.spatial_weight = float(spatial_weight)
        self.top_k = int(top_k)
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
        self._w_sum: np.ndarray | None = None  # (V,) total blend weight per vertex, for uniform blends
        # Set while a shot is chosen on one thread and blended on another (:meth:`_select_and_finish`): each
        # thread then runs the kernels' one-thread twins, the same bits, so no parallel region is launched from
        # two threads (the "workqueue" threading layer aborts on that) or competes for the two cores.
        self._serial = False
        # The natural-neighbour weights by bundle (CSC), for blending each bundle's own weights over the vertices
        # it reaches (:func:`lgi.solve._blend_kernels.blend_on_base`).
        csc = scipy.sparse.csr_matrix((a["w_data"], a["w_indices"], a["w_indptr"]),
                                      shape=(len(self._x0), index.n_markers)).tocsc()
        csc.sort_indices()
        self._csc_ptr = csc.indptr.astype(np.int64)
        self._csc_vert = csc.indices.astype(np.int64)
        self._csc_w = csc.data.astype(np.float64)
        self._no_ramp = np.zeros(len(self._x0))
        self.far_field = None if far_field is None else (float(far_field[0]), float(far_field[1]))
        self._far = _FarField(a, index.n_markers, self.far_field)
        nb_off, nb_idx = a["nb_off"], a["nb_idx"]
        self._neighbours = [nb_idx[nb_off[i]:nb_off[i + 1]] for i in range(index.n_markers)]
        self._rest = a["ptab"][0]
        self.rig = index.jaw_rig()
        if self.rig is not None and jaw == "none":
            raise InputError("the index was built with a jaw rig (its shapes are unskinned): use jaw 'auto' or "
                             "given parameters, or rebuild the index without a rig")
        self._bundle_w = None
        if self.rig is not None:
            self._skin_w = np.ascontiguousarray(self.rig.weights, np.float64)
            self._bundle_w = self.layout.evaluate(self.rig.weights[:, None])[:, 0]
        self.global_fit = GlobalFit(a["ptab"], self.rig, self._bundle_w)
        self.set_noise(noise)
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

    # ---------------------------------------------------------------------------------- frames
    def select(self, bundles: np.ndarray, previous: FrameResult | None = None, needed: np.ndarray | None = None):
        """Choose each bundle's shapes and weights (no blending).

        ``needed`` (M,) bool: the bundles whose choice is used (all by default); the simplex search runs for
        them and, since their second pass reads their natural neighbours' first choices, for those too.
        The other rows are left unsearched (status MISSING, no shapes, ``n_containing`` 0).

        Returns
        -------
        tuple
            ``(p, seen, shapes, weights, n_containing, status, projection, score, fallback)`` as in
            :class:`FrameResult`, ``p`` the bundles as float64 and ``seen`` (M,) bool.
        """
        a = self._a
        p = np.asarray(bundles, np.float64)
        if p.shape != (self.index.n_markers, 3):
            raise InputError(f"bundles have shape {p.shape}, the index has {self.index.n_markers} markers")
        seen = np.all(np.isfinite(p), axis=1)
        pk = np.where(seen[:, None], p, 0.0)
        prev = previous.shapes if previous is not None else np.full((len(p), 4), -1, np.int64)
        mu = self.temporal_weight / MM_PER_CM if previous is not None else 0.0
        args = (pk, seen, a["dim"], a["origin"], a["basis"], a["pts"], a["pt_off"], a["pt_shape"], a["alias_off"],
                a["class_off"], a["alias_shape"], a["sx"], a["tinv"], a["hull"], a["hull_off"], a["grid_lo"],
                a["grid_h"], a["grid_dims"], a["cell_off"], a["cell_start"], a["cell_items"], a["ptab"],
                a["nb_off"], a["nb_idx"], a["snap_radius"], prev, mu)
        tail = (self.alias_min_weight, self.tolerance, self._dist_tol, self.n_project, self.top_k)
        if needed is None:
            needed = first = np.ones(len(p), bool)
        else:
            # A missing bundle takes a seen neighbour's choice (:meth:`_fill_missing`): those are needed too.
            needed = needed.copy()
            needed[self._pair_j[(needed & ~seen)[self._pair_i]]] = True
            first = needed.copy()
            first[self._pair_j[needed[self._pair_i]]] = True
        search = solve_bundles_serial if self._serial else solve_bundles
        shapes, lam, pts, n_contain, status, proj, score, cand, cand_score = search(
            *args, self._no_agree, 0.0, self._no_shapes, self._no_lam, *tail, self._scan, self._no_scores,
            self._no_first, first)
        if self.spatial_weight > 0:
            # Second pass: break near-ties toward the shapes the neighbours and the frame agree on.
            agree = agreement(pts, lam, seen, a["alias_off"], a["class_off"], a["alias_shape"], a["nb_off"],
                                a["nb_idx"], self._n_ext)
            # Bundles with no containing simplex in the first pass scan again (their projection).
            cand[cand[:, 0] < 0] = -2
            shapes, lam, pts, n_contain, status, proj, score, _, _ = search(
                *args, agree, self.spatial_weight / MM_PER_CM, shapes, lam, *tail, cand, cand_score,
                np.nan_to_num(score, nan=np.inf), needed)
        fallback = self._fill_missing(seen, shapes, lam, previous)
        return p, seen, shapes, lam, n_contain, status, proj, score, fallback

    def correct(self, x: np.ndarray, p: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """Take surface ``x`` (V, 3) through the seen bundles (in place); returns the residuals (M,) cm."""
        a = self._a
        resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)
        if self.correct_residuals:
            for _ in range(3):  # the stored basis is truncated: reapplying it removes what is left
                # 1e-7 cm is a hundredth of the 1e-4 mm a bundle may be off the surface.
                fix = np.flatnonzero(np.abs(resid_vec).max(axis=1) > 1e-7)
                if not fix.size:
                    break
                self._add_correction(x, a["corr_indptr"], a["corr_indices"], a["corr_data"], fix, resid_vec[fix])
                resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)
        return np.where(seen, np.linalg.norm(resid_vec, axis=1), np.nan)

    def estimate_jaw(self, bundles: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """(4,) jaw parameters of a frame, fitted with the shape weights to all its bundles."""
        start = None if init is None else GlobalFitResult(np.zeros(0), np.asarray(init, np.float64), np.zeros(0), 0.0)
        return self.global_fit.solve(bundles, init=start).jaw

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

    def select_frame(self, bundles: np.ndarray, previous: FrameResult | None = None,
                     jaw: np.ndarray | None = None) -> FrameResult:
        """Choose shapes and weights (unskinning the bundles first with a jaw rig); no vertices yet."""
        p = np.asarray(bundles, np.float64)
        if p.shape != (self.index.n_markers, 3):
            raise InputError(f"bundles have shape {p.shape}, the index has {self.index.n_markers} markers")
        seen = np.all(np.isfinite(p), axis=1)
        if not seen.any():
            raise InputError("no marker seen in this frame")
        fit = self.global_fit.solve(p, jaw=jaw, init=None if previous is None else previous.fit)
        theta = fit.jaw
        q = p
        if self.rig is not None:
            q = p.copy()
            q[seen] = self.rig.unskin(p[seen], theta, self._bundle_w[seen])
        if self.method == "local" and self.noise > 0:
            m = len(p)
            shapes, lam, score, source, fallback = self._global(q, seen, fit)
            return FrameResult(np.zeros((0, 3), np.float32), shapes, lam, np.full(m, -1, np.int64),
                               np.where(seen, FITTED, MISSING).astype(np.int64), np.full(m, np.nan), score,
                               np.where(seen, 0.0, np.nan), fallback, theta, p, None, source, fit,
                               np.zeros((m, 4), np.int64), np.zeros((m, 4)))
        prev_simplex = None
        if previous is not None:
            # A bundle the global fit met had no simplex searched: no temporal preference from it.
            prev_shapes = np.where((previous.status == FITTED)[:, None], -1, previous.simplex_shapes)
            prev_simplex = FrameResult(previous.vertices, prev_shapes, previous.simplex_weights,
                                       previous.n_containing, previous.status, previous.projection, previous.score,
                                       previous.residual, previous.fallback)
        keep = global_score = None
        if self.method == "local":
            # Where the global weights already fit a bundle's neighbourhood it keeps them (see :meth:`_local`),
            # so its simplex would go unused: only the other bundles are searched.
            global_score = self._shared_misfits(q, seen, fit.weights)
            keep = global_score <= LOCAL_MIN_MISFIT
        q, seen, shapes, lam, n_contain, status, proj, score, fallback = self.select(
            q, prev_simplex, None if keep is None else ~keep)
        if keep is not None:
            met = keep & seen
            status[met] = FITTED
            n_contain[met] = -1
            proj[met] = np.nan
            shapes[met] = 0
            lam[met] = 0.0
        simplex_shapes, simplex_weights = shapes.copy(), lam.copy()
        source = np.full(len(p), "simplex", object)
        if self.method == "local":
            shapes, lam, score, source, fallback = self._local(q, seen, fit, shapes, lam, score, fallback,
                                                               global_score)
        share = None
        if self._far.active:
            dense = np.zeros((len(p), self.global_fit.n_shapes + 1))
            np.add.at(dense, (np.repeat(np.arange(len(p)), shapes.shape[1]), shapes.ravel()), lam.ravel())
            share = self.far_shares(q, seen, dense[:, 1:], fit.weights)
        return FrameResult(np.zeros((0, 3), np.float32), shapes, lam, n_contain, status, proj, score,
                           np.where(seen, 0.0, np.nan), fallback, theta, p, None, source, fit, simplex_shapes,
                           simplex_weights, share)

    def _misfits(self, q: np.ndarray, seen: np.ndarray, w: np.ndarray, rows: np.ndarray | None = None
                 ) -> np.ndarray:
        """(M,) RMS misfit (cm) of each bundle's weights ``w`` (M, S) at the bundle (weight OWN_WEIGHT) and its
        seen natural neighbours, in the index's (unskinned) space; the simplex candidates' score. With ``rows``
        (M,) bool, only those bundles are scored (the others are NaN)."""
        i, j = self._pair_i, self._pair_j
        ok = seen[j] if rows is None else seen[j] & rows[i]
        i, j, cw = i[ok], j[ok], self._pair_w[ok]
        used = np.flatnonzero(np.any(w != 0, axis=0))  # tens of shapes out of hundreds
        pred = self._rest[j] + np.einsum("ek,kec->ec", w[i][:, used], self._basis[used][:, j])
        d2 = np.sum((pred - q[j]) ** 2, axis=1)
        tot = np.bincount(i, cw * d2, minlength=len(q))
        cnt = np.bincount(i, cw, minlength=len(q))
        out = np.sqrt(tot / np.maximum(cnt, 1e-300))
        if rows is not None:
            out[~rows] = np.nan
        return out

    def _shared_misfits(self, q: np.ndarray, seen: np.ndarray, w: np.ndarray) -> np.ndarray:
        """:meth:`_misfits` of one weight vector ``w`` (S,) shared by every bundle: one prediction."""
        nz = np.flatnonzero(w)
        pred = self._rest + np.tensordot(w[nz], self._basis[nz], axes=1)
        i, j = self._pair_i, self._pair_j
        ok = seen[j]
        i, j, cw = i[ok], j[ok], self._pair_w[ok]
        d2 = np.sum((pred[j] - q[j]) ** 2, axis=1)
        m = len(q)
        return np.sqrt(np.bincount(i, cw * d2, minlength=m) / np.maximum(np.bincount(i, cw, minlength=m), 1e-300))

    def _global(self, q: np.ndarray, seen: np.ndarray, fit: GlobalFitResult):
        """Every bundle takes the global fit's weights (noisy bundles: local refits would fit the noise)."""
        m = len(q)
        nz = np.flatnonzero(fit.weights > 0)
        k = max(1, len(nz))
        out_s = np.zeros((m, k), np.int64)
        out_w = np.zeros((m, k))
        out_s[:, :len(nz)] = nz + 1
        out_w[:, :len(nz)] = fit.weights[nz]
        notes = [("global fit" if not seen[i] else "") for i in range(m)]
        score = self._shared_misfits(q, seen, fit.weights)
        return out_s, out_w, score, np.full(m, "global fit", object), notes

    def _local(self, q: np.ndarray, seen: np.ndarray, fit: GlobalFitResult, shapes: np.ndarray, lam: np.ndarray,
               score: np.ndarray, fallback: list[str], global_score: np.ndarray | None = None):
        """Local fits (see ``method``); returns shapes and weights as slots (M, K), scores, sources, notes.
        ``global_score`` (M,) cm: :meth:`_shared_misfits` of the global weights, when already computed."""
        m, n_s = len(q), self.global_fit.n_shapes
        wg = fit.weights
        # Where the global weights already fit the neighbourhood, a local refit could only move shapes the
        # bundles do not see (eyes, the lateral border): keep the global weights. Most bundles of a frame the
        # dataset spans do, and only the others need a local fit and the candidates' scores.
        if global_score is None:
            global_score = self._shared_misfits(q, seen, wg)
        keep = global_score <= LOCAL_MIN_MISFIT
        todo = ~keep
        support = np.flatnonzero(wg > 1e-9)
        # Each bundle's columns: the global support with its simplex's shapes (sorted, distinct).
        ext = np.where((lam > 0) & (shapes > 0) & todo[:, None], shapes - 1, -1)
        in_support = np.zeros(n_s + 1, bool)
        in_support[support + 1] = True
        ext = np.where(in_support[ext + 1], -1, ext)
        ext.sort(axis=1)
        ext = np.where(np.concatenate([np.zeros((m, 1), bool), ext[:, 1:] == ext[:, :-1]], axis=1), -1, ext)
        n_ext = (ext >= 0).sum(axis=1)
        counts = np.where(todo, len(support) + n_ext, 0)
        col_off = np.zeros(m + 1, np.int64)
        col_off[1:] = np.cumsum(counts)
        flat = np.empty(col_off[-1], np.int64)
        for i in np.flatnonzero(todo):
            c = np.concatenate([support, ext[i][ext[i] >= 0]])
            c.sort()
            flat[col_off[i]:col_off[i + 1]] = c
        resid = np.where(seen[:, None], q - self._rest - np.tensordot(wg[wg != 0], self._basis[wg != 0], axes=1), 0.0)
        w_local = np.empty((m, n_s))
        beta = np.full(m, self.local_prior)
        fits = local_fits_serial if self._serial else local_fits
        fits(resid, seen, self._basis, self._a["nb_off"], self._a["nb_idx"], col_off, flat, wg, beta, OWN_WEIGHT,
             w_local)
        local_score = self._misfits(q, seen, w_local, todo)
        # The simplex candidate's weights as a full vector, to compare like with like.
        w_simplex = np.zeros((m, n_s + 1))
        np.add.at(w_simplex, (np.repeat(np.arange(m), shapes.shape[1]), shapes.ravel()), lam.ravel())
        simplex_score = self._misfits(q, seen, w_simplex[:, 1:], todo)
        # A simplex passes exactly through its bundle: with noisy bundles that is fitting the noise, so
        # the simplex candidate competes only with exact bundles.
        use_local = ~(seen & (simplex_score < local_score)) if self.noise == 0 else np.ones(m, bool)
        chosen = np.where(use_local[:, None], w_local, w_simplex[:, 1:])
        source = np.where(use_local, "local fit", "simplex").astype(object)
        chosen[keep] = wg
        source[keep] = "global fit"
        local_score = np.where(keep, global_score, local_score)
        use_local |= keep
        notes = list(fallback)
        for i in np.flatnonzero(~seen):
            n_nb = int(seen[self._neighbours[i]].sum())
            notes[i] = f"fitted to {n_nb} seen natural neighbours" if n_nb else "global fit"
        nz = chosen > 0
        k = max(1, int(nz.sum(1).max()))
        # Each row's nonzero shapes first, in shape order (a stable sort on "is zero").
        order = np.argsort(~nz, axis=1, kind="stable")[:, :k]
        taken = np.take_along_axis(nz, order, axis=1)
        out_s = np.where(taken, order + 1, 0).astype(np.int64)
        out_w = np.where(taken, np.take_along_axis(chosen, order, axis=1), 0.0)
        return out_s, out_w, np.where(use_local, local_score, simplex_score), source, notes

    def surface(self, shapes: np.ndarray, weights: np.ndarray, jaw: np.ndarray | None,
                far_share: np.ndarray | None = None) -> np.ndarray:
        """(V, 3) float64: the natural-neighbour blend of the bundles' shapes, skinned when there is a rig.

        ``shapes``, ``weights``: (M, K) slots per bundle, or (M + 1, K) with the frame's global fit last
        (:meth:`blend_slots`), which the far field blends toward with the bundles' far shares ``far_share``
        (M,) (:meth:`far_shares`; default: every bundle's share 1)."""
        a = self._a
        x = np.empty_like(self._x0)
        if (shapes == shapes[0]).all() and (weights == weights[0]).all():
            # Every bundle has the same weights (noisy bundles: the global fit's): no per-vertex mixing.
            blend_uniform(self._x0.reshape(-1), self._deltas_flat, self._blend_w_sum(),
                            shapes[0], weights[0], x.reshape(-1))
        elif len(shapes) == self.index.n_markers + 1:
            # The last row is the global fit's, which the far field blends toward. Most bundles of an exact
            # frame keep the global weights too: blend that row once over the mesh and, per vertex, only the
            # other bundles' differences from it (12.5 -> 1.6 ms per frame at 500 ICT shapes).
            m = self.index.n_markers
            if self._far.active:
                ramp = self._far.r
                share = np.ones(m) if far_share is None else np.clip(np.asarray(far_share, np.float64), 0.0, 1.0)
            else:
                ramp, share = self._no_ramp, np.zeros(m)
            d_shapes, d_lam = _differences(shapes, weights)
            rows = np.flatnonzero(d_lam[:m, 0] != 0)
            blend_on_base(self._x0.reshape(-1), self._deltas_flat, shapes[-1], weights[-1], self._blend_w_sum(),
                            self._csc_ptr, self._csc_vert, self._csc_w, ramp, share, rows, d_shapes, d_lam,
                            x.reshape(-1))
        else:
            blend(self._x0, self._deltas, a["w_indptr"], a["w_indices"], a["w_data"], shapes[:self.index.n_markers],
                    weights[:self.index.n_markers], x)
        if self.rig is not None:
            skin_points(x, self._skin_w, np.ascontiguousarray(jaw_matrix(jaw, self.rig.pivot)[:3]), x)
        return x

    def _add_correction(self, *args) -> None:
        (add_correction_serial if self._serial else add_correction)(*args)

    def _blend_w_sum(self) -> np.ndarray:
        """(V,) each vertex's total natural-neighbour weight (1 where bundles reach, 0 elsewhere)."""
        if self._w_sum is None:
            a = self._a
            self._w_sum = np.add.reduceat(np.r_[a["w_data"], 0.0], a["w_indptr"][:-1]) * (np.diff(a["w_indptr"]) > 0)
        return self._w_sum

    def far_global_share(self, share: np.ndarray | None) -> np.ndarray:
        """(V,) the far field's share t of the global fit per vertex, given the bundles' far shares (M,) (None:
        all 1): a vertex at ramp r (:class:`_FarField`) keeps ``N_vb (1 - r s_b)`` of bundle b's weights and gives
        ``t = r sum_b N_vb s_b`` to the global fit."""
        return self._far.global_share(share)

    def far_shares(self, q: np.ndarray, seen: np.ndarray, weights: np.ndarray, global_weights: np.ndarray
                   ) -> np.ndarray:
        """(M,) each bundle's far share: how much worse its weights predict the seen bundles of its second
        ring of natural neighbours (not fitted to them) than the global fit's do.

        With ``e_b`` its RMS misfit there and ``g_b`` the global fit's, the share is
        ``(e_b^2 - c g_b^2) / (e_b^2 + c g_b^2)`` clipped to [0, 1], ``c = FAR_MARGIN^2``: 0 unless the bundle's
        weights miss the ring clearly worse than the global fit (which was fitted to it), near 1 where the
        bundle's geometry leaves its neighbourhood (a captured scan that fits a bundle's neighbours and not the
        face beyond).

        Parameters
        ----------
        q : (M, 3) float, cm
            Bundles (unskinned with a rig); rows of unseen ones are ignored.
        seen : (M,) bool
        weights : (M, S) float
            Each bundle's shape weights.
        global_weights : (S,) float
        """
        i, j = self._ring_i, self._ring_j
        ok = seen[j]
        i, j = i[ok], j[ok]
        used = np.flatnonzero(np.any(weights != 0, axis=0))
        pred = self._rest[j] + np.einsum("ek,kec->ec", weights[i][:, used], self._basis[used][:, j])
        d_own = np.sum((pred - q[j]) ** 2, axis=1)
        g = global_weights != 0
        glob = self._rest + np.tensordot(global_weights[g], self._basis[g], axes=1)
        d_glob = np.sum((glob[j] - q[j]) ** 2, axis=1)
        cnt = np.maximum(np.bincount(i, minlength=len(q)), 1)
        e2 = np.bincount(i, d_own, minlength=len(q)) / cnt
        g2 = np.bincount(i, d_glob, minlength=len(q)) / cnt
        # The global fit was fitted to the ring, the bundle's weights were not: the global fit takes a share
        # only where the bundle's weights miss the ring by more than FAR_MARGIN times its RMS misfit.
        c = FAR_MARGIN**2
        return np.clip((e2 - c * g2) / (e2 + c * g2 + 1e-12), 0.0, 1.0)

    def blend_slots(self, sel: FrameResult) -> tuple[np.ndarray, np.ndarray]:
        """A frame's slots for :meth:`surface`: the bundles' (M, K), and the global fit's weights as one more
        row (the far field's, and the base the bundles' weights are blended as differences from)."""
        if sel.fit is None:
            return sel.shapes, sel.weights
        shapes, weights = _append_rows([sel.shapes], [sel.weights], [sel.fit.weights])
        return shapes[0], weights[0]

    def correct_far(self, x: np.ndarray, resid: np.ndarray, seen: np.ndarray, gain: float,
                    t: np.ndarray | None) -> None:
        """Leave the far field's share of the global fit uncorrected (in place): :meth:`correct` took ``x``
        through the bundles by the smooth field of the blend's residuals ``resid`` (M, 3); where the far field
        gives the global fit the share t (V,), that share of the field is taken off again, so those vertices
        are the global fit's surface as it is. The field carries what the bundles' local geometry left to
        meet them; far from them it is an extrapolation (measured: with it the far vertices of the rigged
        synthetic set were at 0.124 mm max against the global fit's 0.081). t is 0 at the bundles, which are
        still met exactly."""
        if t is None or not self.correct_residuals or gain == 0 or not t.any():
            return
        d = np.where(seen[:, None], -np.nan_to_num(resid), 0.0) * gain
        fix = np.flatnonzero(np.abs(d).max(axis=1) > 1e-7)
        if not fix.size:
            return
        a = self._a
        y = np.zeros_like(x)
        self._add_correction(y, a["corr_indptr"], a["corr_indices"], a["corr_data"], fix, d[fix])
        x += t[:, None] * y

    def blend_frame(self, sel: FrameResult, shapes: np.ndarray, weights: np.ndarray,
                    jaw: np.ndarray | None, bundles: np.ndarray | None = None) -> FrameResult:
        """Vertices for chosen (possibly smoothed) shapes and weights, skinned and taken through the bundles.

        ``bundles`` are the positions to pass through (default: those the selection was made for).
        """
        t = self.far_global_share(sel.far_share) if len(shapes) == self.index.n_markers + 1 and self._far.active \
            else None
        x = self.surface(shapes, weights, jaw, sel.far_share)
        p = sel.bundles if bundles is None else np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        at = self.layout.evaluate(x)
        before = np.where(seen, np.linalg.norm(np.where(seen[:, None], p, 0) - at, axis=1), np.nan)
        self.correct(x, at + self.noise_gain * (p - at), seen)
        self.correct_far(x, p - at, seen, self.noise_gain, t)
        residual = np.where(seen, np.linalg.norm(np.nan_to_num(p) - self.layout.evaluate(x), axis=1), np.nan)
        return dataclasses.replace(sel, vertices=x.astype(np.float32), residual=residual, jaw=jaw, bundles=p,
                                   residual_before=before)

    def _fill_missing(self, seen: np.ndarray, shapes: np.ndarray, lam: np.ndarray,
                      previous: FrameResult | None) -> list[str]:
        notes = [""] * len(seen)
        missing = np.flatnonzero(~seen)
        if missing.size == 0:
            return notes
        if not seen.any():
            raise InputError("no marker seen in this frame")
        seen_idx = np.flatnonzero(seen)
        for i in missing:
            if previous is not None:
                shapes[i], lam[i] = previous.shapes[i], previous.weights[i]
                notes[i] = "previous frame"
                continue
            nbs = [j for j in self._neighbours[i] if seen[j]]
            if nbs:
                j = min(nbs, key=lambda j: np.linalg.norm(self._rest[j] - self._rest[i]))
                notes[i] = f"neighbour {self.index.marker_names[j]}"
            else:
                j = seen_idx[np.argmin(np.linalg.norm(self._rest[seen_idx] - self._rest[i], axis=1))]
                notes[i] = f"nearest seen {self.index.marker_names[j]}"
            shapes[i], lam[i] = shapes[j], lam[j]
        return notes

    # ---------------------------------------------------------------------------------- sequences
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
            (:func:`lgi.solve.temporal.estimate_noise`; logged, and in ``SequenceResult.noise``); None keeps the
            solver's. Noisy trajectories are first smoothed marker by marker
            (:func:`lgi.solve.temporal.denoise_trajectories`, the window chosen by Stein's unbiased risk estimate).
        """
        pos, frames, bridged = self.prepare_shot(bundles, frames, max_gap, noise)
        return self.solve_prepared(pos, frames, bridged, self.denoise(pos), smooth, jaw_smooth, jaw, show_progress)

    @one_blas_thread
    def solve_prepared(self, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray, fit_pos: np.ndarray,
                       smooth: int = 1, jaw_smooth: int | None = None, jaw: np.ndarray | None = None,
                       show_progress: bool = False) -> SequenceResult:
        """:meth:`solve_sequence` of a shot already prepared (:meth:`prepare_shot`, :meth:`denoise`)."""
        if jaw is not None and len(jaw) != len(pos):
            raise InputError(f"{len(jaw)} jaw parameter rows for {len(pos)} frames")
        if smooth <= 1 and (jaw_smooth is None or jaw_smooth <= 1 or self.rig is None):
            # Without smoothing each frame can be blended as soon as it is chosen: the choice of the next frame
            # runs beside it, each thread with the one-thread kernels.
            return self._select_and_finish(fit_pos, pos, frames, bridged, jaw, show_progress)
        sels = self.select_sequence(fit_pos, frames, jaw, show_progress)
        return self.finish_sequence(sels, pos, frames, bridged, smooth, jaw_smooth, show_progress, fit_pos)

    def denoise(self, positions: np.ndarray) -> np.ndarray:
        """The positions the frames are fitted to: with noisy bundles (``noise`` > 0) each marker's trajectory
        smoothed by :func:`lgi.solve.temporal.denoise_trajectories`; the noise left after it sets the local fits'
        prior. Exact bundles are returned as they are."""
        self.denoise_windows = None
        self._fit_noise = self.noise
        self.global_fit.gain = join_gain(self.noise)
        if self.noise <= 0:
            return positions
        out, windows = denoise_trajectories(positions, self.noise)
        self.denoise_windows = windows
        # The noise left at a frame is the filter's middle coefficient (its own weight) times the noise.
        c0 = np.array([sg_matrix(w)[w // 2, w // 2] for w in np.unique(windows)])
        share = np.array([(windows == w).mean() for w in np.unique(windows)])
        self._fit_noise = self.noise * float(np.sqrt(share @ c0))
        self.global_fit.gain = join_gain(self._fit_noise)
        log.info("noisy bundles smoothed over %d-%d frames (median %d): about %.3f mm noise left", windows.min(),
                 windows.max(), int(np.median(windows)), self._fit_noise)
        return out

    def prepare_shot(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None, max_gap: int = 0,
                     noise: float | str | None = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A shot's positions (F, M, 3) in layout order, frame numbers and bridged mask (F, M), with the
        solver's noise resolved (:meth:`resolve_noise`) on the positions as given. Gaps are bridged (up to
        ``max_gap`` frames) unless the frames are independent poses rather than a performance: interpolating
        a marker between two unrelated poses would invent a position (a warning says so)."""
        from lgi.solve.temporal import bridge_gaps

        raw, frames, _ = self.prepare(bundles, frames, 0)
        if noise is not None:
            self.resolve_noise(raw, noise)
        if max_gap > 0 and self.independent_poses and not np.all(np.isfinite(raw)):
            log.warning("missing markers are not bridged: the frames change like independent poses")
            max_gap = 0
        pos, bridged = bridge_gaps(raw, max_gap)
        return pos, frames, bridged

    def set_noise(self, noise_mm: float) -> None:
        """Treat the bundles as exact (0) or as measurements with this noise (mm per coordinate)."""
        if not np.isfinite(noise_mm) or noise_mm < 0:
            raise InputError(f"noise must be a finite number of mm >= 0, not {noise_mm}")
        self.noise = float(noise_mm)
        self._fit_noise = self.noise
        self.global_fit.gain = join_gain(self.noise)
        self.noise_gain = NOISE_GAIN if self.noise > 0 else 1.0

    def resolve_noise(self, positions: np.ndarray, noise: float | str = "auto") -> NoiseEstimate | None:
        """Set the solver's noise for a shot (F, M, 3): a given value (mm) or "auto", estimated from the
        shot. Below ``NOISE_FLOOR`` mm, or where the frame-to-frame changes are not noise (neighbouring
        markers change together: independent poses rather than a performance), the bundles are exact.
        Returns the estimate (None for a given value); the decision is logged."""
        if noise != "auto":
            try:
                value = float(noise)
            except (TypeError, ValueError):
                raise InputError(f"noise must be a number of mm or 'auto', not {noise!r}") from None
            self.set_noise(value)
            self.noise_estimate = None
            self.independent_poses = False
            return None
        est = estimate_noise(positions, self._nb_pairs)
        self.noise_estimate = est
        self.independent_poses = bool(np.isfinite(est.noise_mm) and est.noise_mm >= NOISE_FLOOR and not est.is_noise)
        if not np.isfinite(est.noise_mm):
            # A fallback the user must hear of: noisy bundles taken as exact make a surface that chases the noise.
            log.warning("the bundle noise cannot be estimated (no marker is seen for 7 frames in a row): bundles "
                        "treated as exact; give --noise MM if they are not")
            self.set_noise(0.0)
        elif est.noise_mm < NOISE_FLOOR:
            log.info("bundle noise estimated at %.3f mm (below %.2f mm): bundles treated as exact", est.noise_mm,
                     NOISE_FLOOR)
            self.set_noise(0.0)
        elif not est.is_noise:
            log.warning("the bundles change from frame to frame by %.3f mm (median, per coordinate) but neighbouring "
                        "markers change together (correlation %.2f): that is motion (independent poses?), not "
                        "measurement noise, so the bundles are treated as exact; give the noise if they are "
                        "measurements", est.noise_mm, est.coherence)
            self.set_noise(0.0)
        else:
            log.info("bundle noise estimated at %.3f mm per coordinate (%d residuals, neighbour correlation %.2f): "
                     "bundles treated as measurements", est.noise_mm, est.samples, est.coherence)
            self.set_noise(est.noise_mm)
        return est

    def prepare(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None,
                max_gap: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (F, M, 3) in layout order with short gaps bridged, frame numbers, bridged mask (F, M)."""
        from lgi.solve.temporal import bridge_gaps

        if isinstance(bundles, Bundles):
            pos = self.align(bundles)
            frames = bundles.frames
        else:
            pos = np.asarray(bundles, np.float64)
            frames = np.arange(len(pos)) if frames is None else np.asarray(frames)
        pos, bridged = bridge_gaps(pos, max_gap)
        return pos, np.asarray(frames), bridged

    @one_blas_thread
    def select_sequence(self, pos: np.ndarray, frames: np.ndarray, jaw: np.ndarray | None = None,
                        show_progress: bool = False,
                        emit: Callable[[int, FrameResult], None] | None = None,
                        previous: FrameResult | None = None) -> list[FrameResult]:
        """Each frame's choice of shapes and weights, in order (the previous frame's carried into the next);
        ``emit(f, choice)`` is called with each as it is made. ``previous``: the choice of the frame before
        ``pos[0]`` when a shot is chosen in chunks (the result is then the one a single call gives)."""
        sels = []
        prev = previous
        for f in progress(range(len(pos)), "choosing shapes", disable=not show_progress):
            try:
                prev = self.select_frame(pos[f], prev, None if jaw is None else jaw[f])
            except InputError as exc:
                raise InputError(exc.message, frame=int(frames[f])) from None
            sels.append(prev)
            if emit is not None:
                emit(f, prev)
        return sels

    def _select_and_finish(self, fit_pos: np.ndarray, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                           jaw: np.ndarray | None, show_progress: bool) -> SequenceResult:
        """:meth:`select_sequence` then :meth:`finish_sequence` without temporal smoothing, on two threads: the
        choice of frame f + 1 (its kernels compiled without the GIL) runs while frame f is blended. Each frame's
        choice still follows the previous one's in order, and the one-thread kernels give the parallel ones'
        bits, so the result is the one the two calls in turn give (tested); only the wall time changes."""
        import queue
        import threading

        chosen: queue.Queue = queue.Queue(maxsize=16)
        stop = threading.Event()

        class _Stopped(Exception):
            pass

        def put(item: tuple) -> None:
            # Never blocks for good: once the consumer has stopped (it failed or was interrupted), give up.
            while not stop.is_set():
                try:
                    chosen.put(item, timeout=0.1)
                    return
                except queue.Full:
                    continue
            raise _Stopped

        def produce() -> None:
            try:
                self.select_sequence(fit_pos, frames, jaw, False, lambda f, sel: put((f, sel)))
            except _Stopped:
                return
            except BaseException as exc:  # handed to the consumer, which raises it
                try:
                    put((-1, exc))
                except _Stopped:
                    return

        worker = threading.Thread(target=produce, name="lgi-select", daemon=True)
        fin = _Finisher(self, pos, fit_pos)
        sels: list[FrameResult] = []
        self._serial = True
        worker.start()
        try:
            for _ in progress(range(len(pos)), "reconstructing", disable=not show_progress):
                f, sel = chosen.get()
                if f < 0:
                    raise sel
                sels.append(sel)
                fin.frame(f, *self.blend_slots(sel), sel.jaw, sel.far_share)
        finally:
            stop.set()
            worker.join()
            self._serial = False
        thetas = None if self.rig is None else np.stack([s.jaw for s in sels]).astype(np.float64)
        diag = self._diagnostics(sels, frames, bridged, fin.before, fin.r_final, thetas)
        return SequenceResult(np.asarray(frames), fin.out, diag, thetas, self.noise, 1, fin.before, fin.r_final)

    @one_blas_thread
    def finish_sequence(self, sels: list[FrameResult], pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                        smooth: int = 1, jaw_smooth: int | None = None,
                        show_progress: bool = False, fit_pos: np.ndarray | None = None,
                        lo: int = 0, hi: int | None = None) -> SequenceResult:
        """Smooth the choices over time, blend, skin and correct every frame; diagnostics per bundle.

        ``pos`` are the bundles as given (the diagnostics' residuals are measured to them); ``fit_pos`` the
        positions the frames were fitted to (denoised, :meth:`denoise`), which the correction aims at.
        ``sels``, ``pos``, ``frames`` and ``bridged`` cover the whole shot; only frames ``lo:hi`` are finished
        and returned. A frame's result depends only on the frames in its smoothing windows, each computed on
        its own, so finishing a shot in any ranges gives the same bits as finishing it whole (tested)."""
        fit_pos = pos if fit_pos is None else fit_pos
        from lgi.solve.temporal import moving_average, window_slots

        n_f = len(sels)
        hi = n_f if hi is None else hi
        if all(r.fit is not None for r in sels):
            shapes, lam = _append_rows([r.shapes for r in sels], [r.weights for r in sels],
                                       [r.fit.weights for r in sels])
        else:
            shapes, lam = _stack_slots([r.shapes for r in sels], [r.weights for r in sels])
        thetas = None
        if self.rig is not None:
            thetas = smooth_parameters(np.stack([r.jaw for r in sels]), smooth if jaw_smooth is None else jaw_smooth)
        shares = np.stack([np.ones(self.index.n_markers) if r.far_share is None else r.far_share for r in sels])
        if smooth > 1:
            shapes, lam = window_slots(shapes, lam, smooth)
            shares = moving_average(shares, smooth)
        # With smoothing, a frame's correction averages the residuals of its window: those frames are blended too.
        a, b = (max(0, lo - smooth // 2), min(n_f, hi + smooth // 2)) if smooth > 1 else (lo, hi)
        fin = _Finisher(self, pos[a:b], fit_pos[a:b])
        if smooth > 1:
            # The correction follows the same moving average: corrected to each frame's raw residuals, the
            # surface would carry the bundles' noise straight back. So every surface is blended first.
            blends = [fin.blend(f - a, shapes[f], lam[f], None if thetas is None else thetas[f], shares[f])
                      for f in progress(range(a, b), "blending", disable=not show_progress)]
            resid = np.stack([r for _, r, _ in blends])
            fin.before[:] = np.linalg.norm(resid, axis=2)
            resid = moving_average(resid, smooth)
            for f in range(lo, hi):
                fin.finish(f - a, blends[f - a][0], resid[f - a], blends[f - a][2])
        else:
            for f in progress(range(lo, hi), "blending", disable=not show_progress):
                fin.frame(f - a, shapes[f], lam[f], None if thetas is None else thetas[f], shares[f])
        keep = slice(lo - a, hi - a)
        th = None if thetas is None else thetas[lo:hi]
        diag = self._diagnostics(sels[lo:hi], np.asarray(frames)[lo:hi], bridged[lo:hi], fin.before[keep],
                                 fin.r_final[keep], th)
        out = fin.out if (a, b) == (lo, hi) else fin.out[keep].copy()
        return SequenceResult(np.asarray(frames)[lo:hi], out, diag, th, self.noise, smooth, fin.before[keep],
                              fin.r_final[keep])

    def _diagnostics(self, sels: list[FrameResult], frames: np.ndarray, bridged: np.ndarray, before: np.ndarray,
                     r_final: np.ndarray, thetas: np.ndarray | None) -> pd.DataFrame:
        """One row per frame and bundle (the columns of ``diagnostics.csv``), built column by column."""
        n_f, n_m = len(sels), self.index.n_markers
        names = np.asarray(self.index.marker_names, object)
        all_shapes, all_weights = _stack_slots([s.shapes for s in sels], [s.weights for s in sels])
        shape_col, weight_col = slot_labels(all_shapes.reshape(n_f * n_m, -1), all_weights.reshape(n_f * n_m, -1),
                                            self.index.shape_names)
        status = np.empty((n_f, n_m), object)
        note = np.empty((n_f, n_m), object)
        source = np.empty((n_f, n_m), object)
        status_names = np.array([STATUS.get(k, "?") for k in range(max(STATUS) + 1)], object)
        for f, sel in enumerate(sels):
            note[f] = sel.fallback
            status[f] = np.where(np.asarray(sel.fallback, object) != "", "missing", status_names[sel.status])
            source[f] = "simplex" if sel.source is None else sel.source
        status[bridged] = "bridged"
        note[bridged] = "interpolated between the frames around the gap"

        def stack(get: Callable[[FrameResult], np.ndarray | float]) -> np.ndarray:
            return np.stack([np.broadcast_to(np.asarray(get(s), np.float64), (n_m,)) for s in sels]).ravel()

        cols: dict[str, np.ndarray] = {
            "frame": np.repeat(np.asarray(frames, np.int64), n_m),
            "marker": np.tile(names, n_f),
            "status": status.ravel(),
            "n_containing": np.stack([s.n_containing for s in sels]).astype(np.int64).ravel(),
            "shapes": shape_col,
            "weights": weight_col,
            "projection_mm": stack(lambda s: s.projection) * MM_PER_CM,
            "score_mm": stack(lambda s: s.score) * MM_PER_CM,
            "residual_before_mm": before.ravel() * MM_PER_CM,
            "residual_mm": r_final.ravel() * MM_PER_CM,
            "fallback": note.ravel(),
            "source": source.ravel(),
            "fit_residual_mm": stack(lambda s: s.fit.residual if s.fit is not None else np.nan) * MM_PER_CM,
            "fit_rms_mm": stack(lambda s: s.fit.rms if s.fit is not None else np.nan) * MM_PER_CM,
            # How far from the markers this bundle's weights gave way to the global fit (0: not at all).
            "far_share": stack(lambda s: s.far_share if s.far_share is not None else np.nan),
        }
        if thetas is not None:
            for k, n in enumerate(PARAM_NAMES):
                cols[f"jaw_{n}"] = np.repeat(np.asarray(thetas[:, k], np.float64), n_m)
            cols["jaw_source"] = np.repeat(np.array([s.fit.jaw_source if s.fit is not None else "" for s in sels],
                                                    object), n_m)
        return pd.DataFrame(cols)

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


class _Finisher:
    """Blend, skin and correct frames of a sequence into ``out`` (F, V, 3) float32, keeping each bundle's
    distance before (``before``) and after (``r_final``) the correction (F, M), cm."""

    def __init__(self, solver: LGISolver, pos: np.ndarray, fit_pos: np.ndarray) -> None:
        self.solver, self.pos, self.fit_pos = solver, pos, fit_pos
        n_f, n_m = len(pos), solver.index.n_markers
        self.out = np.empty((n_f, solver.index.n_vertices, 3), np.float32)
        self.seen = np.all(np.isfinite(pos), axis=2)
        self.before = np.empty((n_f, n_m))
        self.r_final = np.empty((n_f, n_m))

    def blend(self, f: int, shapes: np.ndarray, lam: np.ndarray, jaw: np.ndarray | None,
              share: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Frame f's surface (V, 3), its residuals (M, 3) to the fitted positions (NaN where missing) and the far
        field's share t (V,) of the global fit (None without a far field), given the bundles' far shares."""
        s = self.solver
        t = s.far_global_share(share) if len(shapes) == s.index.n_markers + 1 and s._far.active else None
        x = s.surface(shapes, lam, jaw, share)
        return x, self.fit_pos[f] - s.layout.evaluate(x), t

    def finish(self, f: int, x: np.ndarray, resid: np.ndarray, t: np.ndarray | None = None) -> None:
        """Correct surface ``x`` by ``noise_gain`` of ``resid`` at the seen bundles (but for the far field's share
        t of the global fit) and store it."""
        s, seen = self.solver, self.seen[f]
        target = np.where(seen[:, None], s.layout.evaluate(x) + s.noise_gain * np.nan_to_num(resid), np.nan)
        s.correct(x, target, seen)
        s.correct_far(x, resid, seen, s.noise_gain, t)
        self.out[f] = x
        self.r_final[f] = np.where(seen, np.linalg.norm(np.nan_to_num(self.pos[f]) - s.layout.evaluate(x), axis=1),
                                   np.nan)

    def frame(self, f: int, shapes: np.ndarray, lam: np.ndarray, jaw: np.ndarray | None,
              share: np.ndarray | None = None) -> None:
        """:meth:`blend` and :meth:`finish` frame f with its own residuals."""
        x, resid, t = self.blend(f, shapes, lam, jaw, share)
        self.before[f] = np.linalg.norm(resid, axis=1)
        self.finish(f, x, resid, t)


def _differences(shapes: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's slots minus the last row's, as slots: ``(N, K')`` shapes and weight differences, each row's
    nonzero differences first and the rest 0 (a row that equals the last one has none).

    Parameters
    ----------
    shapes : (N, K) int64
        Extended shape indices (0: the neutral, with weight 0).
    weights : (N, K) float64
    """
    n = len(shapes)
    width = int(shapes.max()) + 1
    dense = np.zeros((n, width))
    np.add.at(dense, (np.repeat(np.arange(n), shapes.shape[1]), shapes.ravel()), weights.ravel())
    dense -= dense[-1]
    dense[:, 0] = 0.0
    nz = dense != 0.0
    k = max(1, int(nz.sum(1).max()))
    order = np.argsort(~nz, axis=1, kind="stable")[:, :k]
    taken = np.take_along_axis(nz, order, axis=1)
    return (np.ascontiguousarray(np.where(taken, order, 0), np.int64),
            np.ascontiguousarray(np.where(taken, np.take_along_axis(dense, order, axis=1), 0.0)))


def slot_labels(shapes: np.ndarray, weights: np.ndarray, shape_names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """The diagnostics' ``shapes`` and ``weights`` texts of rows of slots: the names of the slots with a
    positive weight joined by ";" and their weights as "%.4f" joined by " ", in slot order.

    Parameters
    ----------
    shapes : (N, K) int
        Shape indices per row and slot.
    weights : (N, K) float
        Their weights; slots at 0 (or padding) are left out.
    shape_names : list of str

    Returns
    -------
    (N,) object, (N,) object
        The two texts per row, equal to Python's formatting of each weight (ties decided as it does).
    """
    n, k = weights.shape
    nz = weights > 0
    # The used slots first (keeping their order): the texts are then prefixes of fixed-width rows.
    order = np.argsort(~nz, axis=1, kind="stable")
    k = int(nz.sum(axis=1).max()) if n else 0  # padding slots beyond the widest row hold nothing
    shapes, weights, nz = (np.take_along_axis(a, order[:, :k], 1) for a in (shapes, weights, nz))
    # Names: a shot repeats few combinations of shapes (each marker's simplices), so each is joined once.
    key = np.ascontiguousarray(np.where(nz, shapes, -1).astype(np.int64))
    codes, uniq = pd.factorize(key.view(f"V{8 * k}").ravel() if k else np.zeros(n, np.int64))
    rows = key[np.unique(codes, return_index=True)[1]] if n else key
    joined = np.array([";".join(shape_names[s] for s in row if s >= 0) for row in rows], object)
    name_text = joined[codes] if n else np.empty(0, object)
    # Weights: "d.dddd" written as bytes, slot after slot, with NULs (which bytes strings drop at the end) for
    # unused slots. rint(w * 1e4) is Python's 4-decimal rounding except within rounding error of a tie, or
    # outside [0, 1]: those rows are formatted by Python itself.
    x = np.asarray(weights, np.float64) * 1e4
    q = np.rint(x).astype(np.int64)
    python = (nz & ((np.abs(x - np.floor(x) - 0.5) <= 1e-6) | (q > 10000))).any(axis=1)
    q = np.clip(q, 0, 10000)
    chars = np.empty((n, k, 7), np.uint8)
    chars[..., 0] = ord(" ")
    chars[..., 1] = ord("0") + q // 10000
    chars[..., 2] = ord(".")
    for d, p in enumerate((1000, 100, 10, 1)):
        chars[..., 3 + d] = ord("0") + (q // p) % 10
    chars[~nz] = 0
    flat = np.ascontiguousarray(chars.reshape(n, 7 * k)[:, 1:]) if k else np.zeros((n, 1), np.uint8)
    weight_text = flat.view(f"S{flat.shape[1]}").ravel().astype(str).astype(object)
    for r in np.flatnonzero(python):
        weight_text[r] = " ".join(f"{w:.4f}" for w in weights[r][nz[r]])
    return name_text, weight_text


def _stack_slots(shapes: list[np.ndarray], weights: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(F, M, K) shapes and weights of frames whose bundles use different numbers of slots (zero-padded)."""
    k = max(s.shape[1] for s in shapes)
    out_s = np.zeros((len(shapes), shapes[0].shape[0], k), np.int64)
    out_w = np.zeros((len(shapes), shapes[0].shape[0], k))
    for f, (s, w) in enumerate(zip(shapes, weights, strict=True)):
        out_s[f, :, :s.shape[1]] = s
        out_w[f, :, :w.shape[1]] = w
    return out_s, out_w


def _append_rows(shapes: list[np.ndarray], weights: list[np.ndarray], fit_weights: list[np.ndarray]
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(F, M + 1, K) slots: each frame's bundles' slots and, as the last row, its global fit's weights (S,)
    as slots (extended shape indices)."""
    rows_s, rows_w = [], []
    for s, w, g in zip(shapes, weights, fit_weights, strict=True):
        nz = np.flatnonzero(np.asarray(g) > 0)
        k = max(s.shape[1], len(nz), 1)
        out_s = np.zeros((s.shape[0] + 1, k), np.int64)
        out_w = np.zeros((s.shape[0] + 1, k))
        out_s[:-1, :s.shape[1]] = s
        out_w[:-1, :w.shape[1]] = w
        out_s[-1, :len(nz)] = nz + 1
        out_w[-1, :len(nz)] = np.asarray(g)[nz]
        rows_s.append(out_s)
        rows_w.append(out_w)
    return _stack_slots(rows_s, rows_w)


class _FarField:
    """The natural-neighbour weights with a far field (see :class:`LGISolver`, ``far_field``).

    A vertex at UV-geodesic distance d from its nearest bundle has the ramp r (V,): 0 up to ``far_field[0]`` cm,
    1 from ``far_field[1]``, a smoothstep between, and 0 on every bundle's own triangle (the surface passes
    through the bundles) and where no bundle's weights reach. Per frame, given each bundle's far share s (M,),
    the vertex keeps ``N_vb (1 - r_v s_b)`` of bundle b's weights and gives ``t_v = r_v sum_b N_vb s_b`` to
    the frame's global fit (:meth:`global_share`; :func:`lgi.solve._blend_kernels.blend_on_base` blends them).
    """

    def __init__(self, arrays, n_markers: int, far_field: tuple[float, float] | None) -> None:
        self.n_markers = n_markers
        self.active = False
        if far_field is None:
            return
        d0, d1 = far_field
        if not (np.isfinite(d0) and d0 >= 0 and d1 > d0):
            raise InputError(f"far field must be two distances 0 <= start < end (cm), not {far_field}")
        indptr, indices, data = arrays["w_indptr"], arrays["w_indices"], arrays["w_data"]
        dist = np.asarray(arrays["nn_distance"], np.float64)
        u = np.clip((dist - d0) / (d1 - d0), 0.0, 1.0) if np.isfinite(d1) else np.zeros_like(dist)
        r = u * u * (3.0 - 2.0 * u)
        r[np.diff(indptr) == 0] = 0.0
        # A bundle's own triangle keeps its weights whatever its size: the surface passes through the bundle.
        r[np.asarray(arrays["marker_vertices"]).ravel()] = 0.0
        if not (r > 0).any():
            return
        self.active = True
        self.n_v = len(indptr) - 1
        self.row = np.repeat(np.arange(self.n_v), np.diff(indptr))  # the vertex of each weight
        self.col = np.asarray(indices, np.int64)
        self.nn = np.asarray(data, np.float64)
        self.r = r

    def global_share(self, share: np.ndarray | None) -> np.ndarray:
        """(V,) t for the bundles' far shares (M,) (None: 1)."""
        s = np.ones(self.n_markers) if share is None else np.clip(np.asarray(share, np.float64), 0.0, 1.0)
        return np.bincount(self.row, self.nn * self.r[self.row] * s[self.col], minlength=self.n_v)
