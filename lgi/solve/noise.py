"""The solver's treatment of measurement noise: exact bundles or noisy measurements (given, or estimated from
the shot's trajectories), and the smoothing of noisy trajectories before the frames are fitted."""

from __future__ import annotations

import logging

import numpy as np

from lgi.errors import InputError
from lgi.solve.globalfit import join_gain
from lgi.solve.temporal import NoiseEstimate, denoise_with_model, estimate_noise
from lgi.units import MM_PER_CM

# Bundles whose trajectories, off the face model's fit, change from frame to frame by less than this (mm per
# coordinate) are exact: a hundredth of the least noise a capture system has, where an exact shot's residuals
# (the model's error, which moves with the face) correlate between neighbours like independent poses' do.
EXACT_NOISE_MM = 1e-3

# The noise left in smoothed positions as the correction's gain counts it, over what the windows' own share says.
# The smoothed positions' error is 1.2-1.9x that share in variance (the windows chosen where the noise looked
# smooth, the runs' ends; per axis at 0.01-0.3 mm, isotropic and stereo), and a residual pooled over a frame's
# bundles is a noisy estimate of what is left beyond it. Measured (synthetic actor, 5 % missing; LGI / the smoothed
# fit at 0.02 / 0.05 / 0.3 mm): 1 gave 0.83 / 0.95 / 1.10; 2: 0.806 / 0.885 / 1.026; 3: 0.799 / 0.904 / 1.007;
# 6: 0.810 / 0.957 / 1.001.
NOISE_LEFT_MARGIN = 2.5

log = logging.getLogger(__name__)


