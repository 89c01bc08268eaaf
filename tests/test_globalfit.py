"""The compiled global fit (lgi.solve._globalfit_kernels global_*): its pieces against direct numpy expressions and its
solution against a dense bounded least-squares solve."""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear

from lgi.solve import _globalfit_kernels as K
from lgi.solve.globalfit import EXACT_GAIN, GlobalFit
from lgi.solve.jaw import JawRig, jaw_matrix


def _problem(seed: int = 0, n_m: int = 40, n_base: int = 10, n_mix: int = 50):
    """Bundles of a rigged actor whose shapes include exact in-betweens (redundant columns)."""
    rng = np.random.default_rng(seed)
    rest = rng.normal(0, 3, (n_m, 3))
    base = rng.normal(0, 0.3, (n_base, n_m, 3))
    mix = rng.uniform(0, 1, (n_mix, n_base)) * (rng.uniform(size=(n_mix, n_base)) < 0.25)
    basis = np.concatenate([base, np.tensordot(mix, base, axes=1)])
    bw = np.where(rest[:, 1] < 0, rng.uniform(0.3, 1, n_m), 0.0)  # the lower half moves with the jaw
    rig = JawRig(np.array([0.0, 2.0, -6.0]), np.zeros(1))
    table = np.concatenate([rest[None], rest[None] + basis])
    return rng, table, rig, bw


def test_jaw_maps_are_rigid_motions_about_the_pivot() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        theta, pivot = rng.normal(0, 10, 4), rng.normal(0, 5, 3)
        t = jaw_matrix(theta, pivot)
        assert np.abs(t[:3, :3] @ t[:3, :3].T - np.eye(3)).max() < 1e-12
        assert np.linalg.det(t[:3, :3]) > 0
        # The pivot moves only by the slide (forward, +z).
        assert np.abs(t[:3, :3] @ pivot + t[:3, 3] - pivot - [0, 0, theta[3]]).max() < 1e-12
        assert np.array_equal(t[3], [0, 0, 0, 1])


def test_column_norms_and_gradient_of_the_skinned_jacobian() -> None:
    _, table, rig, bw = _problem(1)
    basis = table[1:] - table[0]
    seen = np.flatnonzero(np.arange(basis.shape[1]) % 7 != 3)
    rot = np.ascontiguousarray(jaw_matrix(np.array([14.0, 3.0, -2.0, 0.1]), rig.pivot)[:3, :3])
    maps = (1 - bw[seen])[:, None, None] * np.eye(3) + bw[seen][:, None, None] * rot
    jac = np.einsum("eij,kej->kei", maps, basis[:, seen]).reshape(len(basis), -1)  # (S, 3m)
    col2 = np.empty(len(basis))
    K.global_col2(K.shape_products(basis), seen, rot, bw, col2)
    assert np.abs(col2 - (jac**2).sum(1)).max() < 1e-12
    v = np.random.default_rng(2).normal(size=jac.shape[1])
    g = np.empty(len(basis))
    K.global_gradient(np.ascontiguousarray(basis), seen, rot, bw, v, g)
    assert np.abs(g - jac @ v).max() < 1e-12


