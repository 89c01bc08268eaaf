"""The solver's treatment of measurement noise: exact bundles or noisy measurements (given, or estimated from
the shot's trajectories), and the smoothing of noisy trajectories before the frames are fitted."""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.io.stored import ScratchArray, StoredArray
from lgi.solve.globalfit import EXACT_GAIN, FitStore, join_gain
from lgi.solve.streamed import frame_blocks, row_reader, same_rows, streamed_sum
from lgi.solve.temporal import MIN_SMOOTHED_FRAMES, NoiseEstimate, estimate_noise, model_denoised_blocks
from lgi.threads import one_blas_thread
from lgi.units import MM_PER_CM

# Bundles whose trajectories, off the face model's fit, change from frame to frame by less than this (mm per
# coordinate) are exact: a hundredth of the least noise a capture system has, where an exact shot's residuals
# (the model's error, which moves with the face) correlate between neighbours like independent poses' do.
EXACT_NOISE_MM = 1e-3

# The noise left in smoothed positions as the correction's gain counts it, over what the windows' own share says.
# The smoothed positions' error is 1.2-1.9x that share in variance (the windows chosen where the noise looked
# smooth, the runs' ends; per axis at 0.01-0.3 mm, isotropic and stereo), and a residual pooled over a frame's
# bundles is a noisy estimate of what is left beyond it. Measured (synthetic actor, 5 % missing; LGI / the smoothed
# fit at 0.02 / 0.05 / 0.3 mm, before the local fits' James-Stein shrink and GAIN_Z: the trend, not the final
# figures): 1 gave 0.83 / 0.95 / 1.10; 2: 0.806 / 0.885 / 1.026; 3: 0.799 / 0.904 / 1.007; 6: 0.810 / 0.957 / 1.001.
NOISE_LEFT_MARGIN = 2.5

# Standard errors of the frame's mean squared residual taken off the face's share of it (see correction_step).
# Measured (LGI / the smoothed fit, 0.02 and 0.1 mm, 5 % missing): 0 gave 0.801 / 0.995 on the synthetic actor,
# 1.020 / 1.016 on ICT with combinations (whose rigged fit is exact: every step is noise), 0.959 / 1.023 on the
# 400-scan session; 2 gave 0.798 / 0.993, 1.018 / 1.013 and 0.957 / 1.010.
GAIN_Z = 2.0
# The fit's leverage is averaged over about this many frames spread over the shot (a marker's share changes
# slowly with the expression; over a 1000-frame shot a fifth of the cost). A marker seen in none of them takes
# the mean marker's.
LEVERAGE_FRAMES = 200
# A marker whose noise variance is this many times the median marker's is left out of the fits and the correction.
NOISE_LEFT_OUT = 100.0

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class ShotNoise:
    """The bundles' noise as the solver's stages read it: a value, made by :meth:`NoiseHandling.resolve_noise`,
    :meth:`NoiseHandling.noise_from_covariance` or :meth:`uniform`, completed by :meth:`NoiseHandling.denoise`,
    and handed to a solver with :meth:`~lgi.solve.solver.LGISolver.with_noise`.

    Attributes
    ----------
    axes : (3,) float, mm
        The noise per coordinate along the bundles' axes (the median marker's when per marker); zeros: exact.
    sigma : (M, 3) float, mm
        Each marker's noise along its own axes.
    rotations : (M, 3, 3) float or None
        Rows: each marker's noise axes (None: the bundles' own axes).
    dropped : (M,) bool
        Markers left out of the fits and the correction for their noise.
    estimate
        The estimate the noise was taken from (``--noise auto``; None when given).
    independent_poses : bool
        The frames change like independent poses, not a performance (their gaps are not bridged).
    left : (F, M, 3) float, cm^2, or None
        The noise variance left in the smoothed positions along each marker's axes (after :meth:`denoise`).
    windows : (F, M, 3) int or None
        The smoothing windows chosen (after :meth:`denoise`).
    fit_noise : float, mm, or None
        The noise left in the smoothed positions, pooled (after :meth:`denoise`); sets the global fit's join gain.
    """

    axes: np.ndarray
    sigma: np.ndarray
    dropped: np.ndarray
    rotations: np.ndarray | None = None
    estimate: NoiseEstimate | None = None
    independent_poses: bool = False
    left: StoredArray | None = None
    windows: StoredArray | None = None
    fit_noise: float | None = None
    # The resolve's fit of the shot, (positions, fitted, leverage), which denoise reuses once.
    model: tuple | None = field(default=None, repr=False)
    # An exact shot's (frame numbers, positions, each frame's model fit), which its choice reuses.
    frame_fits: tuple | None = field(default=None, repr=False)

    @classmethod
    def uniform(cls, noise_mm: float | np.ndarray, n_markers: int, **more: Any) -> ShotNoise:
        """Exact bundles (0) or measurements with this noise (mm per coordinate, or (3,) per axis of the
        bundles' frame), the same for every marker."""
        axes = np.broadcast_to(np.asarray(noise_mm, np.float64), (3,)).copy()
        if not np.all(np.isfinite(axes)) or np.any(axes < 0):
            raise InputError(f"noise must be a finite number of mm >= 0, not {noise_mm}")
        return cls(axes, np.tile(axes, (n_markers, 1)), np.zeros(n_markers, bool), **more)

    @property
    def level(self) -> float:
        """mm per coordinate, the root mean square of ``axes``: 0 for exact bundles."""
        return float(np.sqrt(np.mean(self.axes**2)))

    @property
    def join_gain(self) -> float:
        """The global fit's join gain (:func:`~lgi.solve.globalfit.join_gain`) for this noise: from what
        smoothing left when the positions were smoothed, else from the bundles' noise."""
        return join_gain(self.level if self.fit_noise is None else self.fit_noise)

    @property
    def ray_gain(self) -> float:
        """How far a one-camera marker's point is taken onto its ray: all the way for exact bundles; with noisy
        bundles it is fitted like them."""
        return 1.0 if self.level == 0 else 0.0


