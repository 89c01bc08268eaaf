"""Compiled loops of the global fit (numba), :class:`lgi.solve.globalfit.GlobalFit`: its linearisation, and
the whole fit of a frame in one compiled call (:func:`global_fit_frame`).
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from lgi.solve._jaw_kernels import jaw_map, jaw_map_derivatives
from lgi.solve.qp import box_qp


class FitModel(NamedTuple):
    """The global fit's model of M bundles and S shapes (:class:`lgi.solve.globalfit.GlobalFit`), made once."""

    rest: np.ndarray  # (M, 3) float64, cm: the bundles on the neutral (unskinned with a rig)
    basis: np.ndarray  # (S, M, 3) float64, cm: each shape's displacement of each bundle
    prod: np.ndarray  # (S, M, 6): :func:`shape_products` of ``basis``
    pivot: np.ndarray  # (3,) cm: the jaw's pivot
    bw: np.ndarray  # (M,): each bundle's jaw skinning weight (zeros without a rig)
    has_rig: bool
    theta_scale: np.ndarray  # (4,): the jaw parameters' units in the solve


class FitSettings(NamedTuple):
    """The global fit's settings, read at each frame (the gain may change between frames)."""

    l2: float  # ridge on the weights, cm^2
    gain: float  # least decrease of the objective (cm^2) for which a shape joins the working set
    max_iter: int  # Gauss-Newton steps at most
    grow: int  # shapes joining the working set per round


# The global fit's linearisation (lgi.solve.globalfit.GlobalFit). Bundle i = seen_idx[e] is modelled as
# (1 - b_i) x_i + b_i (R x_i + t), x_i = rest_i + sum_k w_k basis_ki; the derivative in w_k is
# J_k,e = (1 - b_i) d + b_i R d (d = basis_ki). Loops rather than numpy expressions: those allocate
# (S, m, 3) temporaries, which cost more than the arithmetic (10 ms per call at 500 shapes here), and the
# full Jacobian is never stored: the fit needs its product with a vector and a few of its rows.
@nb.njit(cache=True, inline="always")
def _unskinned(rest, basis, nz, w, i, x):  # pragma: no cover - compiled
    """x (3,) = rest[i] + sum_k w[k] basis[k, i] over the nonzero weights ``nz``: bundle i before skinning."""
    for c in range(3):
        x[c] = rest[i, c]
    for k in nz:
        for c in range(3):
            x[c] += w[k] * basis[k, i, c]


@nb.njit(cache=True)
def global_residual(rest, basis, seen_idx, w, rot, trans, bw, p, r_out):  # pragma: no cover - compiled
    """Model minus ``p`` at the seen bundles, ``r_out[3e + c]``."""
    nz = np.flatnonzero(w)
    x = np.empty(3)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        _unskinned(rest, basis, nz, w, i, x)
        b = bw[i]
        for c in range(3):
            r_out[3 * e + c] = ((1.0 - b) * x[c] + b * (rot[c, 0] * x[0] + rot[c, 1] * x[1] + rot[c, 2] * x[2]
                                                        + trans[c]) - p[i, c])


@nb.njit(cache=True)
def global_gradient(basis, seen_idx, rot, bw, v, out):  # pragma: no cover - compiled
    """``out[k] = J_k . v`` for every shape k: ``sum_e d . ((1 - b) v_e + b R^T v_e)``. One dense product with
    the (S, 3M) basis (BLAS; missing bundles get 0): the gather over the seen bundles did not vectorise and
    took 5x as long."""
    n_m = basis.shape[1]
    u = np.zeros(3 * n_m)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        b = bw[i]
        for c in range(3):
            u[3 * i + c] = (1.0 - b) * v[3 * e + c] + b * (rot[0, c] * v[3 * e] + rot[1, c] * v[3 * e + 1]
                                                          + rot[2, c] * v[3 * e + 2])
    out[:] = np.dot(basis.reshape(basis.shape[0], 3 * n_m), u)


@nb.njit(cache=True, inline="always")
def _shape_derivative(basis, k, i, b, rot, out):  # pragma: no cover - compiled
    """out (3,) = (1 - b) d + b R d for d = basis[k, i]: bundle i's derivative in shape k's weight."""
    d0 = basis[k, i, 0]
    d1 = basis[k, i, 1]
    d2 = basis[k, i, 2]
    for c in range(3):
        out[c] = (1.0 - b) * basis[k, i, c] + b * (rot[c, 0] * d0 + rot[c, 1] * d1 + rot[c, 2] * d2)


