"""Numba kernels of the closest-point queries (:mod:`lgi.dataset.mesh`): one point against one triangle, and a
point's nearest of its candidate triangles, without the (points x candidates) working arrays of numpy."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _dot(x0: float, x1: float, x2: float, y0: float, y1: float, y2: float) -> float:
    # numpy's einsum order for three terms (its two-lane sum): the weights equal the vectorised formula's, bit for
    # bit, so that layouts and indexes built with either are the same.
    return (x0 * y0 + x2 * y2) + x1 * y1


@njit(cache=True, error_model="numpy")
def closest_bary(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, out: np.ndarray) -> None:
    """Barycentric weights (written to ``out`` (3,)) of the point of triangle ``a b c`` closest to ``p`` (each
    (3,) float64): Ericson's region tests, the vertex regions first, then the edges', then the interior."""
    ab0, ab1, ab2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
    ac0, ac1, ac2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
    d1 = _dot(ab0, ab1, ab2, p[0] - a[0], p[1] - a[1], p[2] - a[2])
    d2 = _dot(ac0, ac1, ac2, p[0] - a[0], p[1] - a[1], p[2] - a[2])
    d3 = _dot(ab0, ab1, ab2, p[0] - b[0], p[1] - b[1], p[2] - b[2])
    d4 = _dot(ac0, ac1, ac2, p[0] - b[0], p[1] - b[1], p[2] - b[2])
    d5 = _dot(ab0, ab1, ab2, p[0] - c[0], p[1] - c[1], p[2] - c[2])
    d6 = _dot(ac0, ac1, ac2, p[0] - c[0], p[1] - c[1], p[2] - c[2])
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d1 <= 0 and d2 <= 0:
        out[0], out[1], out[2] = 1.0, 0.0, 0.0
    elif d3 >= 0 and d4 <= d3:
        out[0], out[1], out[2] = 0.0, 1.0, 0.0
    elif vc <= 0 and d1 >= 0 and d3 <= 0:
        v = d1 / (d1 - d3)
        out[0], out[1], out[2] = 1 - v, v, 0.0
    elif d6 >= 0 and d5 <= d6:
        out[0], out[1], out[2] = 0.0, 0.0, 1.0
    elif vb <= 0 and d2 >= 0 and d6 <= 0:
        w = d2 / (d2 - d6)
        out[0], out[1], out[2] = 1 - w, 0.0, w
    elif va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        out[0], out[1], out[2] = 0.0, 1 - w, w
    else:
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        out[0], out[1], out[2] = 1 - v - w, v, w


@njit(cache=True)
def closest_bary_rows(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """:func:`closest_bary` row by row: (N, 3) float64 weights of (N, 3) points and triangle corners."""
    out = np.empty((p.shape[0], 3))
    for i in range(p.shape[0]):
        closest_bary(p[i], a[i], b[i], c[i], out[i])
    return out


@njit(cache=True)
def nearest_of_candidates(p: np.ndarray, candidates: np.ndarray, vertices: np.ndarray, triangles: np.ndarray,
                          centroids: np.ndarray, tri: np.ndarray, bary: np.ndarray, dist: np.ndarray) -> None:
    """For each point of ``p`` (N, 3), the closest of its ``candidates`` (N, K) triangles: its index, the
    barycentric weights of the closest point and the distance, written to ``tri`` (N,), ``bary`` (N, 3) and
    ``dist`` (N,). Of equally close triangles (a point nearest a shared edge or vertex) the one whose centroid is
    nearest wins, then the first candidate."""
    w = np.empty(3)
    for i in range(p.shape[0]):
        best_d, best_c, best_t = np.inf, np.inf, -1
        b0 = b1 = b2 = 0.0
        for j in range(candidates.shape[1]):
            t = candidates[i, j]
            ia, ib, ic = triangles[t, 0], triangles[t, 1], triangles[t, 2]
            closest_bary(p[i], vertices[ia], vertices[ib], vertices[ic], w)
            x = w[0] * vertices[ia, 0] + w[1] * vertices[ib, 0] + w[2] * vertices[ic, 0] - p[i, 0]
            y = w[0] * vertices[ia, 1] + w[1] * vertices[ib, 1] + w[2] * vertices[ic, 1] - p[i, 1]
            z = w[0] * vertices[ia, 2] + w[1] * vertices[ib, 2] + w[2] * vertices[ic, 2] - p[i, 2]
            d = np.sqrt(x * x + y * y + z * z)
            if d > best_d:
                continue
            cx, cy, cz = centroids[t, 0] - p[i, 0], centroids[t, 1] - p[i, 1], centroids[t, 2] - p[i, 2]
            centre = np.sqrt(cx * cx + cy * cy + cz * cz)
            if d < best_d or centre < best_c:
                best_d, best_c, best_t = d, centre, t
                b0, b1, b2 = w[0], w[1], w[2]
        tri[i], dist[i] = best_t, best_d
        bary[i, 0], bary[i, 1], bary[i, 2] = b0, b1, b2
