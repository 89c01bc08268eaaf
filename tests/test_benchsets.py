"""The accuracy benchmark's test sets (lgi.evaluation.benchsets): frames off the dataset, noise and gaps as specified,
bundles on the truth, and the ICT actors' jaw and correctives as documented."""

from __future__ import annotations

import dataclasses
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
    # The truth is the documented model, computed here from its parts: skin(x0 + sum_k w_k s_k, theta).
    s_k = np.stack([np.asarray(ds.deltas[ds.index(n)], np.float64) for n in names])
    for f in range(3):
        expect = rig.skin(ds.neutral + np.tensordot(w[f], s_k, axes=1), s.true_jaw[f])
        np.testing.assert_allclose(s.truth[f], expect, atol=1e-9)
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


# ---------------------------------------------------------------------------------------------- capture sessions
def _scans(s: BenchSet) -> list[int]:
    return [k for k, n in enumerate(s.dataset.names) if n.startswith("scan_")]


@pytest.fixture(scope="module")
def session() -> BenchSet:
    return B.session_set(20, frames=40, n_vertices=5000)


def test_session_set(session: BenchSet) -> None:
    from lgi.synthetic import actor as synth

    s = session
    _check_common(s, min_off_dataset=0.8)
    assert s.name == "session_20" and s.rig is not None and s.mask.all() and s.dataset.n_shapes == 47 + 20
    assert s.info["wide_open_deg"] == pytest.approx(0.6 * 22.0)  # the 47 shapes' widest opening, as synthetic
    # The scans: named by frame, tagged, spread evenly over the 600-frame performance's active frames.
    frames = s.info["scan_frames"]
    perf = synth.random_performance(600, seed=s.info["scan_seed"])
    active = np.flatnonzero((perf > 0).any(1))
    assert len(frames) == 20 and np.all(np.diff(frames) > 0) and set(frames) <= set(active)
    assert frames[0] == active[0] and frames[-1] == active[-1]
    scans = _scans(s)
    assert [s.dataset.names[k] for k in scans] == [f"scan_{f:04d}" for f in frames]
    assert all("scan" in s.dataset.shape_meta[k].tags for k in scans)
    assert not any("scan" in m.tags for m in s.dataset.shape_meta[:47])
    # A scan is the actor's true (nonlinear) face at its frame.
    actor = synth.make_actor(5000)
    k = scans[7]
    np.testing.assert_allclose(s.dataset.deltas[k], actor.evaluate(perf[frames[7]]) - actor.neutral, atol=1e-5)
    # The scans are not the test frames: apart from frames at rest, every frame is off every scan.
    d_mm = 10 * B.min_shape_distance(s.truth, s.dataset.take(scans), s.mask, include_neutral=False)
    moving = ~s.info["at_rest"]
    assert d_mm[moving].min() > 10 * B.OFF_DATASET_CM and np.mean(d_mm > 0.1) >= 0.8


def test_session_without_scans_is_the_47_shapes(session: BenchSet) -> None:
    from lgi.synthetic import actor as synth

    s0 = B.session_set(0, frames=40, n_vertices=5000)
    ref = synth.make_dataset(synth.make_actor(5000))
    assert s0.name == "session_0" and s0.dataset.names == ref.names and len(s0.info["scan_frames"]) == 0
    np.testing.assert_array_equal(s0.dataset.deltas, ref.deltas)
    assert [m.to_json() for m in s0.dataset.shape_meta] == [m.to_json() for m in ref.shape_meta]
    # The shot and its noise do not depend on the scans.
    np.testing.assert_array_equal(s0.truth, session.truth)
    assert np.array_equal(s0.noisy, session.noisy, equal_nan=True)


def test_session_set_refuses_more_scans_than_frames() -> None:
    from lgi.errors import InputError

    with pytest.raises(InputError, match="scans"):
        B.session_set(601, frames=10, n_vertices=3000)