def shape_products(basis):
    """(S, M, 6) products of each shape's displacement at each bundle, (d0^2, d1^2, d2^2, 2 d0 d1, 2 d0 d2,
    2 d1 d2), for :func:`global_col2`."""
    d = basis
    return np.ascontiguousarray(np.stack([d[..., 0] ** 2, d[..., 1] ** 2, d[..., 2] ** 2, 2 * d[..., 0] * d[..., 1],
                                          2 * d[..., 0] * d[..., 2], 2 * d[..., 1] * d[..., 2]], axis=-1))


@nb.njit(cache=True)
def global_col2(prod, seen_idx, rot, bw, out):  # pragma: no cover - compiled
    """``out[k] = |J_k|^2`` for every shape k, from ``prod`` = :func:`shape_products` (S, M, 6).

    ``|(1 - b) d + b R d|^2 = d' Q d`` with ``Q = ((1 - b)^2 + b^2) I + b (1 - b) (R + R')`` (R is a rotation):
    one dense product with the (S, 6M) products instead of a rotation per shape and bundle (0.5 -> 0.05 ms at
    500 shapes)."""
    n_m = prod.shape[1]
    coef = np.zeros(6 * n_m)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        b = bw[i]
        a0 = (1.0 - b) ** 2 + b * b
        a1 = b * (1.0 - b)
        coef[6 * i + 0] = a0 + 2.0 * a1 * rot[0, 0]
        coef[6 * i + 1] = a0 + 2.0 * a1 * rot[1, 1]
        coef[6 * i + 2] = a0 + 2.0 * a1 * rot[2, 2]
        coef[6 * i + 3] = a1 * (rot[0, 1] + rot[1, 0])
        coef[6 * i + 4] = a1 * (rot[0, 2] + rot[2, 0])
        coef[6 * i + 5] = a1 * (rot[1, 2] + rot[2, 1])
    out[:] = np.dot(prod.reshape(prod.shape[0], 6 * n_m), coef)


# The whole fit in one compiled call per frame: Gauss-Newton over the jaw and the bounded weights, each step a
# working-set box QP. In Python the bookkeeping around the kernels above (row caches, sets, small arrays) cost
# 20 ms per frame at 500 shapes, ten times the arithmetic.
@nb.njit(cache=True)
def _gf_system(model, seen_idx, p, w, theta, with_jaw, r, jaw_rows, rot):  # pragma: no cover - compiled
    """Residuals ``r`` (3m,) of the seen bundles at (theta, w), the jaw map's rotation ``rot`` (3, 3) and,
    with ``with_jaw``, the jaw's Jacobian rows (4, 3m) per unit of the model's ``theta_scale``."""
    rest, basis, pivot, bw, has_rig, theta_scale = (model.rest, model.basis, model.pivot, model.bw, model.has_rig,
                                                    model.theta_scale)
    t = np.zeros((3, 4))
    if has_rig:
        jaw_map(theta, pivot, t)
    else:
        for c in range(3):
            t[c, c] = 1.0
    for c in range(3):
        for d in range(3):
            rot[c, d] = t[c, d]
    trans = t[:, 3].copy()
    global_residual(rest, basis, seen_idx, w, rot, trans, bw, p, r)
    if not with_jaw:
        return
    dts = np.empty((4, 3, 4))
    jaw_map_derivatives(theta, pivot, dts)
    nz = np.flatnonzero(w)
    x = np.empty(3)
    for e in range(seen_idx.shape[0]):
        i = seen_idx[e]
        _unskinned(rest, basis, nz, w, i, x)
        b = bw[i]
        for q in range(4):
            s = b * theta_scale[q]
            for c in range(3):
                jaw_rows[q, 3 * e + c] = s * (dts[q, c, 0] * x[0] + dts[q, c, 1] * x[1] + dts[q, c, 2] * x[2]
                                              + dts[q, c, 3])


@nb.njit(cache=True)
def _gf_row(model, seen_idx, rot, jaw_rows, k, out):  # pragma: no cover - compiled
    """Jacobian row (3m,) of variable k (the jaw's first, then the shapes)."""
    basis, bw = model.basis, model.bw
    nj = jaw_rows.shape[0]
    if k < nj:
        out[:] = jaw_rows[k]
        return
    d = np.empty(3)
    for e in range(seen_idx.shape[0]):
        _shape_derivative(basis, k - nj, seen_idx[e], bw[seen_idx[e]], rot, d)
        for c in range(3):
            out[3 * e + c] = d[c]


