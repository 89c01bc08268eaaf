"""A long take's trajectories are prepared a block of frames at a time, from and to files: the statistics, the
bridging, the noise estimate and the smoothing equal the whole shot's bit for bit, whatever the block."""

from __future__ import annotations

import numpy as np
import pytest

from lgi.capture.bundles import Bundles
from lgi.io.stored import ScratchArray, StoredArray
from lgi.solve import streamed, temporal
from lgi.solve.streamed import row_reader, streamed_median, streamed_percentile, streamed_sum

WHOLE = 10**9  # a block longer than any shot here: the whole shot at once


def _trajectories(n_frames: int = 700, n_markers: int = 6, seed: int = 0) -> np.ndarray:
    """(F, M, 3) cm: smooth motion with 0.03 mm of noise, gaps of 1-40 frames, a marker seen in 5 frames only."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 12, n_frames)[:, None, None]
    p = np.sin(t * rng.uniform(0.5, 3, (1, n_markers, 3))) + rng.normal(0, 0.003, (n_frames, n_markers, 3))
    for m in range(n_markers - 1):
        for _ in range(8):
            a = rng.integers(0, n_frames)
            p[a:a + rng.integers(1, 40), m] = np.nan
    p[:, -1] = np.nan
    p[100:105, -1] = 1.0
    return p


def _equal(a, b) -> bool:
    return all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize("n", [1, 2, 7, 8, 1001, 40000])
def test_the_streamed_median_is_numpys(n) -> None:
    rng = np.random.default_rng(n)
    v = np.abs(rng.standard_normal(n)) * 10.0 ** rng.integers(-5, 3, n)
    v[rng.integers(0, n, n // 3)] = v[0]  # ties
    assert streamed_median(lambda: np.array_split(v, 7)) == np.median(v)
    assert np.isnan(streamed_median(lambda: [np.zeros(0)]))


@pytest.mark.parametrize("n", [1, 2, 7, 1001, 40000])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_streamed_percentile_is_numpys(n, dtype) -> None:
    rng = np.random.default_rng(n)
    v = (np.abs(rng.standard_normal(n)) * 10.0 ** rng.integers(-5, 3, n)).astype(dtype)
    v[rng.integers(0, n, n // 3)] = v[0]  # ties
    for q in (0, 5, 50, 95, 99.9, 100):
        assert streamed_percentile(lambda: np.array_split(v, 7), q, dtype) == np.percentile(v, q), q
    assert np.isnan(streamed_percentile(lambda: [np.zeros(0)], 95))


def test_the_streamed_sum_is_numpys_pairwise_sum(monkeypatch) -> None:
    rng = np.random.default_rng(1)
    a = (rng.standard_normal((997, 13, 3)) * 10.0 ** rng.integers(-8, 8, (997, 13, 3)))
    monkeypatch.setattr(streamed, "_SUM_LEAF", 500)  # many leaves
    assert streamed_sum(row_reader(a), a.size) == np.sum(a)
    # a naive sum of the same values in blocks is not (the test could fail)
    assert sum(float(np.sum(a[i:i + 100])) for i in range(0, 997, 100)) != np.sum(a)


@pytest.mark.parametrize("block", [37, 250])
def test_smoothing_in_blocks_equals_the_whole_shot(block) -> None:
    p = _trajectories()
    fit = np.where(np.isnan(p), np.nan, p + np.random.default_rng(2).normal(0, 0.001, p.shape))
    assert _equal(temporal.denoise_trajectories(p, 0.03, block=block),
                  temporal.denoise_trajectories(p, 0.03, block=WHOLE))
    sig, lev = np.full((6, 3), 0.03), np.random.default_rng(3).uniform(0, 0.3, (6, 3))

    def joined(positions, fitted, size: int) -> list[np.ndarray]:
        blocks = list(temporal.model_denoised_blocks(positions, fitted, sig, lev, block=size))
        return [np.concatenate([b[k] for b in blocks]) for k in (2, 3, 4)]

    whole = joined(p, fit, WHOLE)
    parts = joined(ScratchArray.of(p), ScratchArray.of(fit), block)
    assert _equal(whole, parts)


@pytest.mark.parametrize("block", [37, 250])
def test_the_noise_estimate_and_bridging_in_blocks_equal_the_whole_shot(block) -> None:
    p = _trajectories()
    pairs = np.array([[0, 1], [1, 2], [3, 4]])
    whole = temporal.estimate_noise(p, pairs, block=WHOLE)
    part = temporal.estimate_noise(ScratchArray.of(p), pairs, block=block)
    assert np.array_equal(whole.axis_mm, part.axis_mm) and whole.samples == part.samples
    # the neighbours' correlation is summed block by block: equal to rounding
    assert part.coherence == pytest.approx(whole.coherence, rel=1e-12, abs=1e-15)
    for gap in (0, 3, 60):
        filled, bridged = temporal.bridge_gaps(p, gap)
        blocks = list(temporal.bridged_blocks(ScratchArray.of(p), gap, block=block))
        assert np.array_equal(filled, np.concatenate([b[2] for b in blocks]), equal_nan=True)
        assert np.array_equal(bridged, np.concatenate([b[3] for b in blocks]))


def test_a_shot_on_disk_is_prepared_as_in_memory(monkeypatch) -> None:
    from lgi.evaluation.accuracy import build_set_index
    from lgi.evaluation.benchsets import synthetic_set
    from lgi.solve.solver import LGISolver

    bs = synthetic_set(frames=120, n_vertices=3000)
    index = build_set_index(bs)
    rng = np.random.default_rng(4)
    pos = bs.bundles + rng.normal(size=bs.bundles.shape) * np.array([0.001, 0.001, 0.004])
    pos[rng.random(pos.shape[:2]) < 0.05] = np.nan
    frames = np.arange(len(pos))
    results = []
    for positions, block in ((pos, WHOLE), (ScratchArray.of(pos), 48)):
        monkeypatch.setattr(streamed, "BLOCK_FRAMES", block)
        sol = LGISolver(index)
        p, _, bridged, noise = sol.prepare_shot(Bundles(frames, list(index.marker_names), positions), None, 3,
                                                "auto")
        fit, noise = sol.denoise(p, noise)
        results.append([noise.level, np.asarray(p), bridged, np.asarray(fit), np.asarray(noise.left),
                        sol.with_noise(noise).global_fit.gain])
    assert isinstance(p, StoredArray) and isinstance(fit, StoredArray)
    assert results[0][0] > 0 and results[0][2].any()  # noisy, with gaps bridged: every stage ran
    assert _equal(results[0], results[1])


def test_marker_covariance_medians_a_few_markers_at_a_time(monkeypatch) -> None:
    import warnings

    from lgi.solve import solver

    rng = np.random.default_rng(6)
    a = rng.normal(size=(300, 7, 3, 3))
    cov = np.einsum("fmij,fmkj->fmik", a, a) * 1e-6
    cov[rng.random((300, 7)) < 0.3] = np.nan
    cov[:, 4] = np.nan  # a marker without any
    columns = [2, None, 0, 4, 1, 6, 5, 3]  # the index's markers in the file's columns
    monkeypatch.setattr(solver, "MEDIAN_MARKERS", 3)
    monkeypatch.setattr(streamed, "BLOCK_FRAMES", 64)
    med, given = solver._marker_medians(ScratchArray.of(cov), columns)
    aligned = np.full((300, 8, 3, 3), np.nan)
    for m, c in enumerate(columns):
        if c is not None:
            aligned[:, m] = cov[:, c]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        assert np.array_equal(med, np.nanmedian(aligned, axis=0), equal_nan=True)
    assert np.array_equal(given, np.isfinite(aligned).all(axis=(2, 3)).any(axis=0))
    assert not given[1] and not given[3]