def test_session_accuracy_baselines(session: BenchSet) -> None:
    from lgi.evaluation import accuracy as A
    from lgi.evaluation.baselines import BlendshapeSolver
    from lgi.evaluation.metrics import vertex_errors

    s = session
    index = A.build_set_index(s)
    methods = A.methods_for(s, index, noisy=True)
    assert [m.label for m in methods if m.baseline][:3] == [
        "blendshape fit (ridge chosen on the truth)", "blendshape fit + rig", "blendshape fit + rig, smoothed bundles"]
    # LGI and the fits only: the other methods are run on every set by test_baselines, and slowly.
    keep = [m for m in methods if m.label == "LGI (default)" or m.label.startswith("blendshape")]
    table, _ = A.run_set(s, keep, noisy=True, frames=30, index=index)
    by = table.set_index("method")
    smoothed, rigged = by.loc["blendshape fit + rig, smoothed bundles"], by.loc["blendshape fit + rig"]
    assert smoothed.baseline and np.isfinite(smoothed.rms_mm)
    assert abs(smoothed.rms_mm - rigged.rms_mm) > 0.01 * rigged.rms_mm
    # Session sets: the plain fit is the best ridge on the truth, with its weight in the note.
    assert "blendshape fit" not in by.index
    ridge = by.loc["blendshape fit (ridge chosen on the truth)"]
    assert ridge.baseline and ridge.note in {f"l2={v:g}" for v in A.RIDGE_L2}
    plain = BlendshapeSolver(s.dataset, s.layout).solve_sequence(s.noisy[:30])
    assert ridge.rms_mm <= np.sqrt(np.mean(vertex_errors(plain, s.truth[:30]) ** 2)) + 1e-9
    with pytest.raises(ValueError, match="first"):
        A.ridge_on_truth(s).run(s.noisy[1:5])
    # Far from every marker: a part of the face, where the errors are at most the overall maximum.
    far = A.far_vertices(s, index)
    assert 0 < far.sum() < 0.5 * s.mask.sum()
    assert np.all(np.isfinite(table.rms_far_mm)) and np.all(table.max_far_mm <= table.max_mm + 1e-12)
    text = A.format_table(table)
    assert "far max mm" in text and "| note |" in text and "l2=" in text
    # Without a rig the smoothed baseline is the plain fit of the smoothed bundles.
    bare = dataclasses.replace(s, rig=None)
    methods = A.methods_for(bare, A.build_set_index(bare), noisy=True)
    fit = [m for m in methods if m.label == "blendshape fit, smoothed bundles"]
    assert len(fit) == 1 and fit[0].baseline and not any("+ rig" in m.label for m in methods)
    out = fit[0].run(s.noisy[:30])
    assert out.shape == s.truth[:30].shape and np.all(np.isfinite(out))


