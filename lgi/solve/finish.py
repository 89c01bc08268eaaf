"""A sequence finished: the chosen weights smoothed over time, every frame blended, skinned and corrected (on a
second thread beside the choice when nothing is smoothed), and the per-bundle diagnostics table."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator

import numpy as np
import pandas as pd

from lgi.io.stored import rows_from
from lgi.progress import progress
from lgi.solve.jaw import PARAM_NAMES, smooth_parameters
from lgi.solve.results import STATUS, FrameResult, SequenceResult
from lgi.solve.surface import _append_rows, _stack_slots
from lgi.solve.temporal import moving_average, window_slots
from lgi.threads import one_blas_thread
from lgi.units import MM_PER_CM


class Finishing:
    """Frames' surfaces and diagnostics from their choices (:meth:`finish_sequence`).

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...).
    """

    def _stream_unsmoothed(self, fit_pos: np.ndarray, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                           jaw: np.ndarray | None, show_progress: bool, block: int, start: int = 0,
                           carried: tuple[int, list] | None = None
                           ) -> Iterator[tuple[int, int, SequenceResult, tuple[int, list]]]:
        """:meth:`select_sequence` then :meth:`finish_sequence` without temporal smoothing, on two threads, in
        blocks of ``block`` frames: yields ``(lo, hi, result of frames lo:hi)`` in order, holding one block's
        surfaces and choices at a time. The choice of frame f + 1 (its kernels compiled without the GIL) runs
        while frame f is blended, and goes on while a block is written. Each frame's choice still follows the
        previous one's in order, and the one-thread kernels give the parallel ones' bits, so the result is the one
        the two calls in turn give (tested); only the wall time changes.

        From frame ``start`` (a multiple of ``block``) on, with ``carried`` what the block before it yielded last
        (``(first, choices)``: the choices from frame ``first`` the next block reads), a run resumes where one
        stopped, with the same bits."""
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
                self.select_sequence(rows_from(fit_pos, start), frames[start:], None if jaw is None else jaw[start:],
                                     False, lambda f, sel: put((f + start, sel)),
                                     previous=carried[1][-1] if carried else None,
                                     left=None if left is None else rows_from(left, start), keep=False,
                                     serial=True)
            except _Stopped:
                return
            except BaseException as exc:  # handed to the consumer, which raises it
                try:
                    put((-1, exc))
                except _Stopped:
                    return

        n = len(pos)
        left = self.shot_noise.left if self.shot_noise.left is not None and len(self.shot_noise.left) == n else None
        # The shot is chosen on one thread and blended on another: both run the kernels' one-thread twins
        # (``serial``), the same bits, so no parallel region is launched from two threads (the "workqueue" threading
        # layer aborts on that) or competes for the two cores.
        worker = threading.Thread(target=produce, name="lgi-select", daemon=True)
        worker.start()
        try:
            bar = iter(progress(range(start, n), "reconstructing", disable=not show_progress))
            for lo in range(start, n, block):
                hi = min(n, lo + block)
                fin = _Finisher(self, pos[lo:hi], fit_pos[lo:hi], None if left is None else left[lo:hi], True)
                sels: list[FrameResult] = []
                for _ in range(lo, hi):
                    next(bar, None)
                    f, sel = chosen.get()
                    if f < 0:
                        raise sel
                    sels.append(sel)
                    fin.frame(f - lo, *self.blend_slots(sel), sel.jaw, sel.far_share)
                thetas = None if self.rig is None else np.stack([s.jaw for s in sels]).astype(np.float64)
                diag = self._diagnostics(sels, frames[lo:hi], bridged[lo:hi], fin.before, fin.r_final, thetas)
                yield lo, hi, SequenceResult(np.asarray(frames[lo:hi]), fin.out, diag, thetas, self.noise, 1,
                                             fin.before, fin.r_final), (hi - 1, sels[-1:])
            next(bar, None)
        except BaseException:
            # Interrupted, failed or closed: the chooser stops at its next frame, but it may be deep in a first
            # call's compilation (a minute on a loaded machine); waiting for it would hold a Ctrl-C that long. It
            # only computes choices, and as a daemon thread it ends with the process.
            stop.set()
            worker.join(timeout=1.0)
            raise
        stop.set()
        worker.join()

    def _stream_smoothed(self, fit_pos: np.ndarray, pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                         smooth: int, jaw_smooth: int | None, jaw: np.ndarray | None, show_progress: bool,
                         block: int, start: int = 0, carried: tuple[int, list] | None = None
                         ) -> Iterator[tuple[int, int, SequenceResult, tuple[int, list]]]:
        """The same with temporal smoothing: each block is chosen (continuing from the last choice), then
        finished from the choices its smoothing windows reach (:func:`smoothing_reach`), which are all that is
        kept. A frame's result depends only on the frames in its windows, so the blocks give the bits of the
        whole shot finished at once (tested)."""
        n = len(pos)
        left = self.shot_noise.left if self.shot_noise.left is not None and len(self.shot_noise.left) == n else None
        reach = smoothing_reach(smooth, jaw_smooth)
        first, sels = carried if carried else (0, [])
        sels = list(sels)
        chosen = first + len(sels)
        for lo in progress(range(start, n, block), "reconstructing", disable=not show_progress):
            hi = min(n, lo + block)
            a, b = max(0, lo - reach), min(n, hi + reach)
            if chosen < b:
                new = self.select_sequence(fit_pos[chosen:b], frames[chosen:b], None if jaw is None else jaw[chosen:b],
                                           previous=sels[-1] if sels else None,
                                           left=None if left is None else left[chosen:b])
                sels += new
                chosen = b
            del sels[:a - first]
            first = a
            k = slice(first, chosen)
            res = self.finish_sequence(sels, pos[k], frames[k], bridged[k], smooth, jaw_smooth, False, fit_pos[k],
                                       lo - first, hi - first, None if left is None else left[k])
            keep_from = max(first, hi - reach)  # the next block's first frame reads back this far
            yield lo, hi, res, (keep_from, sels[keep_from - first:])

    @one_blas_thread
    def finish_sequence(self, sels: list[FrameResult], pos: np.ndarray, frames: np.ndarray, bridged: np.ndarray,
                        smooth: int = 1, jaw_smooth: int | None = None,
                        show_progress: bool = False, fit_pos: np.ndarray | None = None,
                        lo: int = 0, hi: int | None = None, left: np.ndarray | None = None) -> SequenceResult:
        """Smooth the choices over time, blend, skin and correct every frame; diagnostics per bundle.

        ``pos`` are the bundles as given (the diagnostics' residuals are measured to them); ``fit_pos`` the
        positions the frames were fitted to (denoised, :meth:`denoise`), which the correction aims at.
        ``sels``, ``pos``, ``frames`` and ``bridged`` cover the whole shot; only frames ``lo:hi`` are finished
        and returned. A frame's result depends only on the frames in its smoothing windows, each computed on
        its own, so finishing a shot in any ranges gives the same bits as finishing it whole (tested). ``left``
        (F, M, 3) cm^2: the noise variance left in ``fit_pos`` (:meth:`denoise`; default the solver's when it
        covers these frames, None for exact bundles), which sets each frame's :meth:`correction_step`."""
        fit_pos = pos if fit_pos is None else fit_pos
        if left is None and self.shot_noise.left is not None and len(self.shot_noise.left) == len(pos):
            left = self.shot_noise.left

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
        fin = _Finisher(self, pos[a:b], fit_pos[a:b], None if left is None else left[a:b])
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


class _Finisher:
    """Blend, skin and correct frames of a sequence into ``out`` (F, V, 3) float32, keeping each bundle's
    distance before (``before``) and after (``r_final``) the correction (F, M), cm. ``solver`` is the
    :class:`~lgi.solve.solver.LGISolver` whose :class:`Finishing` stage runs it."""

    def __init__(self, solver: Finishing, pos: np.ndarray, fit_pos: np.ndarray, left: np.ndarray | None = None,
                 serial: bool = False) -> None:
        self.solver, self.pos, self.fit_pos, self.left, self.serial = solver, pos, fit_pos, left, serial
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
        """Correct surface ``x`` at the seen bundles by the share of ``resid`` that is the face
        (:meth:`~lgi.solve.noise.NoiseHandling.correction_step`; all of it for exact bundles), but for the far field's
        share t of the global fit, and store it."""
        s, seen = self.solver, self.seen[f]
        step = s.correction_step(resid, None if self.left is None else self.left[f])
        target = np.where(seen[:, None], s.layout.evaluate(x) + step, np.nan)
        s.correct(x, target, seen, self.serial)
        s.correct_far(x, step, seen, 1.0, t, self.serial)
        self.out[f] = x
        self.r_final[f] = np.where(seen, np.linalg.norm(np.nan_to_num(self.pos[f]) - s.layout.evaluate(x), axis=1),
                                   np.nan)

    def frame(self, f: int, shapes: np.ndarray, lam: np.ndarray, jaw: np.ndarray | None,
              share: np.ndarray | None = None) -> None:
        """:meth:`blend` and :meth:`finish` frame f with its own residuals."""
        x, resid, t = self.blend(f, shapes, lam, jaw, share)
        self.before[f] = np.linalg.norm(resid, axis=1)
        self.finish(f, x, resid, t)


def smoothing_reach(smooth: int, jaw_smooth: int | None = None) -> int:
    """How many frames on either side of a frame its finished surface reads the choices of: its blend spans the
    smoothing window, each blend's weights a window more, and the jaw its own window on top."""
    h = smooth // 2 if smooth > 1 else 0
    hj = (smooth if jaw_smooth is None else jaw_smooth) // 2
    return 2 * h + hj


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