def test_weights_at_a_given_jaw_match_dense_bounded_least_squares() -> None:
    rng, table, rig, bw = _problem(4)
    basis = table[1:] - table[0]
    fit = GlobalFit(table, rig, bw, gain=EXACT_GAIN)
    theta = np.array([9.0, -2.0, 1.0, 0.05])
    m = rig.blend_matrices(theta, bw)
    for trial in range(5):
        w_true = rng.uniform(0, 1, len(basis)) * (rng.uniform(size=len(basis)) < 0.1)
        x = table[0] + np.tensordot(w_true, basis, axes=1)
        p = np.einsum("mij,mj->mi", m[:, :, :3], x) + m[:, :, 3] + rng.normal(0, 0.01, x.shape)
        p[trial] = np.nan  # a missing bundle
        res = fit.solve(p, jaw=theta)
        seen = np.isfinite(p[:, 0])
        jac = np.einsum("eij,kej->kei", m[seen, :, :3], basis[:, seen]).reshape(len(basis), -1).T
        b = (p[seen] - np.einsum("mij,mj->mi", m[seen, :, :3], table[0][seen]) - m[seen, :, 3]).ravel()
        n = len(basis)
        ref = lsq_linear(np.vstack([jac, np.sqrt(fit.l2) * np.eye(n)]), np.r_[b, np.zeros(n)], bounds=(0, 1),
                         method="bvls", tol=1e-14).x

        def cost(w: np.ndarray, jac: np.ndarray = jac, b: np.ndarray = b) -> float:
            return float(np.sum((jac @ w - b) ** 2) + fit.l2 * w @ w)

        # Redundant shapes make the minimiser non-unique up to the ridge: compare the objective and the fitted
        # bundles. The fit stops when no shape on its own would lower the objective by more than ``gain``
        # (1e-14 cm^2); trading weight among several in-betweens can still gain a little (up to 2e-5 of the
        # cost here: 2e-7 cm^2 over 117 coordinates with 0.1 mm noise), which moves no bundle by 1e-5 mm
        # (measured: 6e-7 mm).
        assert cost(res.weights) <= cost(ref) * (1 + 1e-4), trial
        assert np.abs(jac @ res.weights - jac @ ref).max() < 1e-6, trial
        w = res.weights
        g = jac.T @ (jac @ w - b) + fit.l2 * w  # half the objective's gradient
        col2 = (jac**2).sum(0) + fit.l2
        free = (w > 0) & (w < 1)
        assert np.abs(g[free]).max() < 1e-10
        assert np.all(np.maximum(-g[w == 0], 0) ** 2 <= fit.gain * col2[w == 0])
        assert np.all((res.weights >= 0) & (res.weights <= 1))
        assert np.isnan(res.residual[trial]) and np.isfinite(res.residual[seen]).all()


def test_joint_jaw_fit_recovers_the_jaw_and_stops_at_its_own_solution() -> None:
    rng, table, rig, bw = _problem(5)
    basis = table[1:] - table[0]
    fit = GlobalFit(table, rig, bw, gain=EXACT_GAIN)
    theta = np.array([11.0, 1.5, -1.0, 0.04])
    w_true = rng.uniform(0, 1, len(basis)) * (np.arange(len(basis)) < 10) * (rng.uniform(size=len(basis)) < 0.3)
    m = rig.blend_matrices(theta, bw)
    x = table[0] + np.tensordot(w_true, basis, axes=1)
    p = np.einsum("mij,mj->mi", m[:, :, :3], x) + m[:, :, 3]
    res = fit.solve(p)
    assert res.jaw_source == "estimated"
    assert np.abs(res.jaw - theta).max() < 1e-3
    assert res.rms < 1e-5
    # Restarted at its solution the Gauss-Newton loop must stop at once: a damping that pulled the weights
    # (not the step) toward zero could never be accepted there and ran to its iteration cap.
    seen_idx = np.arange(len(p))
    w, th, r = np.empty(len(basis)), np.empty(4), np.empty(3 * len(p))
    cfg = fit.settings()._replace(max_iter=30)
    steps = K.global_gauss_newton(fit.model, cfg, seen_idx, p, res.weights, res.jaw.copy(), True, w, th, r)
    assert steps <= 2
    assert np.abs(th - res.jaw).max() < 1e-6


def test_a_shots_fits_kept_on_disk_come_back_bit_for_bit() -> None:
    from lgi.solve.globalfit import FitStore, GlobalFitResult

    rng = np.random.default_rng(4)
    fits = {f: GlobalFitResult(rng.random(7), rng.normal(size=4), rng.random(5), float(rng.random()),
                               ["estimated", "given"][f % 2]) for f in (0, 1, 2, 5, 6, 9)}
    store = FitStore(10, 7, 5, jaw=True)
    store.BLOCK = 4  # several writes, one of them of a run with a gap
    for f, fit in fits.items():
        store.put(f, fit)
    got = store.take(np.arange(10))
    for f in range(10):
        if f not in fits:
            assert got[f] is None
            continue
        a, b = fits[f], got[f]
        assert np.array_equal(a.weights, b.weights) and np.array_equal(a.jaw, b.jaw)
        assert np.array_equal(a.residual, b.residual) and a.rms == b.rms and a.jaw_source == b.jaw_source
    no_jaw = FitStore(2, 3, 2, jaw=False)
    no_jaw.put(1, GlobalFitResult(np.ones(3), None, np.zeros(2), 0.5, ""))
    assert no_jaw.take([0, 1])[0] is None and no_jaw.take([1])[0].jaw is None