def test_load_sets_knows_the_sessions(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from lgi.errors import InputError

    assert {"session_0", "session_150", "session_400", "ict_session"} <= set(B.SET_NAMES)
    assert B.needs_ict("ict_session") and not B.needs_ict("session_400")
    monkeypatch.setenv("LGI_SHARED_DATA", str(tmp_path))
    with pytest.raises(InputError, match="ICT"):
        B.load_sets(["ict_session"])


@pytest.fixture(scope="module")
def ict_session(ict_dir: Path) -> BenchSet:
    return B.ict_session_set(ict_dir)


def test_ict_session_set(ict_session: BenchSet, ict_combination: BenchSet) -> None:
    s, c = ict_session, ict_combination
    _check_common(s, min_off_dataset=0.9)
    ds, rig, info = s.dataset, s.rig, s.info
    # The frames, noise and actor of ict_combination; the dataset is the jaw actor's 57 shapes plus the scans.
    np.testing.assert_array_equal(s.truth, c.truth)
    assert np.array_equal(s.noisy, c.noisy, equal_nan=True)
    assert info["pairs"] == c.info["pairs"]
    np.testing.assert_array_equal(info["correctives"], c.info["correctives"])
    assert ds.n_shapes == 57 + 150 and ds.names[:57] == c.dataset.names[:57]
    np.testing.assert_array_equal(ds.deltas[:57], c.dataset.deltas[:57])
    scans = _scans(s)
    assert scans == list(range(57, 207))
    assert [ds.names[k] for k in scans] == [f"scan_{f:04d}" for f in info["scan_frames"]]
    assert all(ds.shape_meta[k].tags == ["scan"] for k in scans)
    # A scan is the same actor (pairs, correctives) in another motion, captured with its jaw.
    w, th, idx = info["scan_weights"], info["scan_jaw"], info["pair_index"]
    assert not np.array_equal(w[:20], info["weights"][:20])
    x = B.jaw_actor_frames(ds, rig, info["shapes"], w[:5], th[:5], info["correctives"].astype(np.float64), idx)
    np.testing.assert_allclose(ds.deltas[scans[:5]], x - ds.neutral, atol=1e-5)
    assert th[:, 0].max() > 10
    # The scans carry correctives: unskinned by their jaw, at the markers they leave the base shapes' linear span
    # wherever a pair acts together (about a third of them; the corrective grows with the weights' product).
    lay = s.layout
    unskinned = np.stack([rig.unskin(ds.neutral + np.asarray(ds.deltas[k], np.float64), t)
                          for k, t in zip(scans, th, strict=True)])
    p = (lay.evaluate(unskinned) - lay.evaluate(ds.neutral)).reshape(len(scans), -1).T
    span = lay.evaluate(np.asarray(ds.deltas[:57], np.float64)).reshape(57, -1).T
    resid = p - span @ np.linalg.lstsq(span, p, rcond=None)[0]
    off_mm = 10 * np.linalg.norm(resid.T.reshape(len(scans), -1, 3), axis=2).max(1)
    product = (w[:, idx[:, 0]] * w[:, idx[:, 1]]).max(1)
    assert np.mean(off_mm > 0.1) > 0.3
    assert np.mean(off_mm[product > 0.05] > 0.1) > 0.95
    assert off_mm[product == 0].max() < 0.01


# ---------------------------------------------------------------------------------------------- real motion
# Live Link Face takes from alexdjulin/LiveLinkFace-CSV-Retarget-For-Motionbuilder (c) 2021 Alexandre Donciu-Julin,
# MIT: read in place from the shared data, never copied here.
LIVELINK_WINDOW = {"start": 560, "frames": 120}  # S07-001: closed, a burst of speech, closed again


@pytest.fixture(scope="module")
def ict_livelink(ict_dir: Path, real_dir: Path) -> BenchSet:
    return B.ict_livelink_set(ict_dir, real_dir, **LIVELINK_WINDOW)


def test_ict_livelink_set(ict_livelink: BenchSet, ict_combination: BenchSet) -> None:
    s, c = ict_livelink, ict_combination
    # Every frame off the dataset (the checks of every set), noise and gaps as the others.
    _check_common(s, min_off_dataset=1.0)
    ds, rig, info = s.dataset, s.rig, s.info
    assert s.n_frames == 120 and info["take"] == "S07-001" and info["start"] == 560 and info["frames"] == 120
    assert 29 < info["fps"] < 31 and info["times_s"].shape == (120,)
    assert "S07-001" in s.description and "real iPhone ARKit curves" in s.description
    # The actor's shapes and rig, without ict_combination's combination shapes: the correctives are in no shape.
    assert ds.names == c.dataset.names[:ds.n_shapes] and ds.n_shapes < c.dataset.n_shapes
    np.testing.assert_array_equal(ds.deltas, c.dataset.deltas[:ds.n_shapes])
    np.testing.assert_array_equal(rig.pivot, c.rig.pivot)
    assert info["pairs"] == c.info["pairs"]
    np.testing.assert_array_equal(info["correctives"], c.info["correctives"])
    # The truth is the documented model, with the correctives.
    names, w, idx = info["shapes"], info["weights"], info["pair_index"]
    expect = B.jaw_actor_frames(ds, rig, names, w[::40], s.true_jaw[::40], info["correctives"].astype(np.float64),
                                idx)
    np.testing.assert_allclose(s.truth[::40], expect, atol=1e-5)
    # Real curves hold many shapes at once: the pair correctives act on most frames.
    assert info["pair_active"].mean() > 0.5 and np.median((w > 0.05).sum(1)) > 10
    # The jaw opens (beyond 10 degrees) and closes again within the window, about the yaw limits.
    open_deg = s.true_jaw[:, 0]
    peak = int(np.argmax(open_deg))
    assert open_deg[peak] > 10 and open_deg[:peak].min() < 2 and open_deg[peak:].min() < 2
    assert np.abs(s.true_jaw[:, 1]).max() <= B.ICT_JAW_MAX_YAW_DEG and not s.true_jaw[:, 2:].any()


def test_ict_livelink_is_not_a_plain_linear_blend(ict_livelink: BenchSet) -> None:
    from scipy.optimize import lsq_linear

    s = ict_livelink
    ds = s.dataset
    # The best bounded fit of all the dataset's shapes to the face's vertices (every 5th: bvls on all takes a
    # minute) leaves a residual on every frame tried, a tenth of a millimetre or more once the mouth moves (the
    # window's first frame is near rest, the jaw 0.65 degrees open: 0.026 mm).
    m = np.flatnonzero(s.mask)[::5]
    basis = np.asarray(ds.deltas[:, m], np.float64).reshape(ds.n_shapes, -1).T
    rms_mm = []
    for f in range(0, s.n_frames, 30):
        target = (s.truth[f, m] - ds.neutral[m]).ravel()
        w = lsq_linear(basis, target, bounds=(0.0, 1.0), method="bvls").x
        rms_mm.append(10 * np.sqrt(np.mean(np.sum((basis @ w - target).reshape(-1, 3) ** 2, 1))))
    assert min(rms_mm) > 0.01 and np.median(rms_mm) > 0.1, rms_mm
    # Nor is the rigged fit exact: unskinned by the true jaw, a frame where a pair acts keeps its corrective, which
    # no dataset shape holds.
    keep = [k for k, n in enumerate(ds.names) if n not in B.ICT_NOT_PERFORMED]
    basis = np.asarray(ds.deltas[keep][:, m], np.float64).reshape(len(keep), -1).T
    f = int(np.flatnonzero(s.info["pair_active"])[len(np.flatnonzero(s.info["pair_active"])) // 2])
    target = (s.rig.unskin(s.truth[f], s.true_jaw[f])[m] - ds.neutral[m]).ravel()
    w = lsq_linear(basis, target, bounds=(0.0, 1.0), method="bvls").x
    assert 10 * np.abs(basis @ w - target).max() > 1e-3


def test_ict_livelink_names_map(ict_livelink: BenchSet, real_dir: Path) -> None:
    from lgi.evaluation.realmotion import ICT_WITHOUT_CURVE, arkit_to_ict, load_live_link

    s = ict_livelink
    arkit, _, curves = load_live_link("S07-001", real_dir)
    names, w = s.info["shapes"], s.info["weights"]
    driven = {n for a in arkit for n in arkit_to_ict(a)}
    # Every performed ICT shape is driven by a curve but those ABOUT.md says have none.
    assert set(names) - driven == set(ICT_WITHOUT_CURVE) & set(names) == {"cheekRaiser_L", "cheekRaiser_R"}
    assert not w[:, [names.index("cheekRaiser_L"), names.index("cheekRaiser_R")]].any()
    window = np.clip(curves[560:680], 0.0, 1.0)
    col = {a: k for k, a in enumerate(arkit)}
    for shape, curve in (("eyeBlink_L", "EyeBlinkLeft"), ("mouthSmile_R", "MouthSmileRight"),
                         ("mouthLeft", "MouthLeft"), ("browInnerUp_L", "BrowInnerUp"),
                         ("browInnerUp_R", "BrowInnerUp"), ("cheekPuff_R", "CheekPuff")):
        np.testing.assert_array_equal(w[:, names.index(shape)], window[:, col[curve]])
    # The jaw is the rig's, from JawOpen (25 degrees at 1) and JawLeft - JawRight (3 degrees at 1).
    np.testing.assert_allclose(s.true_jaw[:, 0], 25.0 * window[:, col["JawOpen"]])
    np.testing.assert_allclose(s.true_jaw[:, 1], 3.0 * (window[:, col["JawLeft"]] - window[:, col["JawRight"]]))


def test_ict_livelink_window_and_names(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, ict_dir: Path,
                                       real_dir: Path) -> None:
    from lgi.errors import InputError

    assert "ict_livelink" in B.REAL_SET_NAMES and "ict_livelink" not in B.SET_NAMES
    assert B.needs_ict("ict_livelink") and B.needs_real_performances("ict_livelink")
    with pytest.raises(InputError, match="tracked frames"):
        B.ict_livelink_set(ict_dir, real_dir, start=2000, frames=100)
    monkeypatch.setenv("LGI_SHARED_DATA", str(tmp_path))
    assert B.real_performances_dir_or_none() is None
    with pytest.raises(InputError, match="real performances"):
        B.load_sets(["ict_livelink"], ict_dir=ict_dir)
