"""The default reconstruction: a global fit of the jaw and shape weights, local refits per bundle, the noise
model; measured against the baselines on frames that are not dataset shapes (lgi.evaluation.benchsets)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lgi.errors import InputError
from lgi.evaluation.accuracy import build_set_index
from lgi.evaluation.baselines import RiggedBlendshapeSolver
from lgi.evaluation.benchsets import ict_jaw_set, synthetic_set
from lgi.solve.results import join_results
from lgi.solve.solver import LGISolver
from lgi.solve.temporal import denoise_trajectories, estimate_noise
from tests.checks import THROUGH_MM, gaps_mm


@pytest.fixture(scope="module")
def synth_set():
    bs = synthetic_set(frames=60, n_vertices=3000)
    return bs, build_set_index(bs)


def _rms(recon: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    e = np.linalg.norm(np.asarray(recon, np.float64) - truth, axis=2)[:, mask] * 10
    return float(np.sqrt(np.mean(e**2)))


def test_jaw_estimated_with_the_shapes_on_the_synthetic_actor(synth_set) -> None:
    bs, index = synth_set
    res = LGISolver(index).solve_sequence(bs.bundles)
    err = np.abs(res.jaw - bs.true_jaw)
    assert err[:, 0].max() < 0.1  # degrees of opening; measured 0.013
    assert set(res.diagnostics.jaw_source) == {"estimated"}
    assert {"fit_rms_mm", "fit_residual_mm", "jaw_open_deg", "source"} <= set(res.diagnostics.columns)


def test_default_beats_the_rigged_blendshape_fit_and_passes_through_bundles(synth_set) -> None:
    bs, index = synth_set
    res = LGISolver(index).solve_sequence(bs.bundles)
    fit = RiggedBlendshapeSolver(index).solve_sequence(bs.bundles)
    simplex = LGISolver(index, method="simplex").solve_sequence(bs.bundles)
    ours, theirs = _rms(res.vertices, bs.truth, bs.mask), _rms(fit, bs.truth, bs.mask)
    assert ours < theirs
    assert ours < _rms(simplex.vertices, bs.truth, bs.mask)
    assert res.noise == 0 and gaps_mm(res.vertices, bs.layout, bs.bundles).max() < THROUGH_MM
    # Bundles whose neighbourhood the global weights already fit keep them; the others are refitted.
    src = res.diagnostics.source
    assert (src != "simplex").mean() > 0.5 and (src == "local fit").mean() > 0.2


def test_noise_is_estimated_and_handled(synth_set) -> None:
    bs, index = synth_set
    pairs = LGISolver(index)._nb_pairs
    noisy = estimate_noise(bs.noisy, pairs)
    assert noisy.is_noise and abs(noisy.noise_mm - 0.3) < 0.05
    clean = estimate_noise(bs.bundles, pairs)
    assert clean.noise_mm < 0.05
    sol = LGISolver(index)
    res = sol.solve_sequence(bs.noisy)
    prep = sol.prepare_shot(bs.noisy)
    assert abs(res.noise - 0.3) < 0.05 and sol.denoise(prep.positions, prep.noise)[1].windows is not None
    # Noisy bundles keep their local geometry: they are refitted locally, not all given the global weights.
    d = res.diagnostics
    assert (d.source == "local fit").mean() > 0.5 and (d.source == "simplex").sum() == 0
    # ... and the surface is not taken through them: it stays about the noise away.
    gaps = gaps_mm(res.vertices, bs.layout, bs.noisy)
    assert 0.1 < np.nanmedian(gaps) < 0.6
    # With every bundle on the same weights the single-combination blend equals the per-vertex one.
    from lgi.solve._blend_kernels import blend

    sel = sol.select_frame(bs.noisy[5])
    nz = np.flatnonzero(sel.fit.weights)
    shapes = np.tile(nz + 1, (index.n_markers, 1))
    weights = np.tile(sel.fit.weights[nz], (index.n_markers, 1))
    a = index.arrays
    x = np.empty_like(sol.neutral)
    blend(sol.neutral, sol.deltas, a["w_indptr"], a["w_indices"], a["w_data"], shapes, weights, x)
    assert np.abs(sol.surface(shapes, weights, sel.jaw) - sol.rig.skin(x, sel.jaw)).max() < 1e-9
    fit = RiggedBlendshapeSolver(index).solve_sequence(bs.noisy)
    assert _rms(res.vertices, bs.truth, bs.mask) < _rms(fit, bs.truth, bs.mask)
    # Told the bundles are exact, the surface passes through every seen one (noise and all).
    exact = LGISolver(index).solve_sequence(bs.noisy, noise=0)
    assert exact.noise == 0 and gaps_mm(exact.vertices, bs.layout, bs.noisy).max() < THROUGH_MM


def test_independent_poses_are_not_taken_for_noise(synth_set, caplog) -> None:
    bs, index = synth_set
    rng = np.random.default_rng(1)
    # The performance's frames shuffled, their motion exaggerated so that most markers change from frame to
    # frame by more than the noise floor: independent poses, not a noisy performance.
    rest = bs.layout.evaluate(bs.dataset.neutral)
    poses = rest + 10 * (bs.bundles[rng.permutation(bs.n_frames)] - rest)
    sol = LGISolver(index)
    with caplog.at_level(logging.WARNING, logger="lgi"):
        noise = sol.resolve_noise(poses)
    assert noise.level == 0 and noise.estimate.coherence > 0.3 and noise.estimate.noise_mm > 0.05
    assert any("not measurement noise" in r.getMessage() for r in caplog.records)


def test_denoising_chooses_wider_windows_for_slower_markers() -> None:
    rng = np.random.default_rng(2)
    t = np.arange(200)[:, None]
    slow = np.concatenate([np.sin(t / 40.0), np.cos(t / 40.0), 0 * t], 1)
    fast = np.concatenate([np.sin(t / 3.0), np.cos(t / 3.0), 0 * t], 1)
    truth = np.stack([slow, fast], 1)  # cm
    noisy = truth + rng.normal(scale=0.03, size=truth.shape)
    out, windows = denoise_trajectories(noisy, 0.3)
    assert np.median(windows[:, 0]) > np.median(windows[:, 1])
    for m in range(2):
        assert np.sqrt(np.mean((out[:, m] - truth[:, m]) ** 2)) < np.sqrt(np.mean((noisy[:, m] - truth[:, m]) ** 2))


def test_unobservable_jaw_is_said(synth_set, caplog) -> None:
    from lgi.index.build import build_index

    bs, _ = synth_set
    rig = bs.rig
    w = bs.layout.evaluate(rig.weights[:, None])[:, 0]
    upper = bs.layout.subset([n for n, v in zip(bs.layout.names, w, strict=True) if v < 0.05])
    index, _ = build_index(bs.dataset, upper, show_progress=False, jaw_rig=rig)
    with caplog.at_level(logging.WARNING, logger="lgi"):
        sol = LGISolver(index)
    assert any("cannot be estimated" in r.getMessage() for r in caplog.records)
    res = sol.solve_sequence(upper.evaluate(bs.truth[:5]))
    assert set(res.diagnostics.jaw_source) == {"held at rest (not observable)"}


def test_ict_layout_estimates_the_rotating_jaw_within_a_degree(ict_dir) -> None:
    bs = ict_jaw_set(ict_dir, frames=200)
    index = build_set_index(bs)
    res = LGISolver(index).solve_sequence(bs.bundles)
    assert np.abs(res.jaw[:, 0] - bs.true_jaw[:, 0]).max() < 1.0
    noisy = LGISolver(index).solve_sequence(bs.noisy)
    assert np.abs(noisy.jaw[:, 0] - bs.true_jaw[:, 0]).max() < 1.0


@pytest.mark.parametrize("noise", [0.3, 0.0], ids=["noisy", "exact"])
def test_sequence_on_two_threads_equals_the_two_passes(synth_set, noise) -> None:
    # solve_sequence chooses frame f + 1 while it blends frame f, each thread with the kernels' one-thread twins;
    # the result must be the one that choosing every frame and then blending them (parallel kernels) gives, and
    # a failure in the choosing thread must reach the caller.
    bs, index = synth_set
    sol = LGISolver(index)
    shot = bs.noisy if noise else bs.bundles
    res = sol.solve_sequence(shot, noise=noise)
    pos, frames, bridged, shot_noise = sol.prepare_shot(shot, None, 0, noise)
    fit_pos, shot_noise = sol.denoise(pos, shot_noise)
    sol = sol.with_noise(shot_noise)
    sels = sol.select_sequence(fit_pos, frames)
    if not noise:
        assert (res.diagnostics.source == "local fit").any()  # the local fits ran on both threads' paths
    ref = sol.finish_sequence(sels, pos, frames, bridged, fit_pos=fit_pos)
    assert np.array_equal(res.vertices, ref.vertices)
    assert res.diagnostics.equals(ref.diagnostics)
    assert np.array_equal(res.jaw, ref.jaw)
    bad = np.array(shot, copy=True)
    bad[37] = np.nan  # no marker seen: the choice of frame 37 fails
    with pytest.raises(InputError) as err:
        sol.solve_sequence(bad, noise=noise)
    assert err.value.frame == 37 and "no marker seen" in err.value.message


@pytest.mark.parametrize("smooth", [1, 5], ids=["unsmoothed", "smoothed"])
def test_a_shot_streamed_in_blocks_gives_the_bits_of_the_whole(synth_set, smooth) -> None:
    # A long take is solved block by block, holding one block's surfaces and the choices its windows reach; the
    # blocks (an odd size, so that windows straddle them) must join into the whole shot's result.
    bs, index = synth_set
    sol = LGISolver(index)
    pos, frames, bridged, noise = sol.prepare_shot(bs.noisy, None, 0, "auto")
    fit_pos, noise = sol.denoise(pos, noise)
    sol = sol.with_noise(noise)
    whole = sol.solve_prepared(pos, frames, bridged, fit_pos, smooth)
    blocks = list(sol.stream_prepared(pos, frames, bridged, fit_pos, smooth, block=23))
    assert [(lo, hi) for lo, hi, _ in blocks] == [(lo, min(lo + 23, len(pos))) for lo in range(0, len(pos), 23)]
    assert all(len(r.vertices) == hi - lo for lo, hi, r in blocks)
    joined = join_results([r for _, _, r in blocks])
    assert np.array_equal(whole.vertices, joined.vertices)
    assert whole.diagnostics.equals(joined.diagnostics)
    assert np.array_equal(whole.jaw, joined.jaw)
    # Closed midway (a writer that failed), the chooser thread is stopped and the solver is usable again.
    stream = sol.stream_prepared(pos, frames, bridged, fit_pos, smooth, block=23)
    next(stream)
    stream.close()
    assert np.array_equal(sol.solve_prepared(pos, frames, bridged, fit_pos, smooth).vertices, whole.vertices)


def test_a_failing_blend_stops_the_choosing_thread(synth_set, monkeypatch) -> None:
    import threading

    import lgi.solve.finish as finish_mod

    bs, index = synth_set

    def boom(*args, **kwargs):
        raise RuntimeError("blend failed")

    monkeypatch.setattr(finish_mod._Finisher, "frame", boom)
    with pytest.raises(RuntimeError, match="blend failed"):
        LGISolver(index).solve_sequence(bs.noisy, noise=0.3)
    # The worker was blocked on a full queue (60 frames, 16 places): it must have given up, not hang.
    assert not any(t.name == "lgi-select" for t in threading.enumerate())


def test_far_field_keeps_captured_scans_from_extrapolating() -> None:
    # A capture session without a jaw rig: the local fits of the outer bundles pick scans that fit their
    # neighbourhood and extrapolate beyond it. Without the far field the side of the face was off by 4.1 mm
    # (fit: 0.37 mm); with it the maximum is the global fit's or better, and bundles are still met exactly.
    # Bundles whose weights predict their second ring of neighbours as well as the global fit keep them.
    from lgi.evaluation.benchsets import session_set
    from lgi.index.build import build_index

    bs = session_set(100, frames=60, n_vertices=5000)
    index, _ = build_index(bs.dataset, bs.layout, show_progress=False)
    fit = np.linalg.norm(RiggedBlendshapeSolver(index).solve_sequence(bs.bundles) - bs.truth, axis=2) * 10
    runs = {ff: LGISolver(index, far_field=ff).solve_sequence(bs.bundles) for ff in (None, (0.5, 1.5))}
    err = {ff: np.linalg.norm(r.vertices - bs.truth, axis=2) * 10 for ff, r in runs.items()}
    assert err[None].max() > 5 * fit.max()  # the failure the far field is for
    near = index.arrays["nn_distance"] < 0.5
    np.testing.assert_array_equal(err[None][:, near], err[(0.5, 1.5)][:, near])  # untouched near the markers
    assert err[(0.5, 1.5)].max() <= fit.max()
    assert np.sqrt(np.mean(err[(0.5, 1.5)] ** 2)) < 0.7 * np.sqrt(np.mean(fit**2))
    for r in runs.values():
        assert gaps_mm(r.vertices, bs.layout, bs.bundles).max() < THROUGH_MM
    solver = LGISolver(index)
    shares = np.stack([solver.select_frame(b).far_share for b in bs.bundles[::10]])
    assert (shares == 0).mean() > 0.3 and (shares > 0.9).any()


def test_far_field_option() -> None:
    from lgi.jobs.reconstruct import ReconstructOptions

    assert ReconstructOptions().far_field_cm() == (0.5, 1.5)
    assert ReconstructOptions(far_field="off").far_field_cm() is None
    assert ReconstructOptions(far_field="0:20").far_field_cm() == (0.0, 2.0)


def test_neighbourhood_misfits_are_each_bundles_weights_at_its_neighbours(synth_set) -> None:
    # The compiled misfit against the definition: each bundle's weights predict itself (weight OWN_WEIGHT) and its
    # seen natural neighbours; missing bundles are not scored against, rows not asked for are NaN.
    from lgi.solve._select_kernels import OWN_WEIGHT

    bs, index = synth_set
    sol = LGISolver(index)
    rng = np.random.default_rng(5)
    q = bs.bundles[30].astype(np.float64).copy()
    q[rng.random(len(q)) < 0.1] = np.nan
    seen = np.isfinite(q).all(axis=1)
    n_s = sol._basis.shape[0]
    w = np.where(rng.random((len(q), n_s)) < 0.3, rng.random((len(q), n_s)), 0.0)
    rows = rng.random(len(q)) < 0.7
    got = sol._misfits(q, seen, w, rows)
    nb_off, nb_idx = index.arrays["nb_off"], index.arrays["nb_idx"]
    for i in range(len(q)):
        if not rows[i]:
            assert np.isnan(got[i])
            continue
        pred = sol._rest + np.tensordot(w[i], sol._basis, axes=1)
        js = [i, *nb_idx[nb_off[i]:nb_off[i + 1]]]
        cw = np.array([OWN_WEIGHT] + [1.0] * (len(js) - 1))
        ok = seen[js]
        d2 = np.sum((pred[js] - q[js]) ** 2, axis=1)
        want = np.sqrt(np.sum(cw[ok] * d2[ok]) / max(cw[ok].sum(), 1e-300))
        assert got[i] == pytest.approx(want, rel=1e-12, abs=1e-15)
