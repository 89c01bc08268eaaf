"""Compiled loops of the surface (numba): blending the shapes' deltas over the vertices by the bundles'
weights, and adding the smooth residual correction. Called by :mod:`lgi.solve.surface` (and the baselines).
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np


class BundleReach(NamedTuple):
    """The natural-neighbour blend weights by bundle (CSC): bundle b reaches vertices ``vert[ptr[b]:ptr[b + 1]]``
    with weights ``w`` there."""

    ptr: np.ndarray  # (M+1,) int64
    vert: np.ndarray  # (N,) int64
    w: np.ndarray  # (N,) float64


@nb.njit(parallel=True, cache=True, nogil=True)
def blend(x0, deltas, w_indptr, w_indices, w_data, shapes, lam, out):  # pragma: no cover - compiled
    """out[v] = x0[v] + sum_i w[v, i] sum_c lam[i, c] deltas[shapes[i, c], v] (deltas shape-major; any
    number of slots c per bundle)."""
    n_v = x0.shape[0]
    for v in nb.prange(n_v):
        a0 = x0[v, 0]
        a1 = x0[v, 1]
        a2 = x0[v, 2]
        for e in range(w_indptr[v], w_indptr[v + 1]):
            i = w_indices[e]
            w = w_data[e]
            for c in range(shapes.shape[1]):
                lc = lam[i, c]
                if lc != 0.0:
                    k = shapes[i, c]
                    f = w * lc
                    a0 += f * deltas[k, v, 0]
                    a1 += f * deltas[k, v, 1]
                    a2 += f * deltas[k, v, 2]
        out[v, 0] = a0
        out[v, 1] = a1
        out[v, 2] = a2


@nb.njit(cache=True, nogil=True)
def blend_on_base(x0, deltas, base_shapes, base_lam, w_sum, reach, ramp, share, rows, d_shapes, d_lam,
                  out):  # pragma: no cover - compiled
    """:func:`blend` of bundles whose weights mostly repeat one base blend (the frame's global fit), with the far
    field: ``out[v] = x0[v] + w_sum[v] B[v] + sum_b N[v, b] (1 - ramp[v] share[b]) D_b[v]``, where
    ``B = sum_c base_lam[c] deltas[base_shapes[c]]`` and ``D_b`` the blend of bundle b's differences from the
    base (``d_shapes``, ``d_lam`` (M, K'), zeros after each row's last; only the bundles in ``rows`` have any).
    The far field's share of the global fit is already in the base term: a vertex's weights sum to w_sum.

    Both terms stream over shape rows, one row at a time (the base over every vertex, a difference over the
    vertices its bundle reaches, from the weights by bundle, ``reach`` a :class:`BundleReach`): reading
    memory in order, as :func:`blend_uniform` does. Flat arrays: ``x0``, ``out`` (3V,), ``deltas`` (S, 3V)."""
    c_ptr, c_vert, c_w = reach
    blend_uniform(x0, deltas, w_sum, base_shapes, base_lam, out)
    for b in rows:
        sb = share[b]
        for c in range(d_shapes.shape[1]):
            lc = d_lam[b, c]
            if lc == 0.0:
                break
            row = deltas[d_shapes[b, c]]
            for e in range(c_ptr[b], c_ptr[b + 1]):
                v = c_vert[e]
                f = c_w[e] * (1.0 - ramp[v] * sb) * lc
                for d in range(3):
                    out[3 * v + d] += f * row[3 * v + d]


@nb.njit(cache=True, nogil=True)
def blend_uniform(x0, deltas, w_sum, shapes, lam, out):  # pragma: no cover - compiled
    """:func:`blend` when every bundle has the same shapes (K,) and weights (K,): out[v] = x0[v] + w_sum[v]
    sum_c lam[c] deltas[shapes[c], v], with w_sum[v] the vertex's total blend weight (1 inside the bundles'
    region, 0 where no bundle reaches). Flat arrays: ``x0``, ``out`` (3V,), ``deltas`` (S, 3V), ``w_sum`` (V,).

    One streaming pass over each used shape's row, accumulated in ``out``: the loop vectorises and reads
    memory in order (1.1 ms for 22 of ICT's rows here). Gathering the K rows per vertex instead (the
    per-vertex loop of :func:`blend`) ran 4-10x slower, and so did splitting the rows into chunks over
    threads (numba ``prange``) on this 2-core machine.
    """
    n = out.shape[0]
    for j in range(n):
        out[j] = 0.0
    for c in range(shapes.shape[0]):
        lc = lam[c]
        if lc != 0.0:
            row = deltas[shapes[c]]
            for j in range(n):
                out[j] += lc * row[j]
    for v in range(n // 3):
        ws = w_sum[v]
        for d in range(3):
            out[3 * v + d] = x0[3 * v + d] + ws * out[3 * v + d]


@nb.njit(cache=True, nogil=True)
def _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf):  # pragma: no cover - compiled
    """Half ``part`` (0 or 1) of :func:`add_correction`'s rows summed into ``buf[part]``."""
    for f in range(part * half, min(fix.shape[0], (part + 1) * half)):
        b = fix[f]
        r0 = resid[f, 0]
        r1 = resid[f, 1]
        r2 = resid[f, 2]
        for e in range(c_indptr[b], c_indptr[b + 1]):
            v = c_indices[e]
            w = c_data[e]
            buf[part, v, 0] += w * r0
            buf[part, v, 1] += w * r1
            buf[part, v, 2] += w * r2


@nb.njit(parallel=True, cache=True, nogil=True)
def add_correction(x, c_indptr, c_indices, c_data, fix, resid):  # pragma: no cover - compiled
    """x[v] += sum_f resid[f] * corr[fix[f], v], the correction basis stored as sparse rows (one per
    bundle): the smooth field carrying the residuals of the bundles in ``fix``. Two threads each sum
    half of the rows into a buffer of their own (no write races), then the buffers are added. A plain
    loop, not BLAS: BLAS threads left spinning after a call would compete with the solver's threads."""
    n_v = x.shape[0]
    buf = np.zeros((2, n_v, 3))
    half = (fix.shape[0] + 1) // 2
    for part in nb.prange(2):
        _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf)
    for v in nb.prange(n_v):
        for k in range(3):
            x[v, k] += buf[0, v, k] + buf[1, v, k]


@nb.njit(cache=True, nogil=True)
def add_correction_serial(x, c_indptr, c_indices, c_data, fix, resid):  # pragma: no cover - compiled
    """:func:`add_correction` on the calling thread alone, summed in the same two halves (the same bits)."""
    n_v = x.shape[0]
    buf = np.zeros((2, n_v, 3))
    half = (fix.shape[0] + 1) // 2
    for part in range(2):
        _correction_part(part, half, c_indptr, c_indices, c_data, fix, resid, buf)
    for v in range(n_v):
        for k in range(3):
            x[v, k] += buf[0, v, k] + buf[1, v, k]