@nb.njit(cache=True)
def _gf_gradient(model, seen_idx, rot, jaw_rows, r, dz, z, reg, damp, row_pos, rowbuf, g):  # pragma: no cover
    """g = J^T (r + J dz) + reg (z + dz) + damp dz: the objective's gradient at the step ``dz`` (rows of its
    nonzero entries cached in ``rowbuf`` at ``row_pos``)."""
    nj = jaw_rows.shape[0]
    v = r.copy()
    for k in range(dz.shape[0]):
        if dz[k] != 0.0:
            row = rowbuf[row_pos[k]]
            for j in range(v.shape[0]):
                v[j] += dz[k] * row[j]
    for q in range(nj):
        acc = 0.0
        for j in range(v.shape[0]):
            acc += jaw_rows[q, j] * v[j]
        g[q] = acc
    global_gradient(model.basis, seen_idx, rot, model.bw, v, g[nj:])
    for k in range(g.shape[0]):
        g[k] += reg[k] * (z[k] + dz[k]) + damp * dz[k]


@nb.njit(cache=True)
def _gf_top(score, cand, count, work):  # pragma: no cover - compiled
    """Mark in ``work`` the ``count`` variables of ``cand`` with the largest ``score`` (ties: the first in
    ``cand``, as a stable sort would take them). Picked one at a time, O(count x len(cand)) for 16 of a few
    hundred: a sort costs nothing more per call but compiles for 13 s on the first run after an install."""
    taken = np.zeros(cand.shape[0], np.bool_)
    for _ in range(min(count, cand.shape[0])):
        best = -1
        for a in range(cand.shape[0]):
            if not taken[a] and (best < 0 or score[cand[a]] > score[cand[best]]):
                best = a
        taken[best] = True
        work[cand[best]] = True


