"""Per-frame reconstruction by local geometric indexing.

For every bundle the solver finds the simplices of its point cloud that contain it; each gives convex
barycentric weights over shapes, a candidate local surface through the bundle. It keeps the candidate
whose blend of shapes best fits the bundle's natural neighbours (RMS distance, plus a preference for
shapes shared with the previous frame's choice). A bundle outside its cloud is projected onto the
cloud's hull, the candidate chosen by the same criterion with its own distance included. Every vertex
then mixes the bundles' shape weights with its natural-neighbour weights. Where a bundle was projected
(or an alias shape replaced a merged point), the remaining bundle residuals are interpolated smoothly
(:mod:`lgi.smooth`) so the surface passes through every seen bundle.

A bundle missing from a frame takes its previous frame's choice, or else that of its nearest seen
natural neighbour (or nearest seen bundle); the diagnostics say which.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from . import _kernels as K
from .bundles import Bundles
from .errors import InputError
from .index import LGIIndex
from .progress import progress

STATUS = {K.CONTAINED: "contained", K.PROJECTED: "projected", K.MISSING: "missing", K.BORROWED: "neighbour"}


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
        Simplices that contained the bundle.
    status : (M,) int64
        0 contained, 1 projected, 2 missing, 3 neighbour (took a natural neighbour's mixture).
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


@dataclass
class SequenceResult:
    """A reconstructed sequence: vertices (F, V, 3) float32 cm, frame numbers, per-bundle diagnostics,
    and the jaw parameters used (F, 4) when the index has a rig."""

    frames: np.ndarray
    vertices: np.ndarray
    diagnostics: pd.DataFrame
    jaw: np.ndarray | None = None


class LGISolver:
    """Reconstruct frames of bundles with a built :class:`~lgi.index.LGIIndex`.

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
    """

    def __init__(self, index: LGIIndex, temporal_weight: float = 0.0, alias_min_weight: float = 0.1,
                 correct_residuals: bool = True, tolerance: float = 1e-9, n_project: int = 3,
                 spatial_weight: float = 1e-3, top_k: int = 4, jaw: str = "auto") -> None:
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
        self._deltas = np.asarray(index.deltas)  # read once: the blend touches all of it every frame
        nb_off, nb_idx = a["nb_off"], a["nb_idx"]
        self._neighbours = [nb_idx[nb_off[i]:nb_off[i + 1]] for i in range(index.n_markers)]
        self._rest = a["ptab"][0]
        self.rig = index.jaw_rig()
        if self.rig is not None and jaw == "none":
            raise InputError("the index was built with a jaw rig (its shapes are unskinned): use jaw 'auto' or "
                             "given parameters, or rebuild the index without a rig")
        if self.rig is not None:
            self._bundle_w = self.layout.evaluate(self.rig.weights[:, None])[:, 0]
            self._jaw_bundles = np.flatnonzero(self._bundle_w >= 0.9)
        # A bundle off a flat cloud's plane by less than the flatness tolerance is still inside it.
        self._dist_tol = float(index.manifest["options"]["cloud"]["flat_tol"])

    # ---------------------------------------------------------------------------------- frames
    def select(self, bundles: np.ndarray, previous: FrameResult | None = None):
        """Choose each bundle's shapes and weights (no blending).

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
        mu = self.temporal_weight / 10.0 if previous is not None else 0.0
        args = (pk, seen, a["dim"], a["origin"], a["basis"], a["pts"], a["pt_off"], a["pt_shape"], a["alias_off"],
                a["class_off"], a["alias_shape"], a["sx"], a["tinv"], a["hull"], a["hull_off"], a["grid_lo"],
                a["grid_h"], a["grid_dims"], a["cell_off"], a["cell_start"], a["cell_items"], a["ptab"],
                a["nb_off"], a["nb_idx"], a["snap_radius"], prev, mu)
        tail = (self.alias_min_weight, self.tolerance, self._dist_tol, self.n_project, self.top_k)
        shapes, lam, pts, n_contain, status, proj, score, cand, cand_score = K.solve_bundles(
            *args, self._no_agree, 0.0, self._no_shapes, self._no_lam, *tail, self._scan, self._no_scores,
            self._no_first)
        if self.spatial_weight > 0:
            # Second pass: break near-ties toward the shapes the neighbours and the frame agree on.
            agree = K.agreement(pts, lam, seen, a["alias_off"], a["class_off"], a["alias_shape"], a["nb_off"],
                                a["nb_idx"], self._n_ext)
            # Bundles with no containing simplex in the first pass scan again (their projection).
            cand[cand[:, 0] < 0] = -2
            shapes, lam, pts, n_contain, status, proj, score, _, _ = K.solve_bundles(
                *args, agree, self.spatial_weight / 10, shapes, lam, *tail, cand, cand_score,
                np.nan_to_num(score, nan=np.inf))
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
                K.add_correction(x, a["corr_indptr"], a["corr_indices"], a["corr_data"], fix, resid_vec[fix])
                resid_vec = np.where(seen[:, None], p - self.layout.evaluate(x), 0.0)
        return np.where(seen, np.linalg.norm(resid_vec, axis=1), np.nan)

    def estimate_jaw(self, bundles: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """(4,) jaw parameters fitted to the seen bundles that move with the jaw (weight >= 0.9)."""
        p = np.asarray(bundles, np.float64)
        jb = self._jaw_bundles[np.all(np.isfinite(p[self._jaw_bundles]), axis=1)]
        if jb.size < 3:
            return np.zeros(4) if init is None else np.asarray(init, np.float64)
        return self.rig.fit(self._rest[jb], p[jb], self._bundle_w[jb], init)

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
        return self.blend_frame(sel, sel.shapes, sel.weights, sel.jaw)

    def select_frame(self, bundles: np.ndarray, previous: FrameResult | None = None,
                     jaw: np.ndarray | None = None) -> FrameResult:
        """Choose shapes and weights (unskinning the bundles first with a jaw rig); no vertices yet."""
        p = np.asarray(bundles, np.float64)
        theta = None
        q = p
        if self.rig is not None:
            init = previous.jaw if previous is not None and previous.jaw is not None else None
            theta = np.asarray(jaw, np.float64) if jaw is not None else self.estimate_jaw(p, init)
            seen = np.all(np.isfinite(p), axis=1)
            q = p.copy()
            q[seen] = self.rig.unskin(p[seen], theta, self._bundle_w[seen])
        q, seen, shapes, lam, n_contain, status, proj, score, fallback = self.select(q, previous)
        return FrameResult(np.zeros((0, 3), np.float32), shapes, lam, n_contain, status, proj, score,
                           np.where(seen, 0.0, np.nan), fallback, theta, p)

    def surface(self, shapes: np.ndarray, weights: np.ndarray, jaw: np.ndarray | None) -> np.ndarray:
        """(V, 3) float64: the natural-neighbour blend of the bundles' shapes, skinned when there is a rig."""
        a = self._a
        x = np.empty_like(self._x0)
        K.blend(self._x0, self._deltas, a["w_indptr"], a["w_indices"], a["w_data"], shapes, weights, x)
        return x if self.rig is None else self.rig.skin(x, jaw)

    def blend_frame(self, sel: FrameResult, shapes: np.ndarray, weights: np.ndarray,
                    jaw: np.ndarray | None, bundles: np.ndarray | None = None) -> FrameResult:
        """Vertices for chosen (possibly smoothed) shapes and weights, skinned and taken through the bundles.

        ``bundles`` are the positions to pass through (default: those the selection was made for).
        """
        x = self.surface(shapes, weights, jaw)
        p = sel.bundles if bundles is None else np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        before = np.where(seen, np.linalg.norm(np.where(seen[:, None], p, 0) - self.layout.evaluate(x), axis=1), np.nan)
        residual = self.correct(x, p, seen)
        return FrameResult(x.astype(np.float32), sel.shapes, sel.weights, sel.n_containing, sel.status,
                           sel.projection, sel.score, residual, sel.fallback, jaw, p, before)

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
    def solve_sequence(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None,
                       show_progress: bool = False, smooth: int = 1, jaw_smooth: int | None = None,
                       jaw: np.ndarray | None = None, max_gap: int = 0) -> SequenceResult:
        """Reconstruct frames in order, carrying each frame's choice into the next.

        Parameters
        ----------
        bundles
            A :class:`~lgi.bundles.Bundles` (markers matched by name) or an (F, M, 3) array in layout order.
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
        """
        pos, frames, bridged = self.prepare(bundles, frames, max_gap)
        if jaw is not None and len(jaw) != len(pos):
            raise InputError(f"{len(jaw)} jaw parameter rows for {len(pos)} frames")
        sels = self.select_sequence(pos, frames, jaw, show_progress)
        return self.finish_sequence(sels, pos, frames, bridged, smooth, jaw_smooth, show_progress)

    def prepare(self, bundles: Bundles | np.ndarray, frames: np.ndarray | None = None,
                max_gap: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (F, M, 3) in layout order with short gaps bridged, frame numbers, bridged mask (F, M)."""
        from .temporal import bridge_gaps

        if isinstance(bundles, Bundles):
            pos = self.align(bundles)
            frames = bundles.frames
        else:
            pos = np.asarray(bundles, np.float64)
            frames = np.arange(len(pos)) if frames is None else np.asarray(frames)
        pos, bridged = bridge_gaps(pos, max_gap)
        return pos, np.asarray(frames), bridged

    def select_sequence(self, pos: np.ndarray, frames: np.ndarray, jaw: np.ndarray | None = None,
                        show_progress: bool = False) -> list[FrameResult]:
        """Each frame's choice of shapes and weights, in order (the previous frame's carried into the next)."""
        sels = []
        prev = None
        for f in progress(range(len(pos)), "choosing shapes", disable=not show_progress):
            try:
                prev = self.select_frame(pos[f], prev, None if jaw is None else jaw[f])
            except InputError as exc:
                raise InputError(exc.message, frame=int(frames[f])) from None
            sels.append(prev)
        return sels

    def finish_sequence(self, sels: list[FrameResult], pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                        smooth: int = 1, jaw_smooth: int | None = None,
                        show_progress: bool = False) -> SequenceResult:
        """Smooth the choices over time, blend, skin and correct every frame; diagnostics per bundle."""
        from .temporal import window_slots

        shapes = np.stack([r.shapes for r in sels])
        lam = np.stack([r.weights for r in sels])
        thetas = None
        if self.rig is not None:
            from .jaw import smooth_parameters

            thetas = smooth_parameters(np.stack([r.jaw for r in sels]), smooth if jaw_smooth is None else jaw_smooth)
        if smooth > 1:
            shapes, lam = window_slots(shapes, lam, smooth)
        out = np.empty((len(pos), self.index.n_vertices, 3), np.float32)
        surfaces = []
        resid = np.zeros_like(pos)
        for f in progress(range(len(pos)), "blending", disable=not show_progress):
            x = self.surface(shapes[f], lam[f], None if thetas is None else thetas[f])
            surfaces.append(x)
            resid[f] = pos[f] - self.layout.evaluate(x)  # NaN where missing
        before = np.linalg.norm(resid, axis=2)
        if smooth > 1:
            # The correction follows the same moving average: corrected to each frame's raw residuals,
            # the surface would carry the bundles' noise straight back.
            from .temporal import moving_average

            resid = moving_average(resid, smooth)
        rows = []
        names = self.index.marker_names
        shape_names = self.index.shape_names
        for f in range(len(pos)):
            x = surfaces[f]
            seen = np.all(np.isfinite(pos[f]), axis=1)
            target = np.where(seen[:, None], self.layout.evaluate(x) + np.nan_to_num(resid[f]), np.nan)
            self.correct(x, target, seen)
            out[f] = x
            r_final = np.where(seen, np.linalg.norm(np.nan_to_num(pos[f]) - self.layout.evaluate(x), axis=1), np.nan)
            sel = sels[f]
            for i in range(len(names)):
                nz = sel.weights[i] > 0
                status = STATUS[int(sel.status[i])] if not sel.fallback[i] else "missing"
                note = sel.fallback[i]
                if bridged[f, i]:
                    status, note = "bridged", "interpolated between the frames around the gap"
                rows.append((
                    int(frames[f]), names[i], status, int(sel.n_containing[i]),
                    ";".join(shape_names[k] for k in sel.shapes[i][nz]),
                    " ".join(f"{w:.4f}" for w in sel.weights[i][nz]), sel.projection[i] * 10, sel.score[i] * 10,
                    before[f, i] * 10, r_final[i] * 10, note,
                ))
        diag = pd.DataFrame(rows, columns=["frame", "marker", "status", "n_containing", "shapes", "weights",
                                           "projection_mm", "score_mm", "residual_before_mm", "residual_mm",
                                           "fallback"])
        return SequenceResult(np.asarray(frames), out, diag, thetas)

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
