"""A frame's jaw and global shape weights, fitted together to all its bundles.

Every bundle carries the jaw by its rig weight, and every shape moves it: the frame is modelled as
``p_i = A_i(theta) (r_i + sum_k w_k b_ki) + t_i`` with ``A_i, t_i`` the bundle's blended skinning map
(:meth:`lgi.jaw.JawRig.blend_matrices`), ``r_i`` its rest position and ``b_ki`` its displacement in the
(unskinned) shape k. The weights are bounded to [0, 1] (a blendshape fit); the jaw is solved with them, so
a lower-lip expression is not mistaken for the jaw and no bundle has to be "rigid" for the jaw to be seen.

For fixed ``theta`` the problem is a bounded linear least-squares problem in ``w``; for fixed ``w`` it is a
small nonlinear problem in ``theta``. :class:`GlobalFit` alternates the two, starting from the previous
frame's solution, and reports how well the jaw is determined by the layout.

Used by the LGI solver as the jaw estimate and as a candidate (and prior) for every bundle, and by the
baselines, so that every method is given the same rig and the same jaw estimate.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from . import _kernels as K
from .jaw import N_PARAMS, JawRig, jaw_matrix, jaw_matrix_derivatives

log = logging.getLogger(__name__)

# Scales of the jaw parameters (deg, deg, deg, cm) for the nonlinear steps: a
# degree of opening moves a chin bundle by about 1.5 mm, as does a 0.15 cm slide.
THETA_SCALE = np.array([1.0, 1.0, 1.0, 0.15])
# A marker "moves with the jaw" from this rig weight on; the jaw is estimated only with 3 such markers.
JAW_MIN_WEIGHT = 0.2
# A shape joins the fit only if it lowers the squared residual by more than this (cm^2): with exact bundles
# 1e-7 cm of residual, so the fit is exact; with noisy ones a share of the noise variance (``join_gain``).
EXACT_GAIN = 1e-14
JOIN_NOISE_SHARE = 0.01


def join_gain(noise_mm: float) -> float:
    """The least gain (cm^2) for which a shape joins the fit of bundles with this noise (mm per coordinate):
    ``JOIN_NOISE_SHARE`` of the noise variance.

    With hundreds of redundant in-betweens the exactly solved noisy fit keeps taking shapes that each lower
    the squared residual by a vanishing amount (fitting the noise), and its working set grows to hundreds of
    shapes (188 ms per frame at 500 ICT shapes). A full noise variance per shape (an Akaike-style penalty)
    made it 17x faster but moved the benchmark's noisy figures by up to 11 % (p95, ICT combinations): shapes
    the bundles barely see still shape the vertices. A hundredth of it keeps every noisy figure within 0.4 %
    of the exact fit's at 24 ms per frame."""
    return max(EXACT_GAIN, JOIN_NOISE_SHARE * (float(noise_mm) / 10.0) ** 2)


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
        the attribute may be changed between frames).
    """

    def __init__(self, table: np.ndarray, rig: JawRig | None = None, bundle_weights: np.ndarray | None = None,
                 l2: float = 1e-6, gain: float = EXACT_GAIN) -> None:
        tab = np.asarray(table, np.float64)
        self.rest = tab[0]
        self.basis = tab[1:] - tab[0][None]  # (S, M, 3)
        self.n_shapes, self.n_markers = self.basis.shape[:2]
        self.rig = rig
        self.l2 = float(l2)
        self.gain = float(gain)
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

    # ------------------------------------------------------------------ the model
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

    def _system(self, p: np.ndarray, seen: np.ndarray, weights: np.ndarray, theta: np.ndarray | None,
                with_jaw: bool, shape_col2: np.ndarray | None = None) -> tuple[np.ndarray, _Linearisation]:
        """Residuals (3m,) of the seen bundles and the linearisation of the model at (theta, weights): the
        jaw's Jacobian rows (per unit of THETA_SCALE) and the shapes' as an operator. ``shape_col2``: the
        shapes' squared column norms from an earlier point of the same frame (they serve only the working
        set's joining test, and a GN step's change of the jaw barely moves them)."""
        seen_idx = np.flatnonzero(seen)
        if self.rig is None:
            rot, trans, bw, t0 = np.eye(3), np.zeros(3), np.zeros(self.n_markers), None
        else:
            t0 = jaw_matrix(theta, self.rig.pivot)[:3]
            rot, trans, bw = np.ascontiguousarray(t0[:, :3]), t0[:, 3].copy(), self.bw
        w = np.asarray(weights, np.float64)
        r = np.empty(3 * len(seen_idx))
        K.global_residual(self.rest, self.basis, seen_idx, w, rot, trans, bw, p, r)
        jaw_rows = np.zeros((0, len(r)))
        if with_jaw:
            nz = np.flatnonzero(w)
            x = self.rest[seen_idx] + np.tensordot(w[nz], self.basis[nz][:, seen_idx], axes=1)
            xh = np.concatenate([x, np.ones((len(x), 1))], axis=1)
            b = bw[seen_idx][:, None]
            jaw_rows = np.empty((N_PARAMS, len(r)))
            for k, dt in enumerate(jaw_matrix_derivatives(theta, self.rig.pivot)):
                jaw_rows[k] = (b * (xh @ (THETA_SCALE[k] * dt).T)).ravel()
        return r, _Linearisation(self.basis, seen_idx, rot, bw, jaw_rows, shape_col2)

    def _gauss_newton(self, p: np.ndarray, seen: np.ndarray, weights: np.ndarray, theta: np.ndarray | None,
                      with_jaw: bool, max_iter: int = 30) -> tuple[np.ndarray, np.ndarray | None]:
        """Minimise |r|^2 + l2 |w|^2 over the weights in [0, 1] (and the jaw) by Gauss-Newton steps, each a
        box-constrained quadratic program (:func:`lgi._kernels.box_qp`) with Levenberg-Marquardt damping.

        Alternating between the jaw and the weights stalls where a shape and the jaw move the same bundles
        (ICT's mouthLowerDown and a degree of opening): each step undoes the other's gain; a joint step
        moves both along that valley. Without the jaw the problem is linear and one step solves it."""
        n_s = self.n_shapes
        nj = N_PARAMS if with_jaw else 0
        w = np.clip(np.asarray(weights, np.float64), 0.0, 1.0)
        th = None if theta is None else np.asarray(theta, np.float64).copy()
        reg = np.zeros(nj + n_s)
        reg[nj:] = self.l2

        def cost(r: np.ndarray, w: np.ndarray) -> float:
            return float(r @ r + self.l2 * (w @ w))

        r, jac = self._system(p, seen, w, th, with_jaw)
        c = cost(r, w)
        mu = 0.0
        for _ in range(max_iter):
            dz = _working_set_step(jac, r, w, nj, reg + mu, gain=self.gain)
            w_new = np.clip(w + dz[nj:], 0.0, 1.0)
            th_new = th if not with_jaw else th + dz[:nj] * THETA_SCALE
            r_new, jac_new = self._system(p, seen, w_new, th_new, with_jaw, jac.shape_col2)
            c_new = cost(r_new, w_new)
            if not with_jaw:
                return w_new, th_new
            if c_new <= c:
                step = max(np.abs(dz[:nj]).max(), np.abs(dz[nj:]).max())
                stalled = c_new > c * (1 - 1e-10)
                w, th, r, jac, c = w_new, th_new, r_new, jac_new, c_new
                mu *= 0.1
                # Stalled: redundant shapes can trade weight without changing the cost, so the step need
                # not vanish; a relative gain of 1e-10 does not move the surface.
                if step < 1e-9 or stalled:
                    break
            else:
                # The jaw is nonlinear: damp toward gradient steps (in the scaled parameters) until it helps.
                mu = max(mu * 10, 1e-6 * float(np.mean(jac.col2)))
                if mu > 1e12:
                    break
        return w, th

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
        w, theta = self._gauss_newton(p, seen, w0, theta, with_jaw)
        if with_jaw:
            # The weights at the final jaw exactly (the joint solve stops at a tolerance).
            w, _ = self._gauss_newton(p, seen, w, theta, False)
        r = np.linalg.norm(self.predict(w, theta) - np.where(seen[:, None], p, 0.0), axis=1)
        r = np.where(seen, r, np.nan)
        source = "" if self.rig is None else ("given" if jaw is not None else "estimated" if with_jaw
                                              else "held at rest (not observable)")
        return GlobalFitResult(w, theta, r, float(np.sqrt(np.nanmean(r**2))) if seen.any() else float("nan"),
                               source)


class _Linearisation:
    """The global fit's Jacobian at one point, as an operator over the variables (jaw parameters first, then
    the shapes): its shape rows are formed only for the working set (:mod:`lgi._kernels` ``global_*``)."""

    def __init__(self, basis: np.ndarray, seen_idx: np.ndarray, rot: np.ndarray, bw: np.ndarray,
                 jaw_rows: np.ndarray, shape_col2: np.ndarray | None = None) -> None:
        self.basis, self.seen_idx, self.rot, self.bw = basis, seen_idx, rot, bw
        self.jaw_rows = jaw_rows
        self.nj = len(jaw_rows)
        self.n = self.nj + len(basis)
        if shape_col2 is None:
            shape_col2 = np.empty(len(basis))
            K.global_col2(basis, seen_idx, rot, bw, shape_col2)
        self.shape_col2 = shape_col2
        self.col2 = np.concatenate([np.einsum("ij,ij->i", jaw_rows, jaw_rows), shape_col2])

    def rows(self, idx: np.ndarray) -> np.ndarray:
        """(len(idx), 3m) Jacobian rows of the variables ``idx`` (sorted: the jaw's first)."""
        idx = np.asarray(idx, np.int64)
        out = np.empty((len(idx), self.jaw_rows.shape[1]))
        jaw = idx < self.nj
        out[jaw] = self.jaw_rows[idx[jaw]]
        shape_rows = np.empty((int((~jaw).sum()), out.shape[1]))
        K.global_rows(self.basis, self.seen_idx, self.rot, self.bw, idx[~jaw] - self.nj, shape_rows)
        out[~jaw] = shape_rows
        return out

    def t_dot(self, v: np.ndarray) -> np.ndarray:
        """(n,) J^T v for a residual-space vector v (3m,)."""
        out = np.empty(self.n)
        out[:self.nj] = self.jaw_rows @ v
        K.global_gradient(self.basis, self.seen_idx, self.rot, self.bw, v, out[self.nj:])
        return out


def _working_set_step(jac: _Linearisation, r: np.ndarray, w: np.ndarray, nj: int, reg: np.ndarray,
                      grow: int = 16, gain: float = EXACT_GAIN) -> np.ndarray:
    """The step dz minimising ``|r + J dz|^2 + sum reg (z + dz)^2`` (z: 0 for the jaw, ``w`` for the weights)
    with ``0 <= w + dz_w <= 1``, solved on a working set of variables.

    With hundreds of shapes, most of them in-betweens of others, the solution uses few; the others sit at a
    bound. The box QP is solved over the jaw, the shapes in use and the ``grow`` shapes whose gradient most
    wants them, then the optimality of every other shape is checked and violators join; the dense problem
    over all shapes (its normal matrix alone is 500^2 x 3M flops) is never formed. It stops when no shape
    outside the set could lower the objective by more than ``gain`` (cm^2, i.e. 1e-7 cm of residual) on its
    own.
    """
    n = jac.n
    z = np.zeros(n)
    z[nj:] = w
    lo = np.full(n, -1e30)
    hi = np.full(n, 1e30)
    lo[nj:] = -w
    hi[nj:] = 1.0 - w
    dz = np.zeros(n)

    rows: dict[int, np.ndarray] = {}

    def working_rows(ws: np.ndarray) -> np.ndarray:
        new = [k for k in ws if k not in rows]
        if new:
            for k, row in zip(new, jac.rows(np.array(new)), strict=True):
                rows[k] = row
        return np.array([rows[k] for k in ws]).reshape(len(ws), len(r))

    def gradient(dz: np.ndarray) -> np.ndarray:
        nz = np.flatnonzero(dz)
        return jac.t_dot(r + dz[nz] @ working_rows(nz)) + reg * (z + dz)

    col2 = jac.col2 + reg
    g = gradient(dz)
    wants = np.where(dz <= lo, -g, np.where(dz >= hi, g, np.abs(g)))
    work = set(range(nj)) | set((nj + np.flatnonzero(w > 0)).tolist())
    work |= set(np.argsort(-wants)[:grow].tolist())
    dropped: set[int] = set()
    for _ in range(50):
        ws = np.array(sorted(work))
        js = working_rows(ws)
        h = js @ js.T + np.diag(reg[ws])
        rhs = -(js @ r) - reg[ws] * z[ws]
        sub = dz[ws]  # warm start: the last round's solution, zero for the newcomers
        # The QP's objective is half of this one: the same gain threshold for releasing a bound.
        K.box_qp(h, rhs, lo[ws], hi[ws], sub, 0, 1e-13, 0.5 * gain)
        dz[:] = 0.0
        dz[ws] = sub
        g = gradient(dz)
        out = np.ones(n, bool)
        out[ws] = False
        # Outside the set a variable sits at its starting value: optimal only at a bound the gradient
        # pushes it against (weights at 0 with g >= 0, at 1 with g <= 0).
        at_lo = out & (dz <= lo + 1e-15)
        at_hi = out & (dz >= hi - 1e-15)
        # A shape joins only if moving it alone would lower the objective by more than ``gain`` (cm^2): with
        # redundant shapes the ridge alone would otherwise pull in every in-between, each for a vanishing gain.
        pull = np.where(at_lo, np.maximum(-g, 0.0), np.where(at_hi, np.maximum(g, 0.0), np.abs(g)))
        bad = out & (pull**2 > gain * col2)
        if not bad.any():
            return dz
        viol = np.flatnonzero(bad)
        # Shapes of the set that ended at zero with the gradient holding them there leave it: the set
        # stays as small as the solution's support plus the newcomers.
        idle = {k for k in ws if k >= nj and dz[k] <= lo[k] + 1e-15 and g[k] >= 0.0} - dropped
        work -= idle
        dropped |= idle  # a shape leaves at most once per step: no cycling
        work |= set(viol[np.argsort(-np.abs(g[viol]))[:grow]].tolist())
    return dz
