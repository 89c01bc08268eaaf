"""Real motion readers (lgi.evaluation.realmotion): Live Link Face curves mapped by name, the facial mocap's shapes,
head stabilisation, known noise and neighbour pairs.

The data is read in place from the shared data's real-performances (tests skip with the reason when it is absent):
Live Link Face takes from alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder (c) 2021 Alexandre Donciu-Julin,
MIT; facial mocap from bigoMay/AnimFace, Miguel Ramos Carretero, Bournemouth University 2019, CC BY-SA 4.0.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from lgi.evaluation import realmotion as R


def _random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=rng.integers(1 << 31)).as_matrix()


def test_arkit_to_ict() -> None:
    assert R.arkit_to_ict("EyeBlinkLeft") == ("eyeBlink_L",)
    assert R.arkit_to_ict("MouthSmileRight") == ("mouthSmile_R",)
    assert R.arkit_to_ict("MouthLeft") == ("mouthLeft",) and R.arkit_to_ict("JawRight") == ("jawRight",)
    assert R.arkit_to_ict("JawForward") == ("jawForward",) and R.arkit_to_ict("MouthFunnel") == ("mouthFunnel",)
    assert R.arkit_to_ict("BrowInnerUp") == ("browInnerUp_L", "browInnerUp_R")
    assert R.arkit_to_ict("CheekPuff") == ("cheekPuff_L", "cheekPuff_R")
    assert R.arkit_to_ict("TongueOut") == ()
    assert len(R.ARKIT_NAMES) == len(set(R.ARKIT_NAMES)) == 52
    w = R.ict_weights(["BrowInnerUp", "EyeBlinkLeft", "TongueOut"], np.array([[0.2, 0.5, 0.9]]),
                      ["browInnerUp_R", "eyeBlink_L", "cheekRaiser_L", "browInnerUp_L"])
    np.testing.assert_array_equal(w, [[0.2, 0.5, 0.0, 0.2]])


def test_load_live_link(real_dir: Path) -> None:
    names, times, w = R.load_live_link("S88-001", real_dir)
    # 1939 rows, 277 of them lost tracking (BlendShapeCount 0): skipped.
    assert names == list(R.ARKIT_NAMES) and w.shape == (1662, 52) and times.shape == (1662,)
    assert times[0] == 0 and np.all(np.diff(times) > 0)
    assert 29.5 < 1 / np.median(np.diff(times)) < 30.5
    assert w.min() >= 0 and w.max() < 1.1
    # Columns are mapped by name (the file's order is not ARKit's).
    with open(real_dir / "live-link-face" / "S88-001.csv", newline="") as fh:
        rows = csv.reader(fh)
        header = next(rows)
        first = next(r for r in rows if int(r[header.index("BlendShapeCount")]) > 0)
    assert [h for h in header if h in R.ARKIT_NAMES] != list(R.ARKIT_NAMES)
    for n in ("JawOpen", "EyeBlinkLeft", "MouthLeft", "TongueOut"):
        assert w[0, names.index(n)] == float(first[header.index(n)])
    assert R.load_live_link(real_dir / "live-link-face" / "S88-001.csv")[2].shape == w.shape


def test_load_mocap(real_dir: Path) -> None:
    names, times, x = R.load_mocap("JawMoCap", real_dir)
    assert len(names) == 41 and x.shape == (1590, 41, 3) and x.dtype == np.float64 and times.shape == (1590,)
    assert set(R.HEAD_MARKERS) <= set(names) and {"Chin", "Mouth_Up", "Mouth_Down"} <= set(names)
    np.testing.assert_allclose(np.diff(times), 1 / R.MOCAP_RATE_HZ, rtol=1e-3)
    assert np.isfinite(x).all()
    # cm, Y up: the face is about 20 cm tall and the forehead above the chin.
    assert 10 < np.ptp(x[0, :, 1]) < 30
    assert x[0, names.index("ForeHead_M"), 1] > x[0, names.index("Chin"), 1]
    assert R.load_mocap("JawMoCap.npz", real_dir)[2].shape == x.shape


def test_stabilise_undoes_a_rigid_motion() -> None:
    rng = np.random.default_rng(0)
    rest = rng.normal(scale=5.0, size=(12, 3))
    rot = _random_rotations(30, rng)
    moved = np.einsum("fij,mj->fmi", rot, rest) + rng.normal(scale=3.0, size=(30, 1, 3))
    moved[0] = rest
    names = [f"m{i}" for i in range(12)]
    s = R.stabilise_to_head(names, moved, markers=("m0", "m3", "m5", "m7"))
    np.testing.assert_allclose(s.positions, np.broadcast_to(rest, moved.shape), atol=1e-9)
    assert s.residual_cm.max() < 1e-9 and s.head.tolist() == [0, 3, 5, 7]
    np.testing.assert_allclose(np.linalg.det(s.rotations), 1.0)


def test_stabilise_real_mocap(real_dir: Path) -> None:
    names, _, x = R.load_mocap("JawMoCap", real_dir)
    head = [names.index(m) for m in R.HEAD_MARKERS]
    raw_drift = np.sqrt(np.mean(np.sum((x[:, head] - x[0, head]) ** 2, 2), 1))
    assert raw_drift.max() > 0.5  # the head moves by centimetres
    for reference, mean_cm, max_cm in (("first", 0.04, 0.15), ("mean", 0.03, 0.12)):
        s = R.stabilise_to_head(names, x, reference=reference)
        # The forehead and nose bridge stay within a few tenths of a millimetre RMS of their reference.
        assert s.residual_cm.mean() < mean_cm and s.residual_cm.max() < max_cm, (reference, s.residual_cm.max())
        assert s.positions.shape == x.shape
    # The chin still moves (the jaw exercise), by more than the head markers' residual.
    chin = names.index("Chin")
    assert np.ptp(s.positions[:, chin, 1]) > 1.0


def test_add_noise_has_the_asked_sigma() -> None:
    clean = np.zeros((200_000, 3))
    iso = R.add_noise(clean, 0.03, seed=1)
    np.testing.assert_allclose(iso.std(0), 0.03, rtol=0.02)
    assert np.abs(iso.mean(0)).max() < 1e-3
    sigma = np.array([0.01, 0.02, 0.08])
    aniso = R.add_noise(clean, sigma, seed=1)
    np.testing.assert_allclose(aniso.std(0), sigma, rtol=0.02)
    rot = _random_rotations(1, np.random.default_rng(5))[0]
    turned = R.add_noise(clean, sigma, seed=2, rotation=rot)
    # In the noise frame (the rotation's columns) the noise has the asked sigma per axis and is uncorrelated.
    local = turned @ rot
    np.testing.assert_allclose(local.std(0), sigma, rtol=0.02)
    corr = np.corrcoef(local.T)
    assert np.abs(corr - np.eye(3)).max() < 0.02
    # Not along the positions' own axes.
    assert np.abs(turned.std(0) - sigma).max() > 0.005
    # Reproducible for a seed; NaN stays NaN; the input is not touched.
    x = np.ones((50, 4, 3))
    x[3, 1] = np.nan
    a = R.add_noise(x, sigma, seed=7)
    assert np.array_equal(a, R.add_noise(x, sigma, seed=7), equal_nan=True)
    assert not np.array_equal(a, R.add_noise(x, sigma, seed=8), equal_nan=True)
    assert np.isnan(a[3, 1]).all() and np.isfinite(np.delete(a.reshape(-1, 3), 3 * 4 + 1, axis=0)).all()
    assert np.nanmax(x) == 1.0


def test_neighbour_pairs(real_dir: Path) -> None:
    names, _, x = R.load_mocap("CheeksMoCap", real_dir)
    pairs = R.neighbour_pairs(x[0], k=4)
    assert pairs.ndim == 2 and pairs.shape[1] == 2 and (pairs[:, 0] < pairs[:, 1]).all()
    assert len({tuple(p) for p in pairs}) == len(pairs)
    counts = np.bincount(pairs.ravel(), minlength=len(names))
    assert counts.min() >= 4
    # Each marker's 4 nearest are among its pairs, and no pair is long (41 markers over a face: neighbours under 6 cm).
    d = np.linalg.norm(x[0][:, None] - x[0][None], axis=2)
    for i in range(len(names)):
        for j in np.argsort(d[i])[1:5]:
            assert (min(i, j), max(i, j)) in {tuple(p) for p in pairs}
    assert d[pairs[:, 0], pairs[:, 1]].max() < 6.0
    pair_names = {frozenset((names[a], names[b])) for a, b in pairs}
    assert frozenset(("Mouth_Up", "Mouth_UpL1")) in pair_names
