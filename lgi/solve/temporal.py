"""Temporal treatment of bundle trajectories: bridging short gaps and edge-preserving smoothing."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from lgi.solve.streamed import frame_blocks, streamed_median
from lgi.units import MM_PER_CM


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


def bridged_blocks(positions, max_gap: int, block: int | None = None
                   ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """:func:`bridge_gaps` a block of frames at a time, ``positions`` (F, M, 3) an array or a
    :class:`~lgi.io.stored.StoredArray` read by frame range: each block reads ``max_gap + 1`` frames either side,
    which holds the seen frames around any gap short enough to bridge (a longer one is not bridged, in the block as
    in the shot). Yields ``lo, hi`` and the block's filled positions and bridged mask."""
    n_f = len(positions)
    reach = max(max_gap, 0) + 1
    for lo, hi in frame_blocks(n_f, block):
        a, b = (lo, hi) if max_gap <= 0 else (max(0, lo - reach), min(n_f, hi + reach))
        filled, bridged = bridge_gaps(positions[a:b], max_gap)
        yield lo, hi, filled[lo - a:hi - a], bridged[lo - a:hi - a]


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
    n_ok = ok.astype(np.float64)
    s = np.empty_like(z)
    n = np.empty_like(z)
    # Each frame sums its own window (not a running sum): a frame's value then depends only on the frames in
    # its window, so a shot finished in chunks gives the same bits as finished whole.
    for f in range(len(v)):
        lo, hi = max(0, f - h), min(len(v), f + h + 1)
        s[f] = z[lo:hi].sum(0)
        n[f] = n_ok[lo:hi].sum(0)
    out = np.divide(s, n, out=np.full_like(s, np.nan), where=n > 0)
    return np.where(ok, out, np.nan)


# The noise estimate's window (frames) and the orders of its two local polynomials (see :func:`noise_filter`).
NOISE_WINDOW = 7
NOISE_ORDERS = (4, 2)


