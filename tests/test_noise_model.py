"""Bundles as measurements: the noise seen per axis from the shot (or given by the bundles' covariances), exact
bundles still passed through, and the surface held off noisy ones only as far as their noise says."""

from __future__ import annotations

import numpy as np
import pytest

from lgi.capture.bundles import Bundles
from lgi.evaluation.accuracy import build_set_index
from lgi.evaluation.baselines import RiggedBlendshapeSolver
from lgi.evaluation.benchsets import synthetic_set
from lgi.solve.solver import LGISolver
from tests.checks import THROUGH_MM, gaps_mm


@pytest.fixture(scope="module")
def synth():
    bs = synthetic_set(frames=90, n_vertices=3000)
    return bs, build_set_index(bs)


def _noisy(bundles: np.ndarray, axes_mm, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return bundles + rng.normal(size=bundles.shape) * np.asarray(axes_mm) / 10.0


def _rms(recon: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    e = np.linalg.norm(np.asarray(recon, np.float64) - truth, axis=2)[:, mask] * 10
    return float(np.sqrt(np.mean(e**2)))


def test_exact_bundles_give_the_exact_reconstruction(synth) -> None:
    bs, index = synth
    auto = LGISolver(index)
    res = auto.solve_sequence(bs.bundles)
    # The shot's trajectories, off the face model's fit, do not change beyond a micrometre: exact.
    assert res.noise == 0 and auto.resolve_noise(bs.bundles).estimate.noise_mm < 1e-3
    told = LGISolver(index).solve_sequence(bs.bundles, noise=0)
    assert np.array_equal(res.vertices, told.vertices)
    assert gaps_mm(res.vertices, bs.layout, bs.bundles).max() < THROUGH_MM


@pytest.mark.parametrize("axes", [(0.01, 0.01, 0.01), (0.0025, 0.0025, 0.01), (0.1, 0.1, 0.1), (0.025, 0.025, 0.1)])
def test_noise_is_seen_per_axis_from_a_hundredth_of_a_millimetre(synth, axes) -> None:
    bs, index = synth
    sol = LGISolver(index)
    noise = sol.resolve_noise(_noisy(bs.bundles, axes))
    est = noise.estimate
    assert est.is_noise
    np.testing.assert_allclose(est.axis_mm, axes, rtol=0.3)
    np.testing.assert_allclose(noise.axes, est.axis_mm)
    if axes[2] > axes[0]:  # stereo-like noise is seen as such: deeper along z
        assert est.axis_mm[2] > 2.5 * est.axis_mm[:2].max()


def test_small_noise_keeps_the_local_geometry(synth) -> None:
    bs, index = synth
    shot = _noisy(bs.bundles, (0.02, 0.02, 0.02))
    res = LGISolver(index).solve_sequence(shot)
    assert res.noise > 0
    smoothing = LGISolver(index)
    fits = RiggedBlendshapeSolver(index)
    best_fit = min(_rms(fits.solve_sequence(shot), bs.truth, bs.mask),
                   _rms(fits.solve_sequence(smoothing.denoise(shot, smoothing.resolve_noise(shot))[0]), bs.truth,
                        bs.mask))
    ours = _rms(res.vertices, bs.truth, bs.mask)
    assert ours < 0.9 * best_fit, (ours, best_fit)
    # Between the noisy bundles, not through them.
    assert np.median(gaps_mm(res.vertices, bs.layout, shot)) > 0.005


def _with_covariance(bs, positions: np.ndarray, cov: np.ndarray) -> Bundles:
    return Bundles(frames=np.arange(len(positions)), markers=list(bs.layout.names), positions=positions,
                   covariance=cov)


def test_covariances_given_are_the_noise(synth, caplog) -> None:
    bs, index = synth
    axes = np.array([0.005, 0.005, 0.02])
    cov = np.broadcast_to(np.diag((axes / 10) ** 2), (*bs.bundles.shape[:2], 3, 3)).copy()
    sol = LGISolver(index)
    shot = _with_covariance(bs, _noisy(bs.bundles, axes), cov)
    res = sol.solve_sequence(shot)
    noise = sol.prepare_shot(shot).noise
    np.testing.assert_allclose(noise.axes, axes)
    assert noise.estimate is None and res.noise > 0
    np.testing.assert_allclose(np.sort(noise.sigma, axis=1), np.tile(np.sort(axes), (bs.n_markers, 1)))
    # A marker given no covariance takes the median marker's noise, and the user hears of it.
    cov[:, 7] = np.nan
    with caplog.at_level("WARNING", logger="lgi"):
        LGISolver(index).prepare_shot(_with_covariance(bs, _noisy(bs.bundles, axes), cov))
    assert any("no covariance" in r.getMessage() and bs.layout.names[7] in r.getMessage() for r in caplog.records)


def test_a_bundle_with_a_huge_sigma_does_not_move_the_surface(synth, caplog) -> None:
    bs, index = synth
    axes = np.array([0.005, 0.005, 0.02])
    shot = _noisy(bs.bundles, axes)
    cov = np.broadcast_to(np.diag((axes / 10) ** 2), (*shot.shape[:2], 3, 3)).copy()
    k = 40
    cov[:, k] = np.eye(3)  # 10 mm
    moved = shot.copy()
    moved[:, k] += np.array([0.3, -0.2, 0.5])
    a = LGISolver(index).solve_sequence(_with_covariance(bs, shot, cov))
    b = LGISolver(index).solve_sequence(_with_covariance(bs, moved, cov))
    assert np.abs(a.vertices - b.vertices).max() * 10 < 1e-6
    d = b.diagnostics[b.diagnostics.marker == bs.layout.names[k]]
    assert d.fallback.str.startswith("left out for its noise").all()
    assert any("left out of the fits" in r.getMessage() for r in caplog.records)


def test_noisy_shot_finished_in_chunks_gives_the_same_bits(synth) -> None:
    bs, index = synth
    sol = LGISolver(index)
    shot = _noisy(bs.bundles, (0.01, 0.01, 0.04))
    pos, frames, bridged, noise = sol.prepare_shot(shot, None, 0, "auto")
    fit_pos, noise = sol.denoise(pos, noise)
    sol = sol.with_noise(noise)
    left = noise.left
    sels = sol.select_sequence(fit_pos, frames)
    whole = sol.finish_sequence(sels, pos, frames, bridged, fit_pos=fit_pos)
    parts = [sol.finish_sequence(sels, pos, frames, bridged, fit_pos=fit_pos, lo=lo, hi=min(lo + 25, len(pos)),
                                 left=left) for lo in range(0, len(pos), 25)]
    assert np.array_equal(whole.vertices, np.concatenate([p.vertices for p in parts]))


def test_the_fits_leverage_is_the_share_of_noise_it_takes_at_each_bundle(synth) -> None:
    # The two-part smoothing gives each marker's fitted part its own share of the noise: the variance the fit
    # passes on from noise on every bundle, measured over draws of it on one frame.
    bs, index = synth
    sol = LGISolver(index)
    sigma_cm = 1e-4
    draws = bs.bundles[40] + np.random.default_rng(3).normal(size=(400, *bs.bundles.shape[1:])) * sigma_cm
    fitted, leverage, _ = sol.model_fit(draws)
    passed = np.var(fitted, axis=0) / sigma_cm**2
    assert leverage.shape == passed.shape == (index.n_markers, 3)
    assert leverage.max() > 3 * np.median(leverage)  # far from one share for all
    np.testing.assert_allclose(leverage, passed, atol=0.03, rtol=0.25)


def test_an_exact_shot_is_fitted_once_per_frame(synth) -> None:
    # Resolving the noise fits every frame; an exact shot's choice takes those fits instead of solving again,
    # and gives the bits it would have given solving them.
    bs, index = synth
    sol = LGISolver(index)
    calls = []
    solve = sol.global_fit.solve
    sol.global_fit.solve = lambda *a, **k: calls.append(1) or solve(*a, **k)
    res = sol.solve_sequence(bs.bundles)
    assert res.noise == 0 and len(calls) == len(bs.bundles)
    told = LGISolver(index).solve_sequence(bs.bundles, noise=0)
    assert np.array_equal(res.vertices, told.vertices)


def test_a_shot_leaves_the_solver_as_it_was(synth) -> None:
    # The noise is a value the shot carries: after a shot whose covariances drop a marker and turn every noise
    # axis, the solver's next frame and its next shot keeping the solver's noise (noise=None) are a fresh
    # solver's, bit for bit.
    bs, index = synth
    axes = np.array([0.005, 0.005, 0.02])
    shot = _noisy(bs.bundles, axes)
    cov = np.broadcast_to(np.diag((axes / 10) ** 2), (*shot.shape[:2], 3, 3)).copy()
    cov[:, 40] = np.eye(3)
    fresh = LGISolver(index)
    frame = fresh.solve_frame(shot[10])
    whole = fresh.solve_sequence(shot, noise=None)
    sol = LGISolver(index)
    noisy = sol.solve_sequence(_with_covariance(bs, shot, cov))
    assert noisy.noise > 0 and not np.array_equal(noisy.vertices, whole.vertices)
    assert sol.noise == 0 and np.array_equal(sol.solve_frame(shot[10]).vertices, frame.vertices)
    assert np.array_equal(sol.solve_sequence(shot, noise=None).vertices, whole.vertices)
    # A solver bound to the shot's noise is another object; the one it came from is unchanged.
    prep = sol.prepare_shot(_with_covariance(bs, shot, cov))
    bound = sol.with_noise(prep.noise)
    assert bound.noise > 0 and bound.shot_noise.dropped[40] and not sol.shot_noise.dropped.any()
    assert bound.global_fit is not sol.global_fit and bound.index is sol.index
