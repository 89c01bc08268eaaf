"""Head stabilisation of triangulated bundles: remove head and helmet motion per frame.

Per frame, the neutral marker layout is fitted rigidly (robust, weighted: :func:`lgi.dataset.stabilise.rigid_fit`)
to the stable markers, and the frame is mapped back into the head frame. Which markers are stable is
measured on the shot itself: a robust fit of all markers gives each marker's residual over the shot (its
non-rigid motion); the fifth that move least get weights ``1 / (1 + (r / r0)^2)``, the fit is redone on
them and the residuals measured again, until the set settles (a few rounds). On the synthetic actor it
settles on the nose bridge, upper cheeks and under-eye markers, which is where the truth is rigid.
"""

from __future__ import annotations

import numpy as np

from lgi.dataset.stabilise import rigid_fit


def stabilise_bundles(X: np.ndarray, layout: np.ndarray, stable_fraction: float = 0.2, min_stable: int = 6,
                      stable: np.ndarray | None = None, iterations: int = 8
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

    def fit_all(w: np.ndarray, robust: bool = True):
        R = np.full((F, 3, 3), np.nan)
        t = np.full((F, 3), np.nan)
        for f in range(F):
            s = seen[f] & (w > 0)
            if s.sum() < 3:
                continue
            fit = rigid_fit(layout[s], X[f, s], weights=w[s], robust=robust)
            R[f], t[f] = fit.rotation, fit.translation
        return R, t

    if stable is None:
        # Alternate: fit on the current stable set, measure every marker's residual over the shot, keep the
        # markers that move least. Starts from all markers (the robust fit discounts the moving ones).
        w = np.ones(M)
        k = min(max(int(round(stable_fraction * M)), min_stable), M)
        for it in range(iterations):
            R, t = fit_all(w, robust=it == 0)  # later rounds fit only the (weighted) stable set
            res = np.linalg.norm(np.einsum("fij,mj->fmi", R, layout) + t[:, None] - X, axis=2)
            ok = seen & np.isfinite(res)
            n_seen = ok.sum(axis=0)
            r = np.sqrt(np.where(ok, res, 0.0) ** 2).sum(axis=0) / np.maximum(n_seen, 1)
            r = np.where(n_seen >= 0.5 * F, r, np.inf)  # rarely seen markers cannot anchor the head
            cut = np.sort(r)[k - 1]
            r0 = max(float(np.median(r[r <= cut])), 1e-6)
            w_new = np.where(r <= cut, 1.0 / (1.0 + (r / r0) ** 2), 0.0)
            if np.allclose(w_new, w):
                break
            w = w_new
    else:
        w = np.asarray(stable, bool).astype(np.float64)
    R, t = fit_all(w)
    Xh = np.einsum("fmi,fij->fmj", X - t[:, None], R)  # R^T (x - t)
    return Xh, R, t, w