@nb.njit(cache=True)
def working_set_step(model, seen_idx, rot, jaw_rows, r, w, reg, damp, col2, gain, grow):  # pragma: no cover
    """The step dz minimising ``|r + J dz|^2 + sum reg (z + dz)^2 + damp |dz|^2`` (z: 0 for the jaw, ``w`` for
    the weights; ``damp``: Levenberg-Marquardt damping of the step) with ``0 <= w + dz_w <= 1``, solved on a
    working set of variables.

    With hundreds of shapes, most of them in-betweens of others, the solution uses few; the others sit at a
    bound. The box QP is solved over the jaw, the shapes in use and the ``grow`` shapes whose gradient most
    wants them, then the optimality of every other shape is checked and violators join; the dense problem
    over all shapes (its normal matrix alone is 500^2 x 3m flops) is never formed. It stops when no shape
    outside the set could lower the objective by more than ``gain`` (cm^2) on its own. ``col2`` (n,): the
    Jacobian's squared column norms (without ``reg``). ``jaw_rows`` (nj, 3m): the jaw's Jacobian rows (none
    without the jaw).
    """
    nj = jaw_rows.shape[0]
    n = nj + w.shape[0]
    m3 = r.shape[0]
    z = np.zeros(n)
    lo = np.full(n, -1e30)
    hi = np.full(n, 1e30)
    for k in range(w.shape[0]):
        z[nj + k] = w[k]
        lo[nj + k] = -w[k]
        hi[nj + k] = 1.0 - w[k]
    dz = np.zeros(n)
    row_pos = np.full(n, -1, np.int64)
    rowbuf = np.empty((max(64, 2 * grow), m3))
    n_rows = 0
    g = np.empty(n)
    col2r = col2 + reg + damp
    _gf_gradient(model, seen_idx, rot, jaw_rows, r, dz, z, reg, damp, row_pos, rowbuf, g)
    work = np.zeros(n, np.bool_)
    dropped = np.zeros(n, np.bool_)
    for k in range(n):
        if k < nj or w[k - nj] > 0.0:
            work[k] = True
    wants = np.empty(n)
    for k in range(n):
        wants[k] = -g[k] if dz[k] <= lo[k] else (g[k] if dz[k] >= hi[k] else abs(g[k]))
    _gf_top(wants, np.arange(n), grow, work)
    gram = np.empty((rowbuf.shape[0], rowbuf.shape[0]))  # products of the cached rows, filled as they come
    rdot = np.empty(rowbuf.shape[0])  # and of each with r
    n_gram = 0
    for _ in range(50):
        ws = np.flatnonzero(work)
        nw = ws.shape[0]
        for a in range(nw):
            k = ws[a]
            if row_pos[k] < 0:
                if n_rows == rowbuf.shape[0]:
                    bigger = np.empty((2 * n_rows, m3))
                    bigger[:n_rows] = rowbuf
                    rowbuf = bigger
                    g2 = np.empty((2 * n_rows, 2 * n_rows))
                    g2[:n_rows, :n_rows] = gram[:n_rows, :n_rows]
                    gram = g2
                    r2 = np.empty(2 * n_rows)
                    r2[:n_rows] = rdot[:n_rows]
                    rdot = r2
                _gf_row(model, seen_idx, rot, jaw_rows, k, rowbuf[n_rows])
                row_pos[k] = n_rows
                n_rows += 1
        if n_rows > n_gram:
            # The new rows' products with every cached row and with r (BLAS: the loops did not vectorise).
            blk = np.dot(rowbuf[n_gram:n_rows], rowbuf[:n_rows].T)
            gram[n_gram:n_rows, :n_rows] = blk
            gram[:n_rows, n_gram:n_rows] = blk.T
            rdot[n_gram:n_rows] = np.dot(rowbuf[n_gram:n_rows], r)
            n_gram = n_rows
        h = np.empty((nw, nw))
        rhs = np.empty(nw)
        for a in range(nw):
            pa = row_pos[ws[a]]
            rhs[a] = -rdot[pa] - reg[ws[a]] * z[ws[a]]
            for b in range(nw):
                h[a, b] = gram[pa, row_pos[ws[b]]]
            h[a, a] += reg[ws[a]] + damp
        sub = dz[ws]  # warm start: the last round's solution, zero for the newcomers
        # The QP's objective is half of this one: the same gain threshold for releasing a bound.
        box_qp(h, rhs, lo[ws], hi[ws], sub, np.int64(0), 1e-13, 0.5 * gain)
        dz[:] = 0.0
        for a in range(nw):
            dz[ws[a]] = sub[a]
        _gf_gradient(model, seen_idx, rot, jaw_rows, r, dz, z, reg, damp, row_pos, rowbuf, g)
        # Outside the set a variable sits at its starting value: optimal only at a bound the gradient pushes
        # it against (weights at 0 with g >= 0, at 1 with g <= 0). A shape joins only if moving it alone would
        # lower the objective by more than ``gain``: with redundant shapes the ridge alone would otherwise pull
        # in every in-between, each for a vanishing gain.
        n_bad = 0
        bad = np.empty(n, np.int64)
        for k in range(n):
            if work[k]:
                continue
            if dz[k] <= lo[k] + 1e-15:
                pull = max(-g[k], 0.0)
            elif dz[k] >= hi[k] - 1e-15:
                pull = max(g[k], 0.0)
            else:
                pull = abs(g[k])
            if pull * pull > gain * col2r[k]:
                bad[n_bad] = k
                n_bad += 1
        if n_bad == 0:
            return dz
        # Shapes of the set that ended at zero with the gradient holding them there leave it (at most once
        # per step, so the set cannot cycle): it stays as small as the solution's support plus the newcomers.
        for a in range(nw):
            k = ws[a]
            if k >= nj and dz[k] <= lo[k] + 1e-15 and g[k] >= 0.0 and not dropped[k]:
                work[k] = False
                dropped[k] = True
        _gf_top(np.abs(g), bad[:n_bad], grow, work)
    return dz


