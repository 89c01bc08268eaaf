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
from scipy.optimize import least_squares, lsq_linear

from .jaw import N_PARAMS, JawRig, jaw_matrix

log = logging.getLogger(__name__)

# Scales of the jaw parameters (deg, deg, deg, cm) for the nonlinear steps and the determinacy test: a
# degree of opening moves a chin bundle by about 1.5 mm, as does a 0.15 cm slide.
THETA_SCALE = np.array([1.0, 1.0, 1.0, 0.15])


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
    """

    weights: np.ndarray
    jaw: np.ndarray | None
    residual: np.ndarray
    rms: float


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
    iterations : int
        Alternations between the weights and the jaw.
    """

    def __init__(self, table: np.ndarray, rig: JawRig | None = None, bundle_weights: np.ndarray | None = None,
                 l2: float = 1e-6, iterations: int = 4) -> None:
        tab = np.asarray(table, np.float64)
        self.rest = tab[0]
        self.basis = tab[1:] - tab[0][None]  # (S, M, 3)
        self.n_shapes, self.n_markers = self.basis.shape[:2]
        self.rig = rig
        self.l2 = float(l2)
        self.iterations = int(iterations)
        if rig is not None:
            if bundle_weights is None:
                raise ValueError("a rig needs the bundles' jaw weights")
            self.bw = np.asarray(bundle_weights, np.float64)
            self.determinacy = self._determinacy()
        else:
            self.bw = None
            self.determinacy = None

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

    def _weights(self, p: np.ndarray, seen: np.ndarray, theta: np.ndarray | None) -> np.ndarray:
        m = self._maps(theta if theta is not None else np.zeros(N_PARAMS))[seen]
        a = np.einsum("mij,kmj->mik", m[:, :, :3], self.basis[:, seen]).reshape(-1, self.n_shapes)
        b = (p[seen] - np.einsum("mij,mj->mi", m[:, :, :3], self.rest[seen]) - m[:, :, 3]).ravel()
        if self.l2 > 0:
            a = np.vstack([a, np.sqrt(self.l2) * np.eye(self.n_shapes)])
            b = np.concatenate([b, np.zeros(self.n_shapes)])
        return lsq_linear(a, b, bounds=(0.0, 1.0), method="bvls").x

    def _joint(self, p: np.ndarray, seen: np.ndarray, weights: np.ndarray, theta: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Jaw and weights solved together (bounded nonlinear least squares from a starting point).

        Alternating between the two stalls where a shape and the jaw move the same bundles (ICT's
        mouthLowerDown and a degree of opening): each step undoes the other's gain. A joint Gauss-Newton
        step moves both along that valley."""
        rest, basis = self.rest[seen], self.basis[:, seen]
        bw = self.bw[seen]
        n_s = self.n_shapes
        target = p[seen]
        eye = np.eye(4)[:3]
        sq_l2 = np.sqrt(self.l2)

        def unpack(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return z[:N_PARAMS] * THETA_SCALE, z[N_PARAMS:]

        def resid(z: np.ndarray) -> np.ndarray:
            th, w = unpack(z)
            x = rest + np.tensordot(w, basis, axes=1)
            m = (1 - bw)[:, None, None] * eye + bw[:, None, None] * jaw_matrix(th, self.rig.pivot)[:3]
            r = np.einsum("mij,mj->mi", m[:, :, :3], x) + m[:, :, 3] - target
            return np.concatenate([r.ravel(), sq_l2 * w])

        def jac(z: np.ndarray) -> np.ndarray:
            th, w = unpack(z)
            x = rest + np.tensordot(w, basis, axes=1)
            t0 = jaw_matrix(th, self.rig.pivot)[:3]
            m = (1 - bw)[:, None, None] * eye + bw[:, None, None] * t0
            out = np.zeros((3 * len(rest) + n_s, N_PARAMS + n_s))
            xh = np.concatenate([x, np.ones((len(x), 1))], axis=1)
            for k in range(N_PARAMS):
                step = np.zeros(N_PARAMS)
                step[k] = 1e-6 * THETA_SCALE[k]
                dt = (jaw_matrix(th + step, self.rig.pivot)[:3] - t0) / 1e-6  # per unit scaled parameter
                out[:3 * len(rest), k] = (bw[:, None] * (xh @ dt.T)).ravel()
            out[:3 * len(rest), N_PARAMS:] = np.einsum("mij,kmj->mik", m[:, :, :3], basis).reshape(-1, n_s)
            out[3 * len(rest):, N_PARAMS:] = sq_l2 * np.eye(n_s)
            return out

        z0 = np.concatenate([theta / THETA_SCALE, np.clip(weights, 0.0, 1.0)])
        lo = np.concatenate([np.full(N_PARAMS, -np.inf), np.zeros(n_s)])
        hi = np.concatenate([np.full(N_PARAMS, np.inf), np.ones(n_s)])
        z = least_squares(resid, z0, jac=jac, bounds=(lo, hi), method="trf", xtol=1e-10, ftol=1e-12,
                          max_nfev=50).x
        return unpack(z)

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
        w = self._weights(p, seen, theta)
        if self.rig is not None and jaw is None:
            theta, w = self._joint(p, seen, w, theta)
            # The weights at the final jaw exactly (the joint solve stops at a tolerance).
            w = self._weights(p, seen, theta)
        r = np.linalg.norm(self.predict(w, theta) - np.where(seen[:, None], p, 0.0), axis=1)
        r = np.where(seen, r, np.nan)
        return GlobalFitResult(w, theta, r, float(np.sqrt(np.nanmean(r**2))) if seen.any() else float("nan"))

    # ------------------------------------------------------------------ diagnostics
    def _determinacy(self, eps: float = 1e-4) -> np.ndarray:
        """(4,) for each jaw parameter, the share of the bundle motion it causes (at the rest pose) that no
        combination of shapes can reproduce: near 0, the layout cannot tell that parameter from the shapes."""
        m0 = self.predict(np.zeros(self.n_shapes), np.zeros(N_PARAMS)).ravel()
        cols = []
        for k in range(N_PARAMS):
            th = np.zeros(N_PARAMS)
            th[k] = eps * THETA_SCALE[k]
            cols.append((self.predict(np.zeros(self.n_shapes), th).ravel() - m0) / eps)
        j = np.stack(cols, 1)  # (3M, 4), motion per unit scaled parameter
        b = self.basis.reshape(self.n_shapes, -1).T
        q, _ = np.linalg.qr(b)
        out = np.zeros(N_PARAMS)
        for k in range(N_PARAMS):
            n = np.linalg.norm(j[:, k])
            out[k] = np.linalg.norm(j[:, k] - q @ (q.T @ j[:, k])) / n if n > 0 else 0.0
        return out


__all__ = ["GlobalFit", "GlobalFitResult"]
