"""Compiled loops over the index's per-bundle grids and simplices (numba): the grids' construction, and the
point location the solver's search runs on them (grid cell, barycentric coordinates, closest points).

Arrays are the flattened index (see :mod:`lgi.index.build`): per-bundle blocks of points, simplices, hull
facets and grid cells addressed through offset arrays. Local coordinates are padded to 3 components and
simplices to 4 corners (-1 where unused); a bundle's dimension ``d`` says how many are real.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def build_grids(pts, pt_off, sx, sx_off, dim, target_per_cell, max_dim):  # pragma: no cover - compiled
    """Uniform grid per bundle over its local bounding box; every simplex is listed in the cells its
    bounding box overlaps. Returns lo (M,3), h (M,), dims (M,3), cell_off (M+1), cell_start, items."""
    m = dim.shape[0]
    lo = np.zeros((m, 3))
    h = np.ones(m)
    dims = np.ones((m, 3), np.int64)
    cell_off = np.zeros(m + 1, np.int64)
    for i in range(m):
        d = dim[i]
        a, b = pt_off[i], pt_off[i + 1]
        n_sx = sx_off[i + 1] - sx_off[i]
        ext = 0.0
        for k in range(d):
            lo[i, k] = pts[a:b, k].min()
            e = pts[a:b, k].max() - lo[i, k]
            ext = max(ext, e)
        if d == 0 or ext <= 0:
            cell_off[i + 1] = cell_off[i] + 1
            continue
        vol = 1.0
        for k in range(d):
            vol *= max(pts[a:b, k].max() - lo[i, k], ext * 1e-3)
        cells = max(1.0, n_sx / target_per_cell)
        hh = (vol / cells) ** (1.0 / d)
        h[i] = max(hh, ext / max_dim)
        n_c = 1
        for k in range(d):
            dims[i, k] = min(max_dim, int(np.floor((pts[a:b, k].max() - lo[i, k]) / h[i])) + 1)
            n_c *= dims[i, k]
        cell_off[i + 1] = cell_off[i] + n_c
    counts = np.zeros(cell_off[m] + 1, np.int64)
    for pass_ in range(2):
        if pass_ == 1:
            start = np.zeros(cell_off[m] + 1, np.int64)
            for c in range(cell_off[m]):
                start[c + 1] = start[c] + counts[c]
            items = np.zeros(start[cell_off[m]], np.int64)
            fill = start[:-1].copy()
        for i in range(m):
            d = dim[i]
            for s in range(sx_off[i], sx_off[i + 1]):
                c0 = np.zeros(3, np.int64)
                c1 = np.zeros(3, np.int64)
                for k in range(d):
                    mn = 1e300
                    mx = -1e300
                    for c in range(d + 1):
                        v = pts[sx[s, c], k]
                        mn = min(mn, v)
                        mx = max(mx, v)
                    c0[k] = min(dims[i, k] - 1, max(0, int(np.floor((mn - lo[i, k]) / h[i]))))
                    c1[k] = min(dims[i, k] - 1, max(0, int(np.floor((mx - lo[i, k]) / h[i]))))
                for x in range(c0[0], c1[0] + 1):
                    for y in range(c0[1], c1[1] + 1):
                        for z in range(c0[2], c1[2] + 1):
                            cell = cell_off[i] + (x * dims[i, 1] + y) * dims[i, 2] + z
                            if pass_ == 0:
                                counts[cell] += 1
                            else:
                                items[fill[cell]] = s
                                fill[cell] += 1
    return lo, h, dims, cell_off, start, items


@nb.njit(cache=True)
def _cell(y, i, lo, h, dims, cell_off, d):  # pragma: no cover - compiled
    idx = np.zeros(3, np.int64)
    for k in range(d):
        c = int(np.floor((y[k] - lo[i, k]) / h[i]))
        if c < 0 or c >= dims[i, k]:
            return -1
        idx[k] = c
    return cell_off[i] + (idx[0] * dims[i, 1] + idx[1]) * dims[i, 2] + idx[2]


@nb.njit(cache=True)
def _bary(y, s, sx, tinv, pts, d, lam):  # pragma: no cover - compiled
    p0 = sx[s, 0]
    tot = 0.0
    for r in range(d):
        acc = 0.0
        for k in range(d):
            acc += tinv[s, r, k] * (y[k] - pts[p0, k])
        lam[r + 1] = acc
        tot += acc
    lam[0] = 1.0 - tot
    for r in range(d + 1, 4):
        lam[r] = 0.0


@nb.njit(cache=True)
def _closest_on_segment(y, a, b, d, out):  # pragma: no cover - compiled
    num = 0.0
    den = 0.0
    for k in range(d):
        num += (y[k] - a[k]) * (b[k] - a[k])
        den += (b[k] - a[k]) ** 2
    t = 0.0 if den <= 0 else min(1.0, max(0.0, num / den))
    dist = 0.0
    for k in range(d):
        out[k] = a[k] + t * (b[k] - a[k])
        dist += (y[k] - out[k]) ** 2
    return dist


@nb.njit(cache=True)
def _closest_on_triangle(p, a, b, c, out):  # pragma: no cover - compiled
    """Closest point of triangle abc to p (3D), Ericson's region tests; returns squared distance."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = ab @ ap
    d2 = ac @ ap
    if d1 <= 0 and d2 <= 0:
        out[:] = a
    else:
        bp = p - b
        d3 = ab @ bp
        d4 = ac @ bp
        if d3 >= 0 and d4 <= d3:
            out[:] = b
        else:
            vc = d1 * d4 - d3 * d2
            if vc <= 0 and d1 >= 0 and d3 <= 0:
                out[:] = a + d1 / (d1 - d3) * ab
            else:
                cp = p - c
                d5 = ab @ cp
                d6 = ac @ cp
                if d6 >= 0 and d5 <= d6:
                    out[:] = c
                else:
                    vb = d5 * d2 - d1 * d6
                    if vb <= 0 and d2 >= 0 and d6 <= 0:
                        out[:] = a + d2 / (d2 - d6) * ac
                    else:
                        va = d3 * d6 - d5 * d4
                        if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
                            out[:] = b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b)
                        else:
                            den = 1.0 / (va + vb + vc)
                            out[:] = a + ab * (vb * den) + ac * (vc * den)
    diff = p - out
    return diff @ diff
