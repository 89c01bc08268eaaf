"""The box-constrained QP (lgi.solve.qp.box_qp) against a bounded least-squares solve, on well-posed problems
and on the redundant columns that exact in-betweens give the global fit."""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from lgi.solve.qp import box_qp


def test_box_qp_matches_bounded_least_squares() -> None:
    rng = np.random.default_rng(0)
    for n in (3, 12, 40):
        a = rng.normal(size=(21, n))
        b = rng.normal(size=21)
        lo, hi = -rng.uniform(0, 1, n), rng.uniform(0, 1, n)
        x = np.zeros(n)
        box_qp(a.T @ a + 1e-6 * np.eye(n), a.T @ b, lo, hi, x)
        ref = lsq_linear(np.vstack([a, 1e-3 * np.eye(n)]), np.r_[b, np.zeros(n)], bounds=(lo, hi), method="bvls").x
        assert np.abs(x - ref).max() < 1e-8


def test_box_qp_on_redundant_columns_from_warm_starts() -> None:
    # In-betweens are exact combinations of other shapes: with a ridge of 1e-6 the normal matrix has a
    # condition of ~1e8, where a plain active-set method cycles on rounding (the case of the global fit).
    rng = np.random.default_rng(1)
    for trial in range(20):
        base = rng.normal(size=(90, 12))
        mix = rng.uniform(0, 1, (12, 60)) * (rng.uniform(size=(12, 60)) < 0.2)
        a = np.hstack([base, base @ mix])
        n = a.shape[1]
        b = a @ (rng.uniform(0, 1, n) * (rng.uniform(size=n) < 0.1)) + rng.normal(0, 0.05, 90)
        h = a.T @ a + 1e-6 * np.eye(n)
        ref = lsq_linear(np.vstack([a, 1e-3 * np.eye(n)]), np.r_[b, np.zeros(n)], bounds=(0, 1), method="bvls").x
        g = a.T @ b
        for start in (np.zeros(n), rng.uniform(0, 1, n), np.clip(ref + rng.normal(0, 0.05, n), 0, 1)):
            x = start.copy()
            its = box_qp(h, g, np.zeros(n), np.ones(n), x)
            assert 0 <= its < 10 * n + 10, trial
            assert np.all((x >= 0) & (x <= 1))
            # Redundant columns: the objective, not the weights, is unique up to the ridge.
            f_x, f_ref = 0.5 * x @ h @ x - g @ x, 0.5 * ref @ h @ ref - g @ ref
            assert f_x <= f_ref + 1e-9 * (1 + abs(f_ref)), trial
