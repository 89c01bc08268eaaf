"""The accuracy benchmark's test sets (lgi.evaluation.benchsets): frames off the dataset, noise and gaps as specified,
bundles on the truth, and the ICT actors' jaw and correctives as documented."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lgi.evaluation import benchsets as B
from lgi.evaluation.benchsets import BenchSet


def _check_common(s: BenchSet, min_off_dataset: float) -> None:
    f, v = s.truth.shape[:2]
    m = len(s.layout)
    assert s.truth.dtype == s.bundles.dtype == s.noisy.dtype == np.float64
    assert s.bundles.shape == s.noisy.shape == (f, m, 3)
    assert s.mask.shape == s.lips.shape == (v,) and s.wide_open.shape == (f,)
    assert s.triangles.shape[1] == 3 and s.dataset.n_vertices == v
    assert s.description.strip().endswith(".") and s.description.count(". ") == 0
    np.testing.assert_allclose(s.bundles, s.layout.evaluate(s.truth), atol=1e-12)
    # Lips: measured vertices only, a small region of them.
    assert s.lips.any() and not (s.lips & ~s.mask).any() and s.lips.sum() < 0.3 * s.mask.sum()
    # Not dataset points: the closest dataset shape (or the neutral) is more than 0.1 mm away.
    dist_mm = 10 * B.min_shape_distance(s.truth, s.dataset, s.mask)
    assert np.mean(dist_mm > 0.1) >= min_off_dataset, np.sort(dist_mm)[:10]
    # Tracking noise: 0.3 mm per coordinate, 5 % of marker-frames missing as whole NaN rows.
    gone = np.isnan(s.noisy).any(2)
    assert np.array_equal(gone, np.isnan(s.noisy).all(2))
    assert abs(gone.mean() - 0.05) < 0.002
    err = (s.noisy - s.bundles)[~gone]
    assert 0.027 < err.std() < 0.033 and abs(err.mean()) < 0.003
    if s.true_jaw is not None:
        assert s.true_jaw.shape == (f, 4)
        np.testing.assert_array_equal(s.wide_open, s.true_jaw[:, 0] > s.info["wide_open_deg"])


def _runs(gone: np.ndarray) -> np.ndarray:
    """Lengths of every marker's runs of consecutive missing frames."""
    out = []
    for col in gone.T:
        edges = np.diff(np.concatenate([[0], col.astype(int), [0]]))
        out.extend(np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1))
    return np.asarray(out)


def test_tracking_noise_loses_markers_for_a_few_frames() -> None:
    clean = np.zeros((400, 50, 3))
    noisy = B.tracking_noise(clean, seed=3)
    gone = np.isnan(noisy[..., 0])
    assert gone.sum() == round(0.05 * gone.size)
    runs = _runs(gone)
    # Runs of 1-6 frames; two may touch and merge, rarely.
    assert runs.min() >= 1 and np.mean(runs <= 6) > 0.95 and 2.5 < runs.mean() < 5
    assert np.array_equal(noisy, B.tracking_noise(clean, seed=3), equal_nan=True)
    assert not np.array_equal(noisy, B.tracking_noise(clean, seed=4), equal_nan=True)


@pytest.fixture(scope="module")
def synthetic() -> BenchSet:
    return B.synthetic_set(frames=60, n_vertices=3000)


def test_synthetic_set(synthetic: BenchSet) -> None:
    s = synthetic
    # Frames at rest (no control active) are the neutral: the random performance has a few.
    _check_common(s, min_off_dataset=0.8)
    assert s.dataset.n_shapes == 47 and s.rig is not None and s.mask.all()
    assert s.wide_open.any() and s.info["wide_open_deg"] == pytest.approx(0.6 * 22.0)
    # The lips lie around the mouth line (y = -4.5 cm on the synthetic face).
    y = s.dataset.neutral[s.lips, 1]
    assert abs(np.median(y) + 4.5) < 0.3 and np.ptp(y) <= 3.0 + 1e-9
    again = B.synthetic_set(frames=60, n_vertices=3000)
    assert np.array_equal(again.noisy, s.noisy, equal_nan=True)


