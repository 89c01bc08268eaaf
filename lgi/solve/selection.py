"""A frame's choice of shapes and weights per bundle: the global fit, the simplex search and its second pass
(the neighbours' agreement), the local refits, and missing bundles filled from the previous frame or a
neighbour."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lgi.errors import InputError
from lgi.progress import progress
from lgi.solve._select_kernels import (
    OWN_WEIGHT,
    FramePass,
    SearchSettings,
    agreement,
    local_fits,
    local_fits_serial,
    new_choice,
    solve_bundles,
    solve_bundles_serial,
    weight_misfits,
)
from lgi.solve.globalfit import GlobalFitResult
from lgi.solve.results import FITTED, FrameResult
from lgi.threads import one_blas_thread
from lgi.units import MM_PER_CM

#: Frames whose positions and cached fits :meth:`Selection.select_sequence` reads at a time.
SELECT_BLOCK = 128

# A bundle keeps the global weights where they fit it and its neighbours within this RMS (cm; 1 micrometre).
LOCAL_MIN_MISFIT = 1e-4
# How far (in shape weight) a bundle's local weights are expected to stray from the global fit's: with measured
# bundles the local fit's ridge is the noise variance left over its square.
LOCAL_WEIGHT_SPREAD = 0.1
# Expected lowering of a local fit's neighbourhood misfit (per coordinate) by the noise alone, in units of the noise
# variance left: a local fit's step from the global weights keeps the share of its gain beyond this. Measured on
# the synthetic actor with 5 % missing (LGI / the smoothed fit at 0.02 / 0.1 / 0.3 mm): without it 0.815 / 1.016 /
# 1.032 at best (any spread 0.01-0.03); with it 0.799 / 0.994 / 1.007 (3 and 10: no better).
LOCAL_SHRINK = 1.0


class Selection:
    """Each bundle's shapes and weights in a frame (:meth:`select_frame`) and in a sequence of frames
    (:meth:`select_sequence`), no vertices yet.

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...).
    """

    def select(self, bundles: np.ndarray, previous: FrameResult | None = None, needed: np.ndarray | None = None,
               serial: bool = False):
        """Choose each bundle's shapes and weights (no blending); ``serial``: on the calling thread alone (the
        kernels' one-thread twins, the same bits: a shot chosen on one thread while another blends).

        ``needed`` (M,) bool: the bundles whose choice is used (all by default); the simplex search runs for
        them and, since their second pass reads their natural neighbours' first choices, for those too.
        The other rows are left unsearched (status MISSING, no shapes, ``n_containing`` 0).

        Returns
        -------
        tuple
            ``(p, seen, shapes, weights, n_containing, status, projection, score, fallback)`` as in
            :class:`FrameResult`, ``p`` the bundles as float64 and ``seen`` (M,) bool.
        """
        p = np.asarray(bundles, np.float64)
        if p.shape != (self.index.n_markers, 3):
            raise InputError(f"bundles have shape {p.shape}, the index has {self.index.n_markers} markers")
        seen = np.all(np.isfinite(p), axis=1)
        pk = np.where(seen[:, None], p, 0.0)
        prev = previous.shapes if previous is not None else np.full((len(p), 4), -1, np.int64)
        mu = self.temporal_weight / MM_PER_CM if previous is not None else 0.0
        cfg = SearchSettings(self.alias_min_weight, self.tolerance, self._dist_tol, self.n_project, self.top_k)
        if needed is None:
            needed = first = np.ones(len(p), bool)
        else:
            # A missing bundle takes a seen neighbour's choice (:meth:`_fill_missing`): those are needed too.
            needed = needed.copy()
            needed[self._pair_j[(needed & ~seen)[self._pair_i]]] = True
            first = needed.copy()
            first[self._pair_j[needed[self._pair_i]]] = True
        search = solve_bundles_serial if serial else solve_bundles
        out = new_choice(len(p), self.top_k)
        search(self._ix, cfg, FramePass(pk, seen, prev, mu, self._no_agree, 0.0, self._no_shapes, self._no_lam,
                                        self._scan, self._no_scores, self._no_first, first), out)
        shapes, lam, pts, n_contain, status, proj, score, cand, cand_score = out
        # Second pass: break near-ties toward the shapes the neighbours and the frame agree on. A noisy bundle's
        # simplex only lends its shapes to the bundle's local fit, where the tie-break changed the synthetic actor's
        # and the 400-scan session's RMS by under 0.5 % (0.02-0.3 mm): it costs a third of the frame and is skipped.
        if self.spatial_weight > 0 and self.noise == 0:
            agree = agreement(self._ix, pts, lam, seen, self._n_ext)
            # Bundles with no containing simplex in the first pass scan again (their projection).
            cand[cand[:, 0] < 0] = -2
            out = new_choice(len(p), self.top_k)
            search(self._ix, cfg, FramePass(pk, seen, prev, mu, agree, self.spatial_weight / MM_PER_CM, shapes, lam,
                                            cand, cand_score, np.nan_to_num(score, nan=np.inf), needed), out)
            shapes, lam, pts, n_contain, status, proj, score, _, _ = out
        fallback = self._fill_missing(seen, shapes, lam, previous)
        return p, seen, shapes, lam, n_contain, status, proj, score, fallback

    def estimate_jaw(self, bundles: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """(4,) jaw parameters of a frame, fitted with the shape weights to all its bundles."""
        start = None if init is None else GlobalFitResult(np.zeros(0), np.asarray(init, np.float64), np.zeros(0), 0.0)
        return self.global_fit.solve(bundles, init=start).jaw

    def select_frame(self, bundles: np.ndarray, previous: FrameResult | None = None,
                     jaw: np.ndarray | None = None, left: np.ndarray | None = None,
                     fit: GlobalFitResult | None = None, serial: bool = False) -> FrameResult:
        """Choose shapes and weights (unskinning the bundles first with a jaw rig); no vertices yet. ``left``
        (M, 3) cm^2: the noise variance left in ``bundles`` (default: all of the solver's noise, none for exact
        bundles), which holds each bundle's local fit toward the global weights (:data:`LOCAL_WEIGHT_SPREAD`).
        ``fit``: the frame's global fit of these bundles when already made (:meth:`cached_fits`). ``serial``: as for
        :meth:`select`."""
        p = np.asarray(bundles, np.float64)
        if p.shape != (self.index.n_markers, 3):
            raise InputError(f"bundles have shape {p.shape}, the index has {self.index.n_markers} markers")
        left_out = self.shot_noise.dropped & np.all(np.isfinite(p), axis=1)
        if left_out.any():
            # Too noisy to weigh in (:meth:`noise_from_covariance`): chosen as a missing bundle is.
            p = p.copy()
            p[left_out] = np.nan
        seen = np.all(np.isfinite(p), axis=1)
        if not seen.any():
            raise InputError("no marker seen in this frame")
        if fit is None:
            fit = self.global_fit.solve(p, jaw=jaw, init=None if previous is None else previous.fit)
        theta = fit.jaw
        q = p
        if self.rig is not None:
            q = p.copy()
            q[seen] = self.rig.unskin(p[seen], theta, self._bundle_w[seen])
        prev_simplex = None
        if previous is not None:
            # A bundle the global fit met had no simplex searched: no temporal preference from it.
            prev_shapes = np.where((previous.status == FITTED)[:, None], -1, previous.simplex_shapes)
            prev_simplex = FrameResult(vertices=previous.vertices, shapes=prev_shapes,
                                       weights=previous.simplex_weights, n_containing=previous.n_containing,
                                       status=previous.status, projection=previous.projection, score=previous.score,
                                       residual=previous.residual, fallback=previous.fallback)
        keep = global_score = None
        if self.method == "local":
            # Where the global weights already fit a bundle's neighbourhood it keeps them (see :meth:`_local`),
            # so its simplex would go unused: only the other bundles are searched.
            global_score = self._shared_misfits(q, seen, fit.weights)
            keep = global_score <= LOCAL_MIN_MISFIT
        q, seen, shapes, lam, n_contain, status, proj, score, fallback = self.select(
            q, prev_simplex, None if keep is None else ~keep, serial)
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
            if left is None and self.noise > 0:
                left = (self.shot_noise.sigma / MM_PER_CM) ** 2
            shapes, lam, score, source, fallback = self._local(q, seen, fit, shapes, lam, score, fallback,
                                                               global_score, left, serial)
        for i in np.flatnonzero(left_out):
            mm = np.sqrt(np.mean(self.shot_noise.sigma[i] ** 2))
            fallback[i] = f"left out for its noise ({mm:.3f} mm): {fallback[i]}"
        share = None
        if self._far.active:
            dense = np.zeros((len(p), self.global_fit.n_shapes + 1))
            np.add.at(dense, (np.repeat(np.arange(len(p)), shapes.shape[1]), shapes.ravel()), lam.ravel())
            share = self.far_shares(q, seen, dense[:, 1:], fit.weights)
        return FrameResult(vertices=np.zeros((0, 3), np.float32), shapes=shapes, weights=lam, n_containing=n_contain,
                           status=status, projection=proj, score=score, residual=np.where(seen, 0.0, np.nan),
                           fallback=fallback, jaw=theta, bundles=p, source=source, fit=fit,
                           simplex_shapes=simplex_shapes, simplex_weights=simplex_weights, far_share=share)

    def _misfits(self, q: np.ndarray, seen: np.ndarray, w: np.ndarray, rows: np.ndarray | None = None
                 ) -> np.ndarray:
        """(M,) RMS misfit (cm) of each bundle's weights ``w`` (M, S) at the bundle (weight OWN_WEIGHT) and its
        seen natural neighbours, in the index's (unskinned) space; the simplex candidates' score. With ``rows``
        (M,) bool, only those bundles are scored (the others are NaN)."""
        out = np.empty(len(q))
        weight_misfits(self._rest, self._basis, np.ascontiguousarray(q, np.float64), seen, self._a["nb_off"],
                       self._a["nb_idx"], np.ascontiguousarray(w, np.float64),
                       np.ones(len(q), bool) if rows is None else rows, OWN_WEIGHT, out)
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

    def _local(self, q: np.ndarray, seen: np.ndarray, fit: GlobalFitResult, shapes: np.ndarray, lam: np.ndarray,
               score: np.ndarray, fallback: list[str], global_score: np.ndarray | None = None,
               left: np.ndarray | None = None, serial: bool = False):
        """Local fits (see ``method``); returns shapes and weights as slots (M, K), scores, sources, notes.
        ``global_score`` (M,) cm: :meth:`_shared_misfits` of the global weights, when already computed; ``left``
        (M, 3) cm^2 the noise variance left in the bundles (None: exact)."""
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
        rows = np.concatenate([np.broadcast_to(support, (m, len(support))), np.where(ext >= 0, ext, n_s)], axis=1)
        rows.sort(axis=1)  # the unused slots (n_s) last
        flat = rows[todo][np.arange(rows.shape[1])[None] < counts[todo][:, None]]
        resid = np.where(seen[:, None], q - self._rest - np.tensordot(wg[wg != 0], self._basis[wg != 0], axes=1), 0.0)
        w_local = np.empty((m, n_s))
        beta = np.full(m, self.local_prior)
        if left is not None:
            # A measured bundle's weights are trusted no more than its noise allows: a ridge of the noise variance
            # over the weights' spread about the global fit (a Gaussian prior on their difference).
            beta += np.nan_to_num(np.mean(left, axis=1)) / LOCAL_WEIGHT_SPREAD**2
        fits = local_fits_serial if serial else local_fits
        fits(resid, seen, self._basis, self._a["nb_off"], self._a["nb_idx"], col_off, flat, wg, beta, OWN_WEIGHT,
             w_local)
        local_score = self._misfits(q, seen, w_local, todo)
        if left is not None and LOCAL_SHRINK > 0:
            # With measured bundles a local fit lowers its neighbourhood's misfit by fitting the noise too: its step
            # from the global weights is shrunk by the share that the noise left could explain (James-Stein).
            gain = np.maximum(global_score**2 - local_score**2, 0.0) / 3.0  # per coordinate, cm^2
            noise = np.nan_to_num(np.mean(left, axis=1))
            keep_share = np.clip(1.0 - LOCAL_SHRINK * noise / np.maximum(gain, 1e-300), 0.0, 1.0)
            keep_share[~todo] = 1.0
            w_local = wg + keep_share[:, None] * (w_local - wg)
            local_score = self._misfits(q, seen, w_local, todo)
        # A simplex passes exactly through its bundle: with noisy bundles that is fitting the noise, so
        # the simplex candidate competes only with exact bundles.
        use_local = np.ones(m, bool)
        chosen = w_local
        simplex_score = local_score
        if self.noise == 0:
            # The simplex candidate's weights as a full vector, to compare like with like.
            w_simplex = np.zeros((m, n_s + 1))
            np.add.at(w_simplex, (np.repeat(np.arange(m), shapes.shape[1]), shapes.ravel()), lam.ravel())
            simplex_score = self._misfits(q, seen, w_simplex[:, 1:], todo)
            use_local = ~(seen & (simplex_score < local_score))
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

    @one_blas_thread
    def select_sequence(self, pos: np.ndarray, frames: np.ndarray, jaw: np.ndarray | None = None,
                        show_progress: bool = False,
                        emit: Callable[[int, FrameResult], None] | None = None,
                        previous: FrameResult | None = None, left: np.ndarray | None = None,
                        keep: bool = True, serial: bool = False) -> list[FrameResult]:
        """Each frame's choice of shapes and weights, in order (the previous frame's carried into the next);
        ``emit(f, choice)`` is called with each as it is made (with ``keep`` False, the only place they go: a long
        shot's choices are not held). ``previous``: the choice of the frame before
        ``pos[0]`` when a shot is chosen in chunks (the result is then the one a single call gives). ``left``
        (F, M, 3) cm^2: the noise variance left in ``pos`` (default: the solver's noise's, :meth:`denoise`, when it
        covers these frames). ``serial``: as for :meth:`select`."""
        if left is None and self.shot_noise.left is not None and len(self.shot_noise.left) == len(pos):
            left = self.shot_noise.left
        sels = []
        prev = previous
        lo = hi = 0
        for f in progress(range(len(pos)), "choosing shapes", disable=not show_progress):
            if f == hi:
                # A block of frames at a time: ``pos`` and ``left`` may be a long take's arrays on disk
                # (:class:`~lgi.io.stored.StoredArray`), read by range.
                lo, hi = f, min(len(pos), f + SELECT_BLOCK)
                p = np.asarray(pos[lo:hi])
                lf = None if left is None else np.asarray(left[lo:hi])
                fits = self.cached_fits(p, frames[lo:hi]) if jaw is None else [None] * len(p)
            try:
                prev = self.select_frame(p[f - lo], prev, None if jaw is None else jaw[f],
                                         None if lf is None else lf[f - lo], fits[f - lo], serial)
            except InputError as exc:
                raise InputError(exc.message, frame=int(frames[f])) from None
            if keep:
                sels.append(prev)
            if emit is not None:
                emit(f, prev)
        return sels
