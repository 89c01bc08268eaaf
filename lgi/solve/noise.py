"""The solver's treatment of measurement noise: exact bundles or noisy measurements (given, or estimated from
the shot's trajectories), and the smoothing of noisy trajectories before the frames are fitted."""

from __future__ import annotations

import logging

import numpy as np

from lgi.errors import InputError
from lgi.solve.globalfit import join_gain
from lgi.solve.temporal import NoiseEstimate, denoise_trajectories, estimate_noise, sg_matrix

# With noisy bundles (noise > 0): the share of the remaining bundle residual the correction removes (none:
# what remains after the fit is mostly the noise).
NOISE_GAIN = 0.0
# Estimated noise below this (mm) is treated as none.
NOISE_FLOOR = 0.05

log = logging.getLogger(__name__)


class NoiseHandling:
    """How noisy a shot's bundles are and what the frames are fitted to (:meth:`resolve_noise`, :meth:`denoise`).

    A part of :class:`~lgi.solve.solver.LGISolver`, which composes the stages: its methods read the state that
    ``LGISolver.__init__`` sets up from the index (``_a`` its arrays, ``_basis``, ``_rest``, the natural-neighbour
    pairs ``_pair_i``/``_pair_j``, ``layout``, ``rig``, ``global_fit``, ...).
    """

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
