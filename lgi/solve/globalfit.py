"""A frame's jaw and global shape weights, fitted together to all its bundles.

Every bundle carries the jaw by its rig weight, and every shape moves it: the frame is modelled as
``p_i = A_i(theta) (r_i + sum_k w_k b_ki) + t_i`` with ``A_i, t_i`` the bundle's blended skinning map
(:meth:`lgi.solve.jaw.JawRig.blend_matrices`), ``r_i`` its rest position and ``b_ki`` its displacement in the
(unskinned) shape k. The weights are bounded to [0, 1] (a blendshape fit); the jaw is solved with them, so
a lower-lip expression is not mistaken for the jaw and no bundle has to be "rigid" for the jaw to be seen.

For fixed ``theta`` the problem is a bounded linear least-squares problem in ``w``; for fixed ``w`` it is a
small nonlinear problem in ``theta``. :class:`GlobalFit` alternates the two, starting from the previous
frame's solution, and reports how well the jaw is determined by the layout.

Used by the LGI solver as the jaw estimate and as a candidate (and prior) for every bundle, and by the
baselines, so that every method is given the same rig and the same jaw estimate.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass

import numpy as np

from lgi.io.stored import ScratchArray
from lgi.solve import _globalfit_kernels as K
from lgi.solve.jaw import N_PARAMS, JawRig
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

# Scales of the jaw parameters (deg, deg, deg, cm) for the nonlinear steps: a
# degree of opening moves a chin bundle by about 1.5 mm, as does a 0.15 cm slide.
THETA_SCALE = np.array([1.0, 1.0, 1.0, 0.15])
# A marker "moves with the jaw" from this rig weight on; the jaw is estimated only with 3 such markers.
JAW_MIN_WEIGHT = 0.2
# A shape joins the fit only if it lowers the squared residual by more than this (cm^2): with exact bundles
# 1e-7 cm of residual, so the fit is exact; with noisy ones a share of the noise variance (``join_gain``).
EXACT_GAIN = 1e-14
JOIN_NOISE_SHARE = 1e-4
# Shapes that join the working set per round: those whose gradient most wants them. 6 made the fit 5-15 %
# faster but moved the held-out ICT poses' figures by 2 % RMS and 47 % at the maximum (the exact fit's
# minimisers are not unique among in-betweens, and the set's path picks one).
WORKING_SET_GROW = 16
MAX_STEPS = 30  # Gauss-Newton steps per frame


def join_gain(noise_mm: float) -> float:
    """The least gain (cm^2) for which a shape joins the fit of bundles with this noise (mm per coordinate):
    ``JOIN_NOISE_SHARE`` of the noise variance.

    With hundreds of redundant in-betweens the exactly solved noisy fit keeps taking shapes that each lower
    the squared residual by a vanishing amount (fitting the noise), and its working set grows to hundreds of
    shapes (188 ms per frame at 500 ICT shapes). A full noise variance per shape (an Akaike-style penalty)
    made it 17x faster but moved the benchmark's noisy figures by up to 11 % (p95, ICT combinations): shapes
    the bundles barely see still shape the vertices. A hundredth of it kept the first four sets' noisy figures
    within 0.4 % of the exact fit's at 24 ms per frame, but not a capture session's: with 400 scans and no rig
    it left 0.063 mm RMS where the exact fit reaches 0.055 (rig: maximum 0.51 against 0.45 mm). A ten-thousandth
    gives 0.0552 and 0.450, at 11 instead of 10 ms per extra frame on 500 ICT shapes (noisy, 300 frames)."""
    return max(EXACT_GAIN, JOIN_NOISE_SHARE * (float(noise_mm) / MM_PER_CM) ** 2)


@dataclass
class GlobalFitResult:
    """One frame's global fit.

    Attributes
    ----------
    weights : (S,) float64
        Shape weights in [0, 1] (of the index's shapes; unskinned shapes with a rig).
    jaw : (4,) float64 or None
        Jaw parameters (open, yaw, roll deg; forward cm) with a rig.
    residual : (M,) float64, cm
        Distance from each bundle to the fitted model (NaN for missing bundles).
    rms : float, cm
        RMS of ``residual`` over the seen bundles.
    jaw_source : str
        "estimated", "given", "held at rest (not observable)", or "" without a rig.
    """

    weights: np.ndarray
    jaw: np.ndarray | None
    residual: np.ndarray
    rms: float
    jaw_source: str = ""


class FitStore:
    """Each frame's :class:`GlobalFitResult` of a shot, kept on disk (:class:`~lgi.io.stored.ScratchArray`): an
    exact shot's fits are made once, when its noise is resolved, and read back a block at a time when its frames
    are chosen; a long take holds none of them in memory (500 shapes: 7 kB per frame).

    Frames are put in order (:meth:`put`); :meth:`take` gives a block's fits (None where none was put), bit for
    bit as put.
    """

    #: Fits held before they are written.
    BLOCK = 256

    def __init__(self, n_frames: int, n_shapes: int, n_markers: int, jaw: bool) -> None:
        self.weights = ScratchArray((n_frames, n_shapes), np.float64)
        self.residual = ScratchArray((n_frames, n_markers), np.float64)
        self.jaw = ScratchArray((n_frames, N_PARAMS), np.float64) if jaw else None
        self.rms = np.full(n_frames, np.nan)
        #: (F,) index into ``sources`` of each frame's ``jaw_source``; -1 where no fit was put
        self.source = np.full(n_frames, -1, np.int16)
        self.sources: list[str] = []
        self._held: list[tuple[int, GlobalFitResult]] = []

    def put(self, f: int, fit: GlobalFitResult) -> None:
        """Frame f's fit (frames in increasing order)."""
        if fit.jaw_source not in self.sources:
            self.sources.append(fit.jaw_source)
        self.source[f] = self.sources.index(fit.jaw_source)
        self.rms[f] = fit.rms
        self._held.append((f, fit))
        if len(self._held) >= self.BLOCK:
            self.flush()

    def flush(self) -> None:
        """Write the fits held (each run of consecutive frames at once)."""
        held, self._held = self._held, []
        while held:
            n = 1
            while n < len(held) and held[n][0] == held[0][0] + n:
                n += 1
            run, held = held[:n], held[n:]
            self.weights.write(run[0][0], np.stack([fit.weights for _, fit in run]))
            self.residual.write(run[0][0], np.stack([fit.residual for _, fit in run]))
            if self.jaw is not None:
                self.jaw.write(run[0][0], np.stack([fit.jaw for _, fit in run]))

    def take(self, rows: np.ndarray) -> list[GlobalFitResult | None]:
        """The fits of frames ``rows`` (increasing), None where none was put."""
        self.flush()
        rows = np.asarray(rows, np.int64)
        w, r = self.weights[rows], self.residual[rows]
        j = None if self.jaw is None else self.jaw[rows]
        return [None if self.source[f] < 0 else
                GlobalFitResult(w[k], None if j is None else j[k], r[k], float(self.rms[f]),
                                self.sources[self.source[f]]) for k, f in enumerate(rows)]


class GlobalFit:
    """Bounded blendshape fit with an optional jaw solved jointly (see the module docstring).

    Parameters
    ----------
    table : (S + 1, M, 3) float, cm
        Bundle positions on the neutral (row 0) and on every shape (unskinned when there is a rig).
    rig : JawRig, optional
        The jaw rig; with it every frame's jaw is fitted with the weights.
    bundle_weights : (M,) float, optional
        Each bundle's jaw skinning weight (required with a rig).
    l2 : float
        Ridge on the weights (cm^2 per unit weight^2): keeps the fit unique where shapes are redundant at
        the bundles.
    gain : float
        Least decrease of the squared residual (cm^2) for which a shape joins the fit (:func:`join_gain`;
        :meth:`with_gain` gives the same fit with another).
    """

    def __init__(self, table: np.ndarray, rig: JawRig | None = None, bundle_weights: np.ndarray | None = None,
                 l2: float = 1e-6, gain: float = EXACT_GAIN) -> None:
        tab = np.asarray(table, np.float64)
        self.rest = np.ascontiguousarray(tab[0])
        self.basis = np.ascontiguousarray(tab[1:] - tab[0][None])  # (S, M, 3)
        self._prod = K.shape_products(self.basis)
        self.n_shapes, self.n_markers = self.basis.shape[:2]
        self.rig = rig
        self.l2 = float(l2)
        self.gain = float(gain)
        self.grow = WORKING_SET_GROW
        if rig is not None:
            if bundle_weights is None:
                raise ValueError("a rig needs the bundles' jaw weights")
            self.bw = np.asarray(bundle_weights, np.float64)
            moving = self.bw >= JAW_MIN_WEIGHT
            self.jaw_observable = bool(moving.sum() >= 3)
            self.jaw_note = "" if self.jaw_observable else (
                f"only {int(moving.sum())} markers move with the jaw (rig weight >= {JAW_MIN_WEIGHT}; 3 are needed): "
                "the jaw cannot be estimated from this layout and is held at rest unless given")
        else:
            self.bw = None
            self.jaw_observable = False
            self.jaw_note = ""
        # What the compiled fit takes in place of a missing rig: no bundle moves with a jaw.
        self._bw = np.zeros(self.n_markers) if self.bw is None else np.ascontiguousarray(self.bw)
        pivot = np.zeros(3) if rig is None else np.asarray(rig.pivot, np.float64).reshape(3)
        self.model = K.FitModel(self.rest, self.basis, self._prod, pivot, self._bw, rig is not None, THETA_SCALE)

    def with_gain(self, gain: float) -> GlobalFit:
        """The same fit (its arrays shared) with another join gain (cm^2)."""
        out = copy.copy(self)
        out.gain = float(gain)
        return out

    # ------------------------------------------------------------------ the model
    def settings(self) -> K.FitSettings:
        """The compiled fit's settings (``l2``, ``gain`` and ``grow``)."""
        return K.FitSettings(self.l2, self.gain, MAX_STEPS, self.grow)

    def _maps(self, theta: np.ndarray) -> np.ndarray:
        """(M, 3, 4) blended skinning maps of the bundles."""
        if self.rig is None:
            out = np.zeros((self.n_markers, 3, 4))
            out[:, :, :3] = np.eye(3)
            return out
        return self.rig.blend_matrices(theta, self.bw)

    def predict(self, weights: np.ndarray, theta: np.ndarray | None = None) -> np.ndarray:
        """(M, 3) bundle positions of the model, cm."""
        x = self.rest + np.tensordot(np.asarray(weights, np.float64), self.basis, axes=1)
        if self.rig is None:
            return x
        m = self._maps(theta)
        return np.einsum("mij,mj->mi", m[:, :, :3], x) + m[:, :, 3]

    # ------------------------------------------------------------------ frames
    def solve(self, bundles: np.ndarray, jaw: np.ndarray | None = None, init: GlobalFitResult | None = None
              ) -> GlobalFitResult:
        """Fit one frame.

        Parameters
        ----------
        bundles : (M, 3) float, cm
            Bundle positions (rows of NaN: missing).
        jaw : (4,) float, optional
            Given jaw parameters (a tracked jaw): only the weights are fitted.
        init
            The previous frame's result (its jaw starts the alternation).
        """
        p = np.asarray(bundles, np.float64)
        seen = np.all(np.isfinite(p), axis=1)
        theta = None
        if self.rig is not None:
            if jaw is not None:
                theta = np.asarray(jaw, np.float64)
            elif init is not None and init.jaw is not None:
                theta = init.jaw.copy()
            else:
                theta = np.zeros(N_PARAMS)
        w0 = init.weights if init is not None and len(init.weights) == self.n_shapes else np.zeros(self.n_shapes)
        with_jaw = self.rig is not None and jaw is None and self.jaw_observable
        if self.rig is not None and jaw is None and not self.jaw_observable:
            theta = np.zeros(N_PARAMS)
        seen_idx = np.flatnonzero(seen)
        w = np.empty(self.n_shapes)
        th = np.zeros(N_PARAMS) if theta is None else np.asarray(theta, np.float64).copy()
        r = np.empty(3 * len(seen_idx))
        K.global_fit_frame(self.model, self.settings(), seen_idx, np.where(seen[:, None], p, 0.0),
                           np.asarray(w0, np.float64), th.copy(), with_jaw, w, th, r)
        theta = None if theta is None else th
        r = np.linalg.norm(r.reshape(-1, 3), axis=1)
        res = np.full(self.n_markers, np.nan)
        res[seen] = r
        r = res
        source = "" if self.rig is None else ("given" if jaw is not None else "estimated" if with_jaw
                                              else "held at rest (not observable)")
        return GlobalFitResult(w, theta, r, float(np.sqrt(np.nanmean(r**2))) if seen.any() else float("nan"),
                               source)