@functools.cache
def noise_filter() -> np.ndarray:
    """(13,) the noise estimate's residual filter: a frame's residual from its local quartic over 7 frames, then
    that residual's from its local quadratic over 7 frames. What it passes of a trajectory is its sixth difference:
    white noise passes whole (its variance times the filter's squared norm), slow real motion almost not at all.
    The quadratic alone passed 20 % of real facial motion at 8 Hz (60 Hz mocap) and 117 % at 15 Hz relative to the
    noise, which read 0.01 mm of noise as 0.014 (stereo noise's 0.0025 mm across the rays as 0.0076) on the facial
    mocap of bigoMay/AnimFace (CC BY-SA 4.0); with the quartic first, every axis within 4 % from 0.01 to 0.3 mm on
    its four takes."""
    taps = [-sg_matrix(NOISE_WINDOW, order)[NOISE_WINDOW // 2] for order in NOISE_ORDERS]
    for t in taps:
        t[NOISE_WINDOW // 2] += 1.0
    return np.convolve(*taps)


@dataclass
class NoiseEstimate:
    """A shot's bundle noise as estimated from its trajectories.

    Attributes
    ----------
    noise_mm : float
        Standard deviation per coordinate, the root mean square of ``axis_mm`` (NaN when no marker is seen for
        13 frames in a row).
    samples : int
        Residuals the estimate is based on.
    coherence : float
        Median correlation of the residuals of neighbouring markers: near 0 for measurement noise
        (independent per marker), high when the frame-to-frame changes are motion (independent poses
        rather than a performance), where the estimate is not noise.
    axis_mm : (3,) float
        Standard deviation along each axis of the bundles' (head-stabilised) frame: stereo bundles are noisier
        along the cameras' rays than across them.
    """

    noise_mm: float
    samples: int
    coherence: float
    axis_mm: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))

    @property
    def is_noise(self) -> bool:
        """Whether the residuals look like measurement noise (see ``coherence``)."""
        return bool(np.isfinite(self.noise_mm) and self.coherence < NOISE_MAX_COHERENCE)


# Residuals of neighbouring markers more correlated than this are motion, not measurement noise.
NOISE_MAX_COHERENCE = 0.3


def estimate_noise(positions, pairs: np.ndarray | None = None, fitted=None,
                   leverage: float | np.ndarray = 0.0, block: int | None = None) -> NoiseEstimate:
    """Bundle noise of a shot from its trajectories, per axis.

    Each coordinate's residual from local polynomials over 7 frames (:func:`noise_filter`) is noise plus what the
    motion's sixth difference leaves; the median absolute residual over all markers and frames ignores the few
    fast moments. For white noise of deviation s the residual's deviation is ``s`` times the filter's norm.

    With ``fitted``, the trajectories are first taken off the frames' fit of the face model (the global fit,
    :class:`~lgi.solve.globalfit.GlobalFit`): what the face does together (real motion, where neighbouring
    markers move together from frame to frame) is in the fit, and what is left changes from frame to frame by the
    noise and little else. The fit takes ``leverage`` of each coordinate's noise variance with it (the
    diagonal of its hat matrix), which the estimate puts back.

    The shot is read ``block`` frames at a time (the arrays may wait on disk); the median is numpy's over the
    whole shot, bit for bit.

    Parameters
    ----------
    positions : (F, M, 3) float, cm
        Bundle positions (an array or a :class:`~lgi.io.stored.StoredArray`); NaN rows (missing) are skipped with
        the windows that contain them.
    pairs : (P, 2) int, optional
        Neighbouring markers, for the coherence test (without them coherence is 0).
    fitted : (F, M, 3) float, cm, optional
        The face model's bundle positions fitted to each frame.
    leverage : float or (M, 3) float
        Share of a coordinate's noise variance the fit takes, per marker and axis or for all.
    block : int
        Frames read at once.
    """
    nan = NoiseEstimate(float("nan"), 0, float("nan"))
    g = noise_filter()
    n_f = len(positions)
    if n_f < len(g):
        return nan
    n_r = n_f - len(g) + 1
    lev_scale = None

    def residuals() -> Iterator[np.ndarray]:
        """(k, M, 3) the filter's residuals, ``block`` at a time over the shot's ``n_r`` windows."""
        nonlocal lev_scale
        for lo, hi in frame_blocks(n_r, block):
            p = np.asarray(positions[lo:hi + len(g) - 1], np.float64)
            if fitted is not None:
                p = p - np.asarray(fitted[lo:hi + len(g) - 1], np.float64)
            r = np.lib.stride_tricks.sliding_window_view(p, len(g), axis=0) @ g  # (k, M, 3)
            if lev_scale is None:
                lev_scale = np.sqrt(np.maximum(1.0 - np.broadcast_to(leverage, p.shape[1:]), 0.05))
            yield r / lev_scale

    samples = 0
    dots = np.zeros((len(pairs) if pairs is not None else 0, 3))
    counts = np.zeros(len(dots), np.int64)
    for r in residuals():
        ok = np.isfinite(r)
        samples += int(ok.sum())
        if len(dots):
            # per pair, the sums of a.b, a.a and b.b over the frames that see both markers
            fin = ok.all(axis=2)
            for k, (i, j) in enumerate(np.asarray(pairs)):
                both = fin[:, i] & fin[:, j]
                if not both.any():
                    continue
                a, b = r[both, i].ravel(), r[both, j].ravel()
                dots[k] += (a @ b, a @ a, b @ b)
                counts[k] += int(both.sum())
    if not samples:
        return nan
    scale = MM_PER_CM / 0.6745 / np.sqrt(g @ g)

    def along(a: int):
        return lambda: (np.abs(r[..., a][np.isfinite(r[..., a])]) for r in residuals())

    axis = np.array([streamed_median(along(a)) * scale for a in range(3)])
    noise = float(np.sqrt(np.mean(axis**2)))
    coherence = 0.0
    if len(dots):
        used = (counts >= 3) & (dots[:, 1] * dots[:, 2] > 0)
        corr = dots[used, 0] / np.sqrt(dots[used, 1] * dots[used, 2])
        coherence = float(np.median(corr)) if len(corr) else float("nan")
    return NoiseEstimate(noise, samples, coherence, axis)


SG_WINDOWS = (1, 5, 7, 9, 11, 15, 21, 31)
# A marker seen in fewer frames than this keeps its trajectory as it is (too short to smooth).
MIN_SMOOTHED_FRAMES = 8


def sg_matrix(window: int, order: int = 2) -> np.ndarray:
    """(w, w) the least-squares polynomial fit over ``window`` equally spaced frames: row j gives the fitted
    value at frame j (the middle row is the Savitzky-Golay smoothing filter; the others the ends of a run,
    as scipy's ``savgol_filter(mode="interp")`` fits them)."""
    t = np.arange(window, dtype=np.float64) - window // 2
    v = np.vander(t, order + 1)
    return v @ np.linalg.pinv(v)


def _sg_all(x: np.ndarray, window: int) -> np.ndarray:
    """Savitzky-Golay (quadratic) smoothing of every marker's trajectory (F, M, 3) with NaN rows; each run of
    seen frames is smoothed on its own (runs shorter than the window are left as they are)."""
    from lgi.solve._temporal_kernels import sg_runs

    out = np.array(x, np.float64, copy=True)
    if window <= 1:
        return out
    mat = sg_matrix(window)
    h = window // 2
    sg_runs(np.ascontiguousarray(x, np.float64), np.ascontiguousarray(mat[:h]), np.ascontiguousarray(mat[h]),
              np.ascontiguousarray(mat[window - h:]), out)
    return out


def sg_centre(window: int | np.ndarray) -> np.ndarray:
    """The share of white noise's variance a centred quadratic Savitzky-Golay window lets through (its middle
    coefficient, which for a least-squares projection is the sum of its squared coefficients); 1 for window 1."""
    w = np.asarray(window)
    table = {v: (1.0 if v <= 1 else float(sg_matrix(v)[v // 2, v // 2])) for v in np.unique(w).tolist()}
    return np.vectorize(table.__getitem__, otypes=[np.float64])(w) if w.ndim else np.float64(table[int(w)])


def denoise_trajectories(positions: np.ndarray, noise_mm: float | np.ndarray, windows: tuple[int, ...] = SG_WINDOWS,
                         span: int = 15, block: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smooth each marker's trajectory by local quadratics over the window that minimises Stein's unbiased
    estimate of its error, given the noise, chosen frame by frame and axis by axis.

    For a linear smoother ``y_hat = H y`` of data with white noise of deviation s, the expected squared error
    against the truth is ``|y - y_hat|^2 - n s^2 + 2 s^2 tr(H)`` (SURE). Its per-frame terms, averaged over
    ``span`` frames either side, pick the window for each marker, axis and frame: wide while the marker rests or
    drifts, short through a fast opening of the jaw (one window per marker for the whole shot lagged the
    synthetic actor's fast openings by up to 3.6 mm), and wider along an axis with more noise (stereo depth).

    Parameters
    ----------
    positions : (F, M, 3) float, cm
        Rows of NaN are missing (left missing).
    noise_mm : float, (3,) or (M, 3) float
        Noise deviation per coordinate, per axis, or per marker and axis.
    windows : tuple of int
        Odd windows tried (1: no smoothing).
    span : int
        Frames either side over which the per-frame risk is averaged.
    block : int
        Frames smoothed at once (:func:`smoothed_blocks`; the result does not depend on it).

    Returns
    -------
    smoothed : (F, M, 3) float64, cm
    window : (F, M, 3) int
        The window used per frame, marker and axis.
    """
    p = np.asarray(positions, np.float64)
    s2 = np.broadcast_to((np.asarray(noise_mm, np.float64) / MM_PER_CM) ** 2, p.shape[1:])
    out, chosen = np.empty(p.shape), np.ones(p.shape, np.int64)
    for lo, hi, y, w in smoothed_blocks(lambda lo, hi: p[lo:hi], len(p), s2, windows, span, block):
        out[lo:hi], chosen[lo:hi] = y, w
    return out, chosen


def smoothed_blocks(read: Callable[[int, int], np.ndarray], n_frames: int, s2: np.ndarray,
                    windows: tuple[int, ...] = SG_WINDOWS, span: int = 15, block: int | None = None
                    ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray]]:
    """:func:`denoise_trajectories` a block of frames at a time, reading the trajectories by frame range.

    Each block reads a margin either side, wide enough that every window and every run of seen frames near the
    block looks as it does in the whole shot, and the risks' running sums are carried from block to block in the
    order the whole shot's are made: the result equals the whole shot's bit for bit.

    Parameters
    ----------
    read : callable
        ``read(lo, hi)``: (hi - lo, M, 3) float, cm, frames ``lo .. hi`` (NaN rows missing).
    n_frames : int
    s2 : (M, 3) float, cm^2
        Noise variance per marker and axis.
    windows, span, block
        As :func:`denoise_trajectories`.

    Yields
    ------
    lo, hi : int
        The block's frames.
    smoothed : (hi - lo, M, 3) float64, cm
    window : (hi - lo, M, 3) int64
    """
    cand = [w for w in windows if w > 1]
    smooth = bool((s2 > 0).any() and cand)
    n_ok = None
    if smooth:
        n_ok = sum((np.all(np.isfinite(read(lo, hi)), axis=2).sum(0) for lo, hi in frame_blocks(n_frames, block)),
                   start=np.zeros(s2.shape[0], np.int64))
    wins = np.array([1, *cand])
    size = 2 * span + 1
    # A frame's window reads ``max(cand) // 2`` frames either side and needs its run's length up to ``max(cand)``.
    margin = max(cand, default=1) - 1
    # Running sums of each candidate's risk over the shot padded by ``span`` repeats at each end (c[0] = 0,
    # c[j + 1] = c[j] + risk of padded frame j), kept from index ``c_lo``: the mean over frames f - span .. f + span
    # is (c[f + size] - c[f]) / size.
    c, c_lo = None, 0
    for lo, hi in frame_blocks(n_frames, block):
        if not smooth:
            p = np.asarray(read(lo, hi), np.float64)
            yield lo, hi, p.copy(), np.ones(p.shape, np.int64)
            continue
        c_end = c_lo + (0 if c is None else c.shape[1] - 1)  # the last running sum made
        need = hi + 2 * span  # the last running sum the block's means need
        rb = min(n_frames, hi + span)  # frames whose risks are needed: lo .. rb
        s_lo, s_hi = max(0, lo - margin), min(n_frames, rb + margin)
        p = np.asarray(read(s_lo, s_hi), np.float64)
        ys = [p]
        risks = [np.zeros(p.shape)]  # no smoothing: the reference (its risk is s^2 per coordinate and frame)
        for w in cand:
            y = _sg_all(p, w)
            smoothed = (np.all(np.isfinite(y), axis=2) & np.any(y != p, axis=2))[..., None]
            r = np.where(smoothed, np.nan_to_num((y - p) ** 2) - 2 * s2 * (1.0 - sg_centre(w)), 0.0)
            r[:, w > n_ok] = 1e30  # a window longer than the marker's seen frames is not a candidate
            ys.append(y)
            risks.append(r)
        risk = np.stack(risks).reshape(len(risks), len(p), -1)
        del risks
        padded = np.clip(np.arange(c_end, need) - span, 0, n_frames - 1) - s_lo
        # The running sums carried on from the last one made (one add after another, as numpy's cumsum over the
        # whole shot), in one buffer with those the block still reads.
        keep = 0 if c is None else c.shape[1] - 1
        buf = np.empty((len(ys), keep + 1 + len(padded), risk.shape[2]))
        if c is None:
            buf[:, 0] = 0.0
        else:
            buf[:, :keep + 1] = c
        np.take(risk, padded, axis=1, out=buf[:, keep + 1:])
        del risk
        if c is None:
            np.cumsum(buf[:, 1:], axis=1, out=buf[:, 1:])
        else:
            np.cumsum(buf[:, keep:], axis=1, out=buf[:, keep:])
        c = buf
        local = ((c[:, lo + size - c_lo:hi + size - c_lo] - c[:, lo - c_lo:hi - c_lo]) / size
                 ).reshape(len(ys), hi - lo, *p.shape[1:])
        c, c_lo = c[:, hi - c_lo:].copy(), hi
        del buf
        best = np.argmin(local, axis=0)  # (k, M, 3)
        del local
        best[:, n_ok < MIN_SMOOTHED_FRAMES] = 0
        best[:, s2 <= 0] = 0
        out = np.take_along_axis(np.stack([y[lo - s_lo:hi - s_lo] for y in ys]), best[None], axis=0)[0]
        del ys, p  # not held while the caller works on the block
        yield lo, hi, out, wins[best]


# The fitted part of the trajectories carries ``leverage`` of the noise's variance, the rest the other share;
# SURE over that rest is run as if it had this many times its noise. The rest is the face model's error, small
# and slow, plus the noise: its per-frame risks, averaged over +-15 frames, still chose windows too short for it
# (synthetic actor, 0.02-0.05 mm: the bundles' error 0.0071 / 0.0169 mm at 1x, 0.0068 / 0.0159 at 1.2x,
# 0.0067 / 0.0156 at 1.5x and 2x).
RESIDUAL_NOISE_MARGIN = 1.5


def denoise_with_model(positions: np.ndarray, fitted: np.ndarray, noise_mm: np.ndarray,
                       leverage: float | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Smooth trajectories in two parts: the face model's fit of each frame, and what the fit leaves.

    The fit (the frame's global fit) follows what the face does together and holds ``leverage`` of each
    coordinate's noise variance; the rest is the model's error, small and slow, plus the other share of the
    noise. Each part is smoothed by :func:`denoise_trajectories` with its own noise, so a fast move of the face
    (in the fit) keeps short windows while the noise left beside it is averaged over long ones (synthetic actor,
    0.02 mm per coordinate: 0.0112 mm left by smoothing the bundles themselves, 0.0075 mm this way; 0.3 mm:
    0.142 and 0.102).

    Parameters
    ----------
    positions, fitted : (F, M, 3) float, cm
        The bundles (NaN rows missing) and the model's positions fitted to them.
    noise_mm : (3,) or (M, 3) float
        Noise deviation per axis, or per marker and axis.
    leverage : float or (M, 3) float
        Share of the noise's variance the fit holds, per marker and axis or for all.

    Returns
    -------
    smoothed : (F, M, 3) float64, cm
    left : (F, M, 3) float64, cm^2
        The noise variance left per frame, marker and axis (by the windows chosen, each part's share).
    windows : (F, M, 3) int
        The window of the residual part (the longer of the two).
    """
    smoothed = np.empty(np.shape(positions))
    left, windows = np.empty(smoothed.shape), np.empty(smoothed.shape, np.int64)
    for lo, hi, y, var, w in model_denoised_blocks(positions, fitted, noise_mm, leverage):
        smoothed[lo:hi], left[lo:hi], windows[lo:hi] = y, var, w
    return smoothed, left, windows


def model_denoised_blocks(positions, fitted, noise_mm: np.ndarray, leverage: float | np.ndarray,
                          into: Callable[[np.ndarray], np.ndarray] | None = None, block: int | None = None
                          ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`denoise_with_model` a block of frames at a time (:func:`smoothed_blocks`: equal to the whole shot's,
    bit for bit), ``positions`` and ``fitted`` arrays or :class:`~lgi.io.stored.StoredArray` read by frame range.
    ``into``: a map of (k, M, 3) positions into the frame they are smoothed in (each marker's noise axes), applied
    to both as read. Yields ``lo, hi`` and the block's smoothed positions, noise left and windows."""
    s = np.broadcast_to(np.asarray(noise_mm, np.float64), np.shape(positions)[1:])
    lev = np.clip(np.broadcast_to(np.asarray(leverage, np.float64), s.shape), 0.0, 1.0)
    prep = (lambda x: x) if into is None else into

    def fit_rows(lo: int, hi: int) -> np.ndarray:
        return prep(np.asarray(fitted[lo:hi], np.float64))

    def rest_rows(lo: int, hi: int) -> np.ndarray:
        return prep(np.asarray(positions[lo:hi], np.float64)) - fit_rows(lo, hi)

    n_f = len(positions)
    fit_s2 = ((s * np.sqrt(lev)) / MM_PER_CM) ** 2
    res_s2 = ((s * np.sqrt(1.0 - lev) * RESIDUAL_NOISE_MARGIN) / MM_PER_CM) ** 2
    var = (s / MM_PER_CM) ** 2
    for (lo, hi, fit_s, fit_w), (_, _, res_s, res_w) in zip(
            smoothed_blocks(fit_rows, n_f, fit_s2, block=block), smoothed_blocks(rest_rows, n_f, res_s2, block=block),
            strict=True):
        left = var * (lev * sg_centre(fit_w) + (1.0 - lev) * sg_centre(res_w))
        yield lo, hi, fit_s + res_s, left, res_w
