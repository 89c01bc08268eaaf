"""The head pose solved with the face (lgi.capture.headpose) and the jolting helmet (lgi.synthetic.hmc)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lgi.capture.headpose import JOINT, MIN_MARKERS, STABLE, HeadPoseSolver, pose_error
from lgi.capture.headstab import stabilise_bundles
from lgi.synthetic import actor as synth


@pytest.fixture(scope="module")
def rigged():
    """The small actor's index built with its jaw rig, and its joint head-pose solver."""
    from lgi.index.build import build_index

    actor = synth.make_actor(1500)
    layout, _ = synth.default_layout(actor)
    index, _ = build_index(synth.make_dataset(actor), layout, show_progress=False, jaw_rig=synth.jaw_rig(actor))
    return index, HeadPoseSolver.from_index(index)


def _rotation(rv: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rv).as_matrix()


def _smiling_shot(index, solver: HeadPoseSolver, F: int, seed: int = 0, R=None, t=None):
    """World-frame markers (mm) of a face that smiles while it talks (a few random shapes per frame on top of
    both smiles and an opening jaw), under a known head pose per frame (random when not given)."""
    fit = solver.fit
    names = index.shape_names[1:]
    rng = np.random.default_rng(seed)
    w = np.zeros((F, fit.n_shapes))
    for f in range(F):
        k = rng.choice(fit.n_shapes, 3, replace=False)
        w[f, k] = rng.uniform(0.2, 0.8, 3)
    for n in ("smile_L", "smile_R"):
        w[:, names.index(n)] = np.linspace(0.2, 1.0, F)
    jaw = np.zeros((F, 4))
    jaw[:, 0] = np.linspace(0.0, 12.0, F)  # deg
    if R is None:
        R = _rotation(np.radians(1.0) * rng.normal(size=(F, 3)))
        t = rng.normal(size=(F, 3)) * 2.0
    X = np.stack([(fit.predict(w[f], jaw[f]) * 10) @ R[f].T + t[f] for f in range(F)])
    return X, R, t


def test_joint_fit_recovers_a_known_pose_while_the_face_smiles(rigged) -> None:
    index, solver = rigged
    X, R_true, t_true = _smiling_shot(index, solver, 16)
    neutral_mm = index.arrays["ptab"][0] * 10
    _, R0, t0, _ = stabilise_bundles(X, neutral_mm)
    centre = neutral_mm.mean(0)
    deg0, mm0 = pose_error(R0, t0, R_true, t_true, centre)
    # The smile moves the markers the stable-marker fit takes as rigid: it is off (what the joint fit is for).
    assert deg0.max() > 0.02 or mm0.max() > 0.05
    poses = solver.solve(X, R0, t0)
    deg, mm = pose_error(poses.R, poses.t, R_true, t_true, centre)
    assert np.all(poses.source == JOINT)
    assert deg.max() <= 1e-3 and mm.max() <= 1e-3, (deg.max(), mm.max())
    assert np.nanmax(poses.rms_mm) < 1e-3
    assert not poses.outliers.any()


def test_a_jolt_is_followed_not_smoothed_away(rigged) -> None:
    """The helmet jumps 1.5 deg and 3 mm between frames 5 and 6 and stays: frame 6 is posed as exactly as the
    others (no frame borrows its neighbours' pose), while the stable-marker fit is off there."""
    index, solver = rigged
    F = 12
    jolted = np.arange(F) >= 6
    R_true = np.where(jolted[:, None, None], _rotation(np.radians([0.0, 1.5, 0.0]))[None], np.eye(3)[None])
    t_true = np.where(jolted[:, None], np.array([3.0, 0.0, 0.0]), 0.0)
    X, _, _ = _smiling_shot(index, solver, F, seed=3, R=R_true, t=t_true)
    neutral_mm = index.arrays["ptab"][0] * 10
    _, R0, t0, _ = stabilise_bundles(X, neutral_mm)
    poses = solver.solve(X, R0, t0)
    deg, mm = pose_error(poses.R, poses.t, R_true, t_true, neutral_mm.mean(0))
    assert deg.max() <= 1e-3 and mm.max() <= 1e-3, (deg, mm)
    # The 1.5 deg / 3 mm jump is there in full at frame 6, not spread over its neighbours.
    step = pose_error(poses.R[5:6], poses.t[5:6], poses.R[6:7], poses.t[6:7], neutral_mm.mean(0))
    assert abs(step[0][0] - 1.5) < 1e-3


def test_too_few_markers_keep_the_stable_pose_and_say_so(rigged, caplog) -> None:
    index, solver = rigged
    X, _, _ = _smiling_shot(index, solver, 4, seed=5)
    X[2, MIN_MARKERS - 2:] = np.nan  # frame 2 sees too few markers for the joint fit
    _, R0, t0, _ = stabilise_bundles(X, index.arrays["ptab"][0] * 10)
    with caplog.at_level(logging.WARNING, logger="lgi.capture.headpose"):
        poses = solver.solve(X, R0, t0)
    assert list(poses.source) == [JOINT, JOINT, STABLE, JOINT]
    np.testing.assert_array_equal(poses.R[2], R0[2])
    assert "1 of 4 frames could not be solved with the face" in caplog.text


def test_helmet_jolts_are_sudden_then_held() -> None:
    from scipy.spatial.transform import Rotation

    from lgi.synthetic.hmc import JOLT_FRAMES, VIBRATION_DEG, helmet_jolts

    R, t, jolting = helmet_jolts(400, seed=2)
    starts = np.flatnonzero(np.diff(np.concatenate([[0], jolting.astype(int)])) == 1)
    assert len(starts) >= 3
    ang = Rotation.from_matrix(R).as_rotvec()
    for s in starts:
        n = int(np.argmin(jolting[s:]))
        assert JOLT_FRAMES[0] <= n <= JOLT_FRAMES[1]
        turn = np.degrees(np.linalg.norm(ang[s + n] - ang[s - 1]))
        shift = np.linalg.norm(t[s + n] - t[s - 1])
        assert 0.4 <= turn <= 1.6 and 0.9 <= shift <= 3.1, (turn, shift)
        # Then held: only the vibration moves it over the next frames.
        held = np.degrees(np.linalg.norm(ang[s + n:s + n + 20] - ang[s + n], axis=1))
        assert held.max() <= 4 * VIBRATION_DEG * np.sqrt(3)
