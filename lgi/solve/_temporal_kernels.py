"""Compiled loop of the temporal treatment (numba): Savitzky-Golay smoothing of runs of trajectories.
Called by :mod:`lgi.solve.temporal`.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def sg_runs(x, left, mid, right, out):  # pragma: no cover - compiled
    """Savitzky-Golay smoothing of every marker's trajectory, each run of seen frames on its own.

    ``x`` (F, M, 3) with NaN rows for missing frames; ``mid`` (w,) the central coefficients, ``left`` and
    ``right`` (h, w) the fitted values at the first and last h = w // 2 frames of a run from its first and
    last w frames (scipy's ``mode="interp"``). Runs shorter than w are copied; ``out`` must hold a copy of
    ``x`` on entry (missing rows stay NaN).
    """
    n_f, n_m = x.shape[0], x.shape[1]
    w = mid.shape[0]
    h = w // 2
    for m in range(n_m):
        t = 0
        while t < n_f:
            if not (np.isfinite(x[t, m, 0]) and np.isfinite(x[t, m, 1]) and np.isfinite(x[t, m, 2])):
                t += 1
                continue
            a = t
            while t < n_f and np.isfinite(x[t, m, 0]) and np.isfinite(x[t, m, 1]) and np.isfinite(x[t, m, 2]):
                t += 1
            b = t
            if b - a < w:
                continue
            for c in range(3):
                for f in range(a, b):
                    acc = 0.0
                    if f - a < h:
                        for j in range(w):
                            acc += left[f - a, j] * x[a + j, m, c]
                    elif b - 1 - f < h:
                        r = f - b + h  # row of ``right``: 0 .. h-1 for frames b-h .. b-1
                        for j in range(w):
                            acc += right[r, j] * x[b - w + j, m, c]
                    else:
                        for j in range(w):
                            acc += mid[j] * x[f - h + j, m, c]
                    out[f, m, c] = acc