class NoiseHandling:
    """How noisy a shot's bundles are and what the frames are fitted to (:meth:`resolve_noise`, :meth:`denoise`).

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...). The noise is a value
    (:class:`ShotNoise`): resolving and smoothing a shot return it, and a solver bound to it
    (:meth:`~lgi.solve.solver.LGISolver.with_noise`) reads it as ``shot_noise``.
    """

    @one_blas_thread
    def model_fit(self, positions: np.ndarray, noise: ShotNoise | None = None
                  ) -> tuple[np.ndarray, np.ndarray, FitStore]:
        """Each frame's global fit (:class:`~lgi.solve.globalfit.GlobalFit`, from the previous frame's) of
        ``positions`` (F, M, 3) cm (an array or a :class:`~lgi.io.stored.StoredArray`, read a block at a time) as
        bundle positions (F, M, 3) cm (a :class:`~lgi.io.stored.ScratchArray`; NaN in frames without a bundle),
        and its leverage per marker and axis (M, 3): the share of a coordinate's noise variance the fit takes with
        it (the diagonal of its hat matrix over the free parameters, the weights strictly inside their bounds and
        the jaw's when estimated), averaged over the frames that see it, along each marker's noise axes when they
        are set (``noise``, default the solver's; its left-out markers are not fitted), and each frame's fit
        (:class:`~lgi.solve.globalfit.FitStore`).

        The share is far from uniform: on ICT's rotating jaw it runs from 0.01 to 0.2 (a mean of 0.1), the jaw
        and lip markers holding most. Smoothing every marker's fitted part as if it held the mean left the jaw's
        noise in the fit (0.3 mm, the rigged fit of the smoothed bundles: 0.119 mm against 0.090 per marker)."""
        n_f, n_m = len(positions), positions.shape[1]
        # Written a block at a time, read back by range: a long take's fitted positions wait on disk.
        out = ScratchArray((n_f, n_m, 3), np.float64)
        lev = np.zeros((n_m, 3))
        count = np.zeros(n_m)
        init = None
        noise = self.shot_noise if noise is None else noise
        # Every shape the frame wants joins: what a coarser fit leaves of the motion would be smoothed as noise (the
        # synthetic actor at 0.3 mm: LGI at 1.071x the smoothed fit with a noise-sized join gain, 1.014x exact).
        gf = self.global_fit.with_gain(EXACT_GAIN)
        # Each frame's fit goes to disk as it is made: an exact shot's choice reuses them (:meth:`cached_fits`).
        fits = FitStore(n_f, gf.n_shapes, n_m, gf.rig is not None)
        with_jaw = gf.rig is not None and gf.jaw_observable
        rot = noise.rotations
        stride = max(1, n_f // LEVERAGE_FRAMES)
        for lo, hi in frame_blocks(n_f):
            p = np.array(positions[lo:hi], np.float64)
            p[:, noise.dropped] = np.nan
            o = np.full(p.shape, np.nan)
            for k, f in enumerate(range(lo, hi)):
                seen = np.isfinite(p[k]).all(axis=1)
                if not seen.any():
                    continue
                init = gf.solve(p[k], init=init)
                fits.put(f, init)
                o[k] = gf.predict(init.weights, init.jaw)
                if f % stride == 0:
                    lev[seen] += self._fit_leverage(gf, init, o[k], seen, with_jaw, rot)
                    count[seen] += 1
            out.write(lo, o)
        fits.flush()
        sampled = count > 0
        if not sampled.any():
            return out, np.zeros((n_m, 3)), fits
        lev[sampled] /= count[sampled, None]
        lev[~sampled] = np.mean(lev[sampled], axis=0)
        return out, np.clip(lev, 0.0, 0.9), fits

    @staticmethod
    def _fit_leverage(gf, fit, at: np.ndarray, seen: np.ndarray, with_jaw: bool, rot: np.ndarray | None
                      ) -> np.ndarray:
        """(n, 3) the hat matrix's diagonal of one frame's fit by ``gf`` (``at``: its bundle positions, (M, 3) cm)
        at its ``seen`` markers, per axis (of each marker's noise, with ``rot``): the fit's Jacobian over its free
        parameters (a free shape's displacement, skinned; the jaw's by a finite difference)."""
        free = np.flatnonzero((fit.weights > 1e-9) & (fit.weights < 1 - 1e-9))
        cols = gf.basis[free][:, seen]  # (k, n, 3)
        if gf.rig is not None:
            maps = gf.rig.blend_matrices(fit.jaw, gf.bw)[seen, :, :3]
            cols = np.einsum("mij,kmj->kmi", maps, cols)
        if with_jaw:
            step = 1e-4
            jac = []
            for k in range(len(fit.jaw)):
                d = np.zeros(len(fit.jaw))
                d[k] = step
                jac.append((gf.predict(fit.weights, fit.jaw + d)[seen] - at[seen]) / step)
            cols = np.concatenate([cols, np.asarray(jac)], axis=0)
        n = int(seen.sum())
        if not len(cols):
            return np.zeros((n, 3))
        # The hat matrix J (J'J + R)^-1 J' with the fit's ridge R on the weights (none on the jaw): rows of
        # J L^-T, with L the Cholesky factor of J'J + R.
        jac = cols.reshape(len(cols), -1)
        reg = np.full(len(cols), gf.l2)
        reg[len(free):] = 0.0
        gram = jac @ jac.T + np.diag(reg)
        gram[np.diag_indices_from(gram)] += 1e-12 * np.trace(gram)
        q = np.linalg.solve(np.linalg.cholesky(gram), jac).T.reshape(n, 3, -1)
        if rot is not None:
            q = np.einsum("mij,mjk->mik", rot[seen], q)
        return np.sum(q**2, axis=2)

    @one_blas_thread
    def denoise(self, positions: np.ndarray, noise: ShotNoise | None = None) -> tuple[np.ndarray, ShotNoise]:
        """The positions the frames are fitted to, and the noise completed with what smoothing left.

        With noisy bundles (``noise``, default the solver's, with a level above 0) each marker's trajectory is
        smoothed in two parts, the face model's fit and what it leaves (:func:`lgi.solve.temporal.denoise_with_model`);
        the noise left after it (``left``, (F, M, 3) cm^2) sets how far the surface is taken through each bundle
        (:meth:`correction_step`), and its pooled size the global fit's join gain. Exact bundles are returned as
        they are."""
        noise = self.shot_noise if noise is None else noise
        # The resolve's fit is used once: a long take's fitted positions are not held past here.
        model = noise.model
        noise = dataclasses.replace(noise, left=None, windows=None, fit_noise=None, model=None)
        if noise.level <= 0:
            return positions, noise
        n_f = len(positions)
        seen = sum((np.all(np.isfinite(positions[lo:hi]), axis=2).sum(axis=0) for lo, hi in frame_blocks(n_f)),
                   start=np.zeros(positions.shape[1], np.int64))
        short = int((seen < MIN_SMOOTHED_FRAMES).sum())
        if short:
            # Their trajectories are left as they are: the surface is still held off their bundles by the noise.
            log.warning("%d of %d markers are seen in fewer than %d frames: too few to smooth their noisy "
                        "trajectories, which are fitted frame by frame", short, len(seen), MIN_SMOOTHED_FRAMES)
        # The shot's noise was resolved on these positions before its gaps were bridged (a copy): reuse that fit.
        if model is None or not same_rows(model[0], positions):
            model = (positions, *self.model_fit(positions, noise)[:2])
        rot = noise.rotations
        into = None if rot is None else (lambda x: np.einsum("mij,fmj->fmi", rot, x))
        # Smoothed a block at a time into files read a block at a time by the choice and the finish: a long take's
        # would not fit in memory. Each marker's trajectory is smoothed in its noise's principal axes (its
        # covariance's), where the axes are apart.
        out = ScratchArray((n_f, *positions.shape[1:]), np.float64)
        left = ScratchArray(out.shape, np.float64)
        windows = ScratchArray(out.shape, np.int64)
        for lo, _, smoothed, lf, win in model_denoised_blocks(positions, model[1], noise.sigma, model[2], into):
            out.write(lo, smoothed if rot is None else np.einsum("mji,fmj->fmi", rot, smoothed))
            left.write(lo, lf)
            windows.write(lo, win)
        del model
        # np.nanmean(left), bit for bit: numpy's sum of the left with its NaN as 0, over the count of the others
        read = row_reader(left, lambda x: np.where(np.isnan(x), 0.0, x))
        given = sum((int(np.count_nonzero(~np.isnan(left[lo:hi]))) for lo, hi in frame_blocks(n_f)), start=0)
        fit_noise = float(np.sqrt(streamed_sum(read, int(np.prod(out.shape))) / given)) * MM_PER_CM
        log.info("noisy bundles smoothed (the face model's fit and what it leaves): about %.4f mm noise left per "
                 "coordinate", fit_noise)
        return out, dataclasses.replace(noise, left=left, windows=windows, fit_noise=fit_noise)

    def noise_from_covariance(self, covariance: np.ndarray) -> ShotNoise:
        """The bundles' noise from their covariances (F, M, 3, 3) or (M, 3, 3), cm^2 (NaN where not given): each
        marker's median over the frames, in its principal axes; a marker without any takes the median marker's.
        Markers whose noise is far above the shot's (``NOISE_LEFT_OUT`` times the median variance) are left out
        of the fits and the correction (``dropped``); the others weigh alike."""
        cov = np.asarray(covariance, np.float64)
        if cov.ndim == 3:
            per_marker = cov
        else:
            with warnings.catch_warnings():  # a marker never given: all NaN, filled below
                warnings.simplefilter("ignore", RuntimeWarning)
                per_marker = np.nanmedian(cov, axis=0)
        given = np.isfinite(per_marker).all(axis=(1, 2))
        if not given.any():
            raise InputError("no bundle covariance given")
        per_marker = np.where(given[:, None, None], per_marker, np.median(per_marker[given], axis=0))
        lam, vec = np.linalg.eigh(0.5 * (per_marker + np.transpose(per_marker, (0, 2, 1))))
        sigma = np.sqrt(np.maximum(lam, 0.0)) * MM_PER_CM
        axes = np.sqrt(np.maximum(np.median(np.diagonal(per_marker, axis1=1, axis2=2), axis=0), 0.0)) * MM_PER_CM
        var = np.mean(sigma**2, axis=1)
        dropped = var > NOISE_LEFT_OUT * max(float(np.median(var)), 1e-30)
        if dropped.any():
            names = [self.index.marker_names[i] for i in np.flatnonzero(dropped)]
            log.warning("%d markers are noisier than %g times the median marker (%s): left out of the fits and not "
                        "passed through; their points follow their neighbours", len(names), NOISE_LEFT_OUT,
                        ", ".join(names[:5]) + (" ..." if len(names) > 5 else ""))
        return ShotNoise(axes, sigma, dropped, np.transpose(vec, (0, 2, 1)))

    @staticmethod
    def _face_variance(resid: np.ndarray, left: np.ndarray) -> np.ndarray:
        """(3,) cm^2: per axis, the mean squared residual (N, 3) beyond the noise left (N, 3) over N bundles, less
        its standard error (the mean of N squared residuals scatters by sqrt(2 / N) of itself), so that what the
        noise alone gives does not pass for the face."""
        e2 = np.mean(resid**2, axis=0)
        return np.maximum(e2 - np.mean(left, axis=0) - GAIN_Z * np.sqrt(2.0 / max(len(resid), 1)) * e2, 0.0)

    def correction_step(self, resid: np.ndarray, left: np.ndarray | None) -> np.ndarray:
        """How far a frame's surface is moved at each bundle toward it: all of its residual for exact bundles; for
        measurements, per bundle and noise axis, the share of the blend's residual that is the face and not the
        noise left, ``m^2 / (m^2 + n^2)`` (a Wiener gain), with ``n^2`` the noise left at the bundle (``left``,
        counted with ``NOISE_LEFT_MARGIN``) and ``m^2`` the frame's mean squared residual beyond the noise, per
        axis, over its seen bundles. Bundles left out for their noise are not moved toward.

        Parameters
        ----------
        resid : (M, 3) float, cm
            The blend's residuals to the positions it was fitted to (NaN: missing).
        left : (M, 3) float, cm^2, or None
            The noise variance left in those positions along each marker's noise axes (None: exact).

        Returns
        -------
        (M, 3) float64, cm (0 where missing)
        """
        r = np.nan_to_num(np.asarray(resid, np.float64))
        ok = np.all(np.isfinite(resid), axis=1) & ~self.shot_noise.dropped
        if left is None:
            return np.where(ok[:, None], r, 0.0)
        rot = self.shot_noise.rotations
        if rot is not None:
            r = np.einsum("mij,mj->mi", rot, r)
        if not ok.any():
            return np.zeros_like(r)
        left = left * NOISE_LEFT_MARGIN
        m2 = self._face_variance(r[ok], left[ok])
        step = np.where(ok[:, None], m2 / np.maximum(m2 + left, 1e-300) * r, 0.0)
        return step if rot is None else np.einsum("mji,mj->mi", rot, step)

    def resolve_noise(self, positions: np.ndarray, noise: float | str = "auto") -> ShotNoise:
        """A shot's noise (F, M, 3): a given value (mm) or "auto", estimated per axis from the shot's trajectories
        off the face model's fit of each frame (:func:`lgi.solve.temporal.estimate_noise`). Where what the fit
        leaves changes together at neighbouring markers (independent poses rather than a performance), the
        bundles are exact. The decision is logged; the estimate is the value's ``estimate`` (None for a given
        value)."""
        n_m = self.index.n_markers
        if noise != "auto":
            try:
                value = float(noise)
            except (TypeError, ValueError):
                raise InputError(f"noise must be a number of mm or 'auto', not {noise!r}") from None
            return ShotNoise.uniform(value, n_m)
        # Fitted with every marker in the bundles' own axes: the shot's noise is not known yet.
        fitted, leverage, fits = self.model_fit(positions, ShotNoise.uniform(0.0, n_m))
        est = estimate_noise(positions, self._nb_pairs, fitted, leverage)
        found = {"estimate": est,
                 "independent_poses": bool(np.isfinite(est.noise_mm) and est.noise_mm >= EXACT_NOISE_MM
                                           and not est.is_noise)}
        if not np.isfinite(est.noise_mm):
            # A fallback the user must hear of: noisy bundles taken as exact make a surface that chases the noise.
            log.warning("the bundle noise cannot be estimated (no marker is seen for 13 frames in a row): bundles "
                        "treated as exact; give --noise MM if they are not")
        elif est.noise_mm < EXACT_NOISE_MM:
            log.info("the bundles change from frame to frame by %.5f mm beyond the face model's fit: exact",
                     est.noise_mm)
        elif not est.is_noise:
            log.warning("the bundles change from frame to frame by %.4f mm (median, per coordinate) beyond the face "
                        "model's fit, and neighbouring markers change together (correlation %.2f): that is motion "
                        "(independent poses?), not measurement noise, so the bundles are treated as exact; give the "
                        "noise if they are measurements", est.noise_mm, est.coherence)
        else:
            log.info("bundle noise estimated at %.4f mm per coordinate (x %.4f, y %.4f, z %.4f; %d residuals, "
                     "neighbour correlation %.2f)", est.noise_mm, *est.axis_mm, est.samples, est.coherence)
            return ShotNoise.uniform(est.axis_mm, n_m, model=(positions, fitted, leverage), **found)
        # Exact bundles are chosen from the same fit of the same positions: the choice takes it (see
        # :meth:`cached_fits`; :meth:`prepare_shot` names the frames) instead of solving every frame twice. The
        # positions and fits wait on disk (a long take's would not fit in memory).
        stored = positions if isinstance(positions, StoredArray) else ScratchArray.of(positions)
        return ShotNoise.uniform(0.0, n_m, frame_fits=(None, stored, fits), **found)

    def cached_fits(self, positions: np.ndarray, frames: np.ndarray) -> list:
        """Per frame of ``positions`` (F, M, 3) cm, numbered ``frames``, the global fit that resolving an exact
        shot made of the same frame (:meth:`resolve_noise` through ``prepare_shot``); None where there is none
        or the frame's bundles differ from those fitted (a bridged gap). Reads only these frames' fits."""
        cache = self.shot_noise.frame_fits
        if cache is None or cache[0] is None or self.shot_noise.level != 0:
            return [None] * len(positions)
        shot_frames, fitted, store = cache
        shot_frames, frames = np.asarray(shot_frames, np.int64), np.asarray(frames, np.int64)
        if len(shot_frames) > 1 and not np.all(np.diff(shot_frames) > 0):  # numbered out of order: the last row
            row = {int(f): r for r, f in enumerate(shot_frames)}
            at = np.array([row.get(int(f), 0) for f in frames], np.int64)
        else:
            at = np.minimum(np.searchsorted(shot_frames, frames), len(shot_frames) - 1)
        known = shot_frames[at] == frames
        out: list = [None] * len(positions)
        if not known.any():
            return out
        rows = at[known]
        same = np.flatnonzero(known)
        fits = store.take(rows)
        given = fitted[rows]
        for k, q, fit, g in zip(same, np.asarray(positions)[same], fits, given, strict=True):
            if np.array_equal(q, g, equal_nan=True):
                out[k] = fit
        return out
