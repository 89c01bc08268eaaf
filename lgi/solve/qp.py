"""A small dense box-constrained quadratic programme, compiled (numba): ``min 0.5 x'Hx - g'x`` subject to
``lo <= x <= hi``, by a primal active-set method on an updated Cholesky factor.

The local fits (:mod:`lgi.solve._select_kernels`) and each Gauss-Newton step of the global fit
(:mod:`lgi.solve._globalfit_kernels`) solve one per bundle or frame.
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True)
def _chol_add(h, fl, nf, a, lf):  # pragma: no cover - compiled
    """Append variable ``a`` to the Cholesky factor ``lf`` of h[fl[:nf], fl[:nf]] (O(nf^2)); returns False
    (nothing changed) if the extended block is not numerically positive definite."""
    d = h[a, a]
    for c in range(nf):
        s = h[a, fl[c]]
        for k in range(c):
            s -= lf[nf, k] * lf[c, k]
        lf[nf, c] = s / lf[c, c]
        d -= lf[nf, c] * lf[nf, c]
    if d <= 1e-14 * h[a, a]:
        return False
    lf[nf, nf] = np.sqrt(d)
    fl[nf] = a
    return True


@nb.njit(cache=True)
def _chol_remove(fl, nf, p, lf):  # pragma: no cover - compiled
    """Remove the variable at position ``p`` of ``fl`` from the Cholesky factor ``lf`` (O(nf^2)): its row is
    dropped and the columns it leaves out of shape are rotated back to lower-triangular (Givens)."""
    for i in range(p, nf - 1):
        fl[i] = fl[i + 1]
        for k in range(i + 2):
            lf[i, k] = lf[i + 1, k]
    for c in range(p, nf - 1):
        x0 = lf[c, c]
        y0 = lf[c, c + 1]
        r = np.sqrt(x0 * x0 + y0 * y0)
        cs = x0 / r
        sn = y0 / r
        for i in range(c, nf - 1):
            u = lf[i, c]
            v = lf[i, c + 1]
            lf[i, c] = cs * u + sn * v
            lf[i, c + 1] = -sn * u + cs * v
    for i in range(nf - 1):
        lf[i, nf - 1] = 0.0


@nb.njit(cache=True)
def box_qp(h, g, lo, hi, x, max_iter=0, tol=1e-13, gain=0.0):  # pragma: no cover - compiled
    """Minimise 0.5 x'hx - g'x subject to lo <= x <= hi (h SPD, small), in place from a feasible x.

    Primal active-set method: Newton steps on the free variables, cut at the first bound they reach (which
    joins the active set); at a subspace minimum the bound variable whose multiplier most wants it free is
    released, if releasing it alone would lower the objective by more than ``gain`` (``m^2 / (2 h_aa)`` for
    multiplier ``m``). The Cholesky factor of the free block is updated as variables join and leave
    (O(n^2) per step, not a factorisation). Warm starts from a nearby solution take a few steps.

    Rounding can make a just-released variable's Newton step point back into its bound (redundant columns
    with a ridge of 1e-6 against norms of 1: h's condition is ~1e8 and the multiplier at the rounding
    level); the variable is then returned to its bound and not released again, and a variable whose column
    the free block cannot take (not positive definite) stays at its bound, so the method cannot cycle.
    Returns the iterations, or -1 if the starting free block is not positive definite.
    """
    n = x.shape[0]
    if max_iter <= 0:
        max_iter = 10 * n + 10
    state = np.zeros(n, np.int64)  # 0 free, -1 at the lower bound, +1 at the upper
    for a in range(n):
        if x[a] <= lo[a]:
            x[a] = lo[a]
            state[a] = -1
        elif x[a] >= hi[a]:
            x[a] = hi[a]
            state[a] = 1
    banned = np.zeros(n, np.bool_)
    grad = np.empty(n)
    fl = np.empty(n, np.int64)
    step = np.empty(n)
    lf = np.zeros((n, n))
    nf = 0
    for a in range(n):
        if state[a] == 0:
            if not _chol_add(h, fl, nf, a, lf):
                return -1
            nf += 1
    scale = 0.0
    for a in range(n):
        scale = max(scale, abs(g[a]), abs(h[a, a]))
    tol = max(tol, 1e-12 * scale)
    released = -1
    at_min = False  # after a full Newton step: at the free variables' minimum, up to rounding
    for it in range(max_iter):
        for a in range(n):
            acc = -g[a]
            for b in range(n):
                acc += h[a, b] * x[b]
            grad[a] = acc
        big = 0.0
        if nf > 0 and not at_min:
            for c in range(nf):
                s = -grad[fl[c]]
                for k in range(c):
                    s -= lf[c, k] * step[k]
                step[c] = s / lf[c, c]
            for c in range(nf - 1, -1, -1):
                s = step[c]
                for k in range(c + 1, nf):
                    s -= lf[k, c] * step[k]
                step[c] = s / lf[c, c]
                big = max(big, abs(step[c]))
        if at_min or big <= 1e-14 * (1.0 + scale):
            # (Repeating the Newton step there would only chase rounding: with h's condition ~1e8 its
            # size stays ~1e-11, never below a fixed threshold.)
            at_min = False
            # At the minimum over the free variables: release the most wrongly held bound, if any.
            worst = -1
            worst_v = tol
            for a in range(n):
                if banned[a]:
                    continue
                m = -grad[a] if state[a] == -1 else grad[a] if state[a] == 1 else 0.0
                if m > worst_v and m * m > gain * 2.0 * h[a, a]:
                    worst, worst_v = a, m
            if worst < 0:
                return it
            if not _chol_add(h, fl, nf, worst, lf):
                banned[worst] = True
                at_min = True
                continue
            nf += 1
            state[worst] = 0
            released = worst
            continue
        alpha = 1.0
        block = -1
        for c in range(nf):
            a = fl[c]
            if step[c] < 0.0:
                t = (lo[a] - x[a]) / step[c]
            elif step[c] > 0.0:
                t = (hi[a] - x[a]) / step[c]
            else:
                continue
            if t < alpha:
                alpha = t
                block = c
        if block >= 0 and fl[block] == released and alpha <= 1e-12:
            # The released variable would go straight back to its bound: rounding, not a descent direction.
            state[released] = -1 if step[block] < 0.0 else 1
            banned[released] = True
            _chol_remove(fl, nf, block, lf)
            nf -= 1
            released = -1
            at_min = True
            continue
        released = -1
        for c in range(nf):
            x[fl[c]] += alpha * step[c]
        at_min = block < 0
        if block >= 0:
            a = fl[block]
            if step[block] < 0.0:
                x[a] = lo[a]
                state[a] = -1
            else:
                x[a] = hi[a]
                state[a] = 1
            _chol_remove(fl, nf, block, lf)
            nf -= 1
    return max_iter