class NoiseHandling:
    """How noisy a shot's bundles are and what the frames are fitted to (:meth:`resolve_noise`, :meth:`denoise`).

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...).
    """

    def model_fit(self, positions: np.ndarray) -> tuple[np.ndarray, float]:
        """Each frame's global fit (:class:`~lgi.solve.globalfit.GlobalFit`, from the previous frame's) as bundle
        positions (F, M, 3) cm, and the fit's mean leverage: its free parameters (weights strictly inside their
        bounds, and the jaw's when estimated) over the seen coordinates."""
        p = np.asarray(positions, np.float64)
        out = np.empty_like(p)
        lev = np.zeros(len(p))
        init = None
        jaw = 4 if self.rig is not None and self.global_fit.jaw_observable else 0
        for f in range(len(p)):
            if not np.isfinite(p[f]).all(axis=1).any():
                out[f] = np.nan
                continue
            init = self.global_fit.solve(p[f], init=init)
            out[f] = self.global_fit.predict(init.weights, init.jaw)
            free = int(np.sum((init.weights > 1e-9) & (init.weights < 1 - 1e-9))) + jaw
            lev[f] = free / max(3 * int(np.isfinite(p[f]).all(axis=1).sum()), 1)
        return out, float(np.clip(np.mean(lev), 0.0, 0.9))

    def denoise(self, positions: np.ndarray) -> np.ndarray:
        """The positions the frames are fitted to: with noisy bundles (``noise`` > 0) each marker's trajectory
        smoothed in two parts, the face model's fit and what it leaves (:func:`lgi.solve.temporal.denoise_with_model`);
        the noise left after it (``noise_left``, (F, M, 3) cm^2) sets how far the surface is taken through each
        bundle (:meth:`correction_gain`). Exact bundles are returned as they are."""
        self.denoise_windows = None
        self.noise_left = None
        self.global_fit.gain = join_gain(self.noise)
        if self.noise <= 0:
            return positions
        model = self._model
        if model is None or model[0] is not positions:
            model = (positions, *self.model_fit(positions))
        out, left, windows = denoise_with_model(positions, model[1], self.noise_axes, model[2])
        self.denoise_windows = windows
        self.noise_left = left
        fit_noise = float(np.sqrt(np.nanmean(left))) * MM_PER_CM
        self.global_fit.gain = join_gain(fit_noise)
        log.info("noisy bundles smoothed (the face model's fit and what it leaves): about %.4f mm noise left per "
                 "coordinate", fit_noise)
        return out

    def set_noise(self, noise_mm: float | np.ndarray) -> None:
        """Treat the bundles as exact (0) or as measurements with this noise (mm per coordinate, or (3,) per axis of
        the bundles' frame)."""
        axes = np.broadcast_to(np.asarray(noise_mm, np.float64), (3,)).copy()
        if not np.all(np.isfinite(axes)) or np.any(axes < 0):
            raise InputError(f"noise must be a finite number of mm >= 0, not {noise_mm}")
        self.noise_axes = axes
        self.noise = float(np.sqrt(np.mean(axes**2)))
        self.global_fit.gain = join_gain(self.noise)
        self.noise_left = None
        self._model = None
        # A marker seen by one camera stands on its ray; with noisy bundles its point is fitted like them.
        self.noise_gain = 1.0 if self.noise == 0 else 0.0

    def correction_gain(self, resid: np.ndarray, left: np.ndarray | None) -> np.ndarray | float:
        """How far a frame's surface is taken through each bundle: 1 for exact bundles; for measurements, per
        bundle and axis, the share of the blend's residual that is the face and not the noise left,
        ``m^2 / (m^2 + n^2)`` (a Wiener gain), with ``n^2`` the noise left at the bundle (``left``) and ``m^2`` the
        frame's mean squared residual beyond the noise, per axis, over its seen bundles.

        Parameters
        ----------
        resid : (M, 3) float, cm
            The blend's residuals to the positions it was fitted to (NaN: missing).
        left : (M, 3) float, cm^2, or None
            The noise variance left in those positions (None: exact).
        """
        if left is None:
            return 1.0
        ok = np.all(np.isfinite(resid), axis=1)
        if not ok.any():
            return 1.0
        left = left * NOISE_LEFT_MARGIN
        m2 = np.maximum(np.mean(resid[ok] ** 2, axis=0) - np.mean(left[ok], axis=0), 0.0)
        return m2 / np.maximum(m2 + left, 1e-300)

    def resolve_noise(self, positions: np.ndarray, noise: float | str = "auto") -> NoiseEstimate | None:
        """Set the solver's noise for a shot (F, M, 3): a given value (mm) or "auto", estimated per axis from the
        shot's trajectories off the face model's fit of each frame (:func:`lgi.solve.temporal.estimate_noise`).
        Where what the fit leaves changes together at neighbouring markers (independent poses rather than a
        performance), the bundles are exact. Returns the estimate (None for a given value); the decision is
        logged."""
        if noise != "auto":
            try:
                value = float(noise)
            except (TypeError, ValueError):
                raise InputError(f"noise must be a number of mm or 'auto', not {noise!r}") from None
            self.set_noise(value)
            self.noise_estimate = None
            self.independent_poses = False
            return None
        fitted, leverage = self.model_fit(positions)
        est = estimate_noise(positions, self._nb_pairs, fitted, leverage)
        self.noise_estimate = est
        self.independent_poses = bool(np.isfinite(est.noise_mm) and est.noise_mm >= EXACT_NOISE_MM and not est.is_noise)
        if not np.isfinite(est.noise_mm):
            # A fallback the user must hear of: noisy bundles taken as exact make a surface that chases the noise.
            log.warning("the bundle noise cannot be estimated (no marker is seen for 7 frames in a row): bundles "
                        "treated as exact; give --noise MM if they are not")
            self.set_noise(0.0)
        elif est.noise_mm < EXACT_NOISE_MM:
            log.info("the bundles change from frame to frame by %.5f mm beyond the face model's fit: exact",
                     est.noise_mm)
            self.set_noise(0.0)
        elif not est.is_noise:
            log.warning("the bundles change from frame to frame by %.4f mm (median, per coordinate) beyond the face "
                        "model's fit, and neighbouring markers change together (correlation %.2f): that is motion "
                        "(independent poses?), not measurement noise, so the bundles are treated as exact; give the "
                        "noise if they are measurements", est.noise_mm, est.coherence)
            self.set_noise(0.0)
        else:
            log.info("bundle noise estimated at %.4f mm per coordinate (x %.4f, y %.4f, z %.4f; %d residuals, "
                     "neighbour correlation %.2f)", est.noise_mm, *est.axis_mm, est.samples, est.coherence)
            self.set_noise(est.axis_mm)
            self._model = (positions, fitted, leverage)
        return est