def test_load_sets_names(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from lgi.errors import InputError

    with pytest.raises(InputError, match="unknown"):
        B.load_sets(["nope"])
    monkeypatch.setenv("LGI_SHARED_DATA", str(tmp_path))
    assert B.ict_dir_or_none() is None
    with pytest.raises(InputError, match="ICT"):
        B.load_sets(["ict_jaw"])


# ---------------------------------------------------------------------------------------------- ICT
@pytest.fixture(scope="module")
def ict_jaw(ict_dir: Path) -> BenchSet:
    return B.ict_jaw_set(ict_dir)


@pytest.fixture(scope="module")
def ict_combination(ict_dir: Path) -> BenchSet:
    return B.ict_combination_set(ict_dir)


def test_ict_jaw_set(ict_jaw: BenchSet) -> None:
    s = ict_jaw
    _check_common(s, min_off_dataset=0.9)
    ds, rig = s.dataset, s.rig
    assert rig is not None and s.mask.sum() == 9409 and ds.n_shapes == 57
    # jawOpen is the rig's rotation of the neutral, about 25 degrees.
    params = s.info["jaw_open_params"]
    assert 20 < params[0] < 30
    np.testing.assert_allclose(ds.deltas[ds.index("jawOpen")], rig.skin(ds.neutral, params) - ds.neutral, atol=1e-5)
    # No expression and the jaw at rest give the neutral; the truth is the documented model.
    names, w = s.info["shapes"], s.info["weights"]
    rest = B.jaw_actor_frames(ds, rig, names, np.zeros((1, len(names))), np.zeros((1, 4)))
    np.testing.assert_allclose(rest[0], ds.neutral, atol=1e-12)
    np.testing.assert_allclose(B.jaw_actor_frames(ds, rig, names, w[:3], s.true_jaw[:3]), s.truth[:3], atol=1e-12)
    assert not set(names) & set(B.ICT_NOT_PERFORMED)
    active = (w > 0).sum(1)
    assert active.min() >= 1 and active.max() <= 4 and (w.sum(1) > 1).mean() > 0.2
    assert w.min() >= 0 and w.max() <= 1
    # A smooth jaw, open wide (> 15 degrees) in some frames, yaw within 3 degrees, no roll or slide.
    jaw = s.true_jaw
    assert jaw[:, 0].min() >= 0 and jaw[:, 0].max() >= 15 and s.wide_open.any()
    assert np.abs(jaw[:, 1]).max() <= 3 and not jaw[:, 2:].any()
    assert np.abs(np.diff(jaw[:, 0])).max() < 3 and np.abs(np.diff(w, axis=0)).max() < 0.2
    # The lower teeth follow the jaw rigidly.
    f = int(np.argmax(jaw[:, 0]))
    teeth = B.ICT_LOWER_TEETH
    np.testing.assert_allclose(s.truth[f, teeth], rig.skin(ds.neutral[teeth] + np.tensordot(
        w[f], np.asarray(ds.deltas[[ds.index(n) for n in names]], np.float64)[:, teeth], axes=1), jaw[f],
        np.ones(teeth.size)), atol=1e-3)


def test_ict_heldout_set(ict_dir: Path) -> None:
    from lgi.evaluation.accuracy import ICT_HELD_OUT

    s = B.ict_heldout_set(ict_dir)
    _check_common(s, min_off_dataset=1.0)
    assert s.rig is None and s.true_jaw is None and s.n_frames == 66
    assert s.dataset.n_shapes == 51 + 400 and not set(ICT_HELD_OUT) & set(s.dataset.names)
    names = s.info["frame_names"]
    assert sorted(n for n in names if n in ICT_HELD_OUT) == sorted(ICT_HELD_OUT)
    assert all(any(h + "*" in n or h == n for h in ICT_HELD_OUT) for n in names)


def test_ict_combination_set(ict_combination: BenchSet) -> None:
    s = ict_combination
    _check_common(s, min_off_dataset=0.9)
    ds, rig, info = s.dataset, s.rig, s.info
    pairs, idx, corr, w = info["pairs"], info["pair_index"], info["correctives"], info["weights"]
    assert len(pairs) == 12 and ds.n_shapes == 57 + 24
    # Each pair is in the dataset at (1, 1) and (0.5, 0.5) with its corrective at the weights' product.
    for (a, b), c in zip(pairs, corr, strict=True):
        plain = np.asarray(ds.deltas[ds.index(a)], np.float64) + ds.deltas[ds.index(b)]
        np.testing.assert_allclose(ds.deltas[ds.index(f"{a}+{b}")], plain + c, atol=1e-5)
        np.testing.assert_allclose(ds.deltas[ds.index(f"{a}*0.5+{b}*0.5")], 0.5 * plain + 0.25 * c, atol=1e-5)
        peak = np.linalg.norm(c[s.mask], axis=1).max()
        assert 0.3 - 1e-6 <= peak <= 0.5 + 1e-6
    # The truth differs from the plain sum by the (skinned) corrective exactly where a pair is active.
    plain = B.jaw_actor_frames(ds, rig, info["shapes"], w, s.true_jaw)
    product = w[:, idx[:, 0]] * w[:, idx[:, 1]]
    expected = np.stack([rig.skin(ds.neutral + np.tensordot(p, corr.astype(np.float64), axes=1), th)
                         - rig.skin(ds.neutral, th) for p, th in zip(product, s.true_jaw, strict=True)])
    np.testing.assert_allclose(s.truth - plain, expected, atol=1e-6)
    held = info["pair_active"]
    assert 0.5 < held.mean() < 0.85
    assert not np.any(s.truth[~held] - plain[~held])
    strong = product.max(1) > 0.25
    assert strong.any()
    diff_mm = 10 * np.linalg.norm(s.truth[strong] - plain[strong], axis=2).max(1)
    assert diff_mm.min() > 0.5
    # Pair frames also move the jaw (as in the jaw set).
    assert s.true_jaw[held, 0].max() > 10
