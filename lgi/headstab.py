"""Head stabilisation of triangulated bundles: remove head and helmet motion per frame.

Per frame, the neutral marker layout is fitted rigidly (robust, weighted: :func:`lgi.stabilize.rigid_fit`)
to the stable markers, and the frame is mapped back into the head frame. Which markers are stable is
measured on the shot itself: a first robust fit of all markers gives each marker's residual over the
shot (its non-rigid motion); the markers that move least (forehead, nose bridge, temples on a face) get
weights ``1 / (1 + (r / r0)^2)`` and the fit is redone on them.
"""

from __future__ import annotations

import numpy as np

from .stabilize import rigid_fit


def stabilize_bundles(X: np.ndarray, layout: np.ndarray, stable_fraction: float = 0.3, min_stable: int = 6,
                      stable: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Map world-frame bundles into the head frame.

    Parameters
    ----------
    X : (F, M, 3) float, world frame (NaN where not seen)
    layout : (M, 3) float, neutral marker positions in the head frame, same units
    stable : (M,) bool, optional
        Markers known to move rigidly with the skull; found from the shot when omitted.

    Returns
    -------
    Xh : (F, M, 3) float64, head frame
    R, t : (F, 3, 3), (F, 3): head -> world per frame (NaN for frames with too few markers)
    weights : (M,) float64: each marker's weight in the fit
    """
    F, M = X.shape[:2]
    seen = np.all(np.isfinite(X), axis=2)

    def fit_all(w: np.ndarray):
        R = np.full((F, 3, 3), np.nan)
        t = np.full((F, 3), np.nan)
        for f in range(F):
            s = seen[f] & (w > 0)
            if s.sum() < 3:
                continue
            fit = rigid_fit(layout[s], X[f, s], weights=w[s])
            R[f], t[f] = fit.rotation, fit.translation
        return R, t

    if stable is None:
        R, t = fit_all(np.ones(M))
        res = np.linalg.norm(np.einsum("fij,mj->fmi", R, layout) + t[:, None] - X, axis=2)
        n_seen = seen.sum(axis=0)
        r = np.sqrt(np.where(seen, res**2, 0.0).sum(axis=0) / np.maximum(n_seen, 1))
        r = np.where((n_seen > 0) & np.isfinite(r), r, np.inf)
        k = min(max(int(round(stable_fraction * M)), min_stable), M)
        cut = np.sort(r)[k - 1]
        r0 = max(float(np.median(r[r <= cut])), 1e-6)
        w = np.where(r <= cut, 1.0 / (1.0 + (r / r0) ** 2), 0.0)
    else:
        w = np.asarray(stable, bool).astype(np.float64)
    R, t = fit_all(w)
    Xh = np.einsum("fmi,fij->fmj", X - t[:, None], R)  # R^T (x - t)
    return Xh, R, t, w
