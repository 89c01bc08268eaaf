"""Temporal treatment of bundle trajectories: bridging short gaps and edge-preserving smoothing."""

from __future__ import annotations

import numpy as np


def bridge_gaps(positions: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill runs of missing frames of each marker by linear interpolation between the frames around them.

    Parameters
    ----------
    positions : (F, M, 3) float
        NaN rows where a marker was not seen.
    max_gap : int
        Longest run (frames) that is filled; longer runs, and runs at either end of the shot, stay
        missing (they are not guessed).

    Returns
    -------
    filled : (F, M, 3) float64
    bridged : (F, M) bool
        Which entries were filled.
    """
    pos = np.array(positions, np.float64)
    n_f, n_m = pos.shape[:2]
    bridged = np.zeros((n_f, n_m), bool)
    if max_gap <= 0:
        return pos, bridged
    seen = np.all(np.isfinite(pos), axis=2)
    for m in range(n_m):
        f = 0
        while f < n_f:
            if seen[f, m]:
                f += 1
                continue
            start = f
            while f < n_f and not seen[f, m]:
                f += 1
            end = f  # first seen frame after the run (or n_f)
            if start == 0 or end == n_f or end - start > max_gap:
                continue
            a, b = pos[start - 1, m], pos[end, m]
            t = (np.arange(start, end) - (start - 1)) / (end - (start - 1))
            pos[start:end, m] = a + t[:, None] * (b - a)
            bridged[start:end, m] = True
    return pos, bridged


def bilateral_filter(positions: np.ndarray, sigma_t: float = 1.5, sigma_r: float = 0.05,
                     rest: np.ndarray | None = None, sigma_s: float | None = None, k: int = 6) -> np.ndarray:
    """Spatio-temporal bilateral filter of bundle trajectories (Bickel et al. 2007, section 3).

    A marker's displacement from its rest position becomes a weighted mean of its own and its nearest
    markers' displacements in nearby frames, with weights
    ``exp(-dt^2 / 2 sigma_t^2) exp(-ds^2 / 2 sigma_s^2) exp(-|d' - d|^2 / 2 sigma_r^2)``: where the skin
    moves fast or differently from its neighbours, far displacements weigh little, so motion is smoothed
    less than noise.

    Parameters
    ----------
    positions : (F, M, 3) float, cm
        NaN where missing (kept missing, and ignored by the others).
    sigma_t : float, frames
    sigma_r : float, cm
        Range scale: displacement differences much larger than this are not averaged.
    rest : (M, 3) float, cm, optional
        Rest positions; with ``sigma_s`` the ``k`` nearest markers (at rest) join the average.
    sigma_s : float, cm, optional
        Spatial scale; without it (or ``rest``) the filter is temporal only.
    """
    pos = np.asarray(positions, np.float64)
    n_f, n_m = pos.shape[:2]
    origin = np.zeros((n_m, 3)) if rest is None else np.asarray(rest, np.float64)
    if rest is not None and sigma_s:
        from scipy.spatial import cKDTree

        dist, nbr = cKDTree(origin).query(origin, k=min(k, n_m))
        ws = np.exp(-(dist**2) / (2 * sigma_s**2))
    else:
        nbr, ws = np.arange(n_m)[:, None], np.ones((n_m, 1))
    disp = pos - origin[None]
    valid = np.all(np.isfinite(pos), axis=2)
    base = np.nan_to_num(disp)
    h = max(1, int(np.ceil(3 * sigma_t)))
    acc = np.zeros_like(base)
    wsum = np.zeros((n_f, n_m))
    for dt in range(-h, h + 1):
        lo, hi = max(0, -dt), min(n_f, n_f - dt)
        wt = np.exp(-(dt**2) / (2 * sigma_t**2))
        for j in range(nbr.shape[1]):
            other = base[lo + dt:hi + dt][:, nbr[:, j]]
            d2 = np.sum((other - base[lo:hi]) ** 2, axis=2)
            w = wt * ws[None, :, j] * np.exp(-d2 / (2 * sigma_r**2)) * valid[lo + dt:hi + dt][:, nbr[:, j]]
            acc[lo:hi] += w[..., None] * other
            wsum[lo:hi] += w
    out = np.full_like(pos, np.nan)
    ok = valid & (wsum > 0)
    out[ok] = origin[None].repeat(n_f, 0)[ok] + acc[ok] / wsum[ok][:, None]
    return out


def window_slots(shapes: np.ndarray, weights: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Central moving average of every bundle's shape weights over ``window`` frames.

    Parameters
    ----------
    shapes : (F, M, K) int; weights : (F, M, K) float
        Per frame and bundle, K (shape, weight) slots.
    window : int
        Frames averaged (odd; at the ends, the frames available).

    Returns
    -------
    shapes : (F, M, K * window) int64; weights : (F, M, K * window) float64
        The window's slots side by side, weights divided by the frames averaged (a shape may appear in
        several slots: the blend adds them).
    """
    n_f, n_m, k = shapes.shape
    h = window // 2
    out_s = np.zeros((n_f, n_m, k * (2 * h + 1)), np.int64)
    out_w = np.zeros((n_f, n_m, k * (2 * h + 1)))
    for f in range(n_f):
        lo, hi = max(0, f - h), min(n_f, f + h + 1)
        n = hi - lo
        s = np.transpose(shapes[lo:hi], (1, 0, 2)).reshape(n_m, -1)
        w = np.transpose(weights[lo:hi], (1, 0, 2)).reshape(n_m, -1) / n
        out_s[f, :, : s.shape[1]] = s
        out_w[f, :, : w.shape[1]] = w
    return out_s, out_w


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Central moving average along axis 0 over ``window`` frames, ignoring NaN (which stays NaN).

    Parameters
    ----------
    values : (F, ...) float
    window : int
        Odd; at the ends the frames available are used.
    """
    v = np.asarray(values, np.float64)
    h = window // 2
    ok = np.isfinite(v)
    z = np.where(ok, v, 0.0)
    cs = np.concatenate([np.zeros_like(z[:1]), np.cumsum(z, axis=0)])
    cn = np.concatenate([np.zeros_like(z[:1]), np.cumsum(ok, axis=0)])
    idx = np.arange(len(v))
    lo, hi = np.maximum(0, idx - h), np.minimum(len(v), idx + h + 1)
    s = cs[hi] - cs[lo]
    n = cn[hi] - cn[lo]
    out = np.divide(s, n, out=np.full_like(s, np.nan), where=n > 0)
    return np.where(ok, out, np.nan)