@nb.njit(cache=True, nogil=True)
def global_gauss_newton(model, cfg, seen_idx, p, w0, theta0, with_jaw, w_out, theta_out,
                        r_out):  # pragma: no cover - compiled
    """Minimise |r|^2 + l2 |w|^2 over the weights in [0, 1] (and, with ``with_jaw``, the jaw) by Gauss-Newton
    steps from (w0, theta0), each a box QP on a working set (:func:`working_set_step`) with
    Levenberg-Marquardt damping of the jaw. ``model``: a :class:`FitModel`; ``cfg``: :class:`FitSettings`.
    ``seen_idx`` (m,) the seen bundles, ``p`` (M, 3) cm the bundles. Writes ``w_out`` (S,), ``theta_out`` (4,)
    and the residuals ``r_out`` (3m,) of the seen bundles at the result. Returns the Gauss-Newton steps taken.

    Alternating between the jaw and the weights stalls where a shape and the jaw move the same bundles
    (ICT's mouthLowerDown and a degree of opening): each step undoes the other's gain; a joint step moves
    both along that valley. Without the jaw the problem is linear and one step solves it.
    """
    l2, gain, max_iter, grow, theta_scale = cfg.l2, cfg.gain, cfg.max_iter, cfg.grow, model.theta_scale
    n_s = model.basis.shape[0]
    nj = 4 if with_jaw else 0
    m3 = 3 * seen_idx.shape[0]
    w = np.minimum(np.maximum(w0, 0.0), 1.0)
    th = theta0.copy()
    reg = np.zeros(nj + n_s)
    reg[nj:] = l2
    r = np.empty(m3)
    rot = np.empty((3, 3))
    jaw_rows = np.zeros((nj, m3))
    _gf_system(model, seen_idx, p, w, th, with_jaw, r, jaw_rows, rot)
    # The shapes' column norms serve only the joining test; a step's change of the jaw barely moves them.
    col2 = np.empty(nj + n_s)
    global_col2(model.prod, seen_idx, rot, model.bw, col2[nj:])
    for q in range(nj):
        col2[q] = np.sum(jaw_rows[q] ** 2)
    c = np.sum(r**2) + l2 * np.sum(w**2)
    mu = 0.0
    r_new = np.empty(m3)
    rot_new = np.empty((3, 3))
    jaw_new = np.zeros((nj, m3))
    steps = 0
    for _ in range(max_iter):
        steps += 1
        dz = working_set_step(model, seen_idx, rot, jaw_rows, r, w, reg, mu, col2, gain, grow)
        w_new = np.minimum(np.maximum(w + dz[nj:], 0.0), 1.0)
        th_new = th.copy()
        for q in range(nj):
            th_new[q] += dz[q] * theta_scale[q]
        _gf_system(model, seen_idx, p, w_new, th_new, with_jaw, r_new, jaw_new, rot_new)
        c_new = np.sum(r_new**2) + l2 * np.sum(w_new**2)
        if not with_jaw:
            w, th = w_new, th_new
            r[:] = r_new
            break
        if c_new <= c:
            step = 0.0
            for k in range(dz.shape[0]):
                step = max(step, abs(dz[k]))
            stalled = c_new > c * (1 - 1e-10)
            w, th, c = w_new, th_new, c_new
            r[:] = r_new
            rot[:] = rot_new
            jaw_rows[:] = jaw_new
            for q in range(nj):
                col2[q] = np.sum(jaw_rows[q] ** 2)
            mu *= 0.1
            # Stalled: redundant shapes can trade weight without changing the cost, so the step need not
            # vanish; a relative gain of 1e-10 does not move the surface.
            if step < 1e-9 or stalled:
                break
        elif c_new <= c * (1 + 1e-10):
            break  # at the minimum: the step only moves the cost by rounding
        else:
            # The jaw is nonlinear: damp toward gradient steps (in the scaled parameters) until it helps. The
            # damping penalises the step, not the weights (a ridge on w + dz would pull every weight to 0 and
            # could never be accepted: measured, 22 wasted steps on 2 % of frames).
            mu = max(mu * 10, 1e-6 * np.mean(col2))
            if mu > 1e12:
                break
    w_out[:] = w
    theta_out[:] = th
    r_out[:] = r
    return steps


@nb.njit(cache=True, nogil=True)
def global_fit_frame(model, cfg, seen_idx, p, w0, theta0, with_jaw, w_out, theta_out,
                     r_out):  # pragma: no cover - compiled
    """One frame's global fit (:class:`lgi.solve.globalfit.GlobalFit`): :func:`global_gauss_newton` over the jaw
    and the weights, then (with ``with_jaw``) the weights again at the final jaw exactly, since the joint
    solve stops at a tolerance. Arguments as for :func:`global_gauss_newton`."""
    steps = global_gauss_newton(model, cfg, seen_idx, p, w0, theta0, with_jaw, w_out, theta_out, r_out)
    if with_jaw:
        w1 = w_out.copy()
        th1 = theta_out.copy()
        # ``not with_jaw`` (False) rather than the literal: a literal argument is a type of its own, and numba
        # would compile the whole fit a second time for it.
        steps += global_gauss_newton(model, cfg, seen_idx, p, w1, th1, not with_jaw, w_out, theta_out, r_out)
    return steps
