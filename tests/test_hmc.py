"""Head-mounted cameras: lens models, synthetic calibration, dot detection, tracking, the footage chain."""

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lgi.capture.calibration import Board, calibrate_stereo, calibrate_views
from lgi.capture.camera import StereoRig
from lgi.capture.dots import detect_dots
from lgi.cli import main
from lgi.errors import InputError
from lgi.synthetic.hmc import BoardRenderer, board_corner_views, board_poses, hmc_rig


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_triangulation_is_exact_without_noise_and_reports_reprojection(model: str) -> None:
    rig = hmc_rig(model)
    X = np.random.default_rng(0).uniform([-60, -90, 0], [60, 80, 70], (300, 3))
    uv0, uv1 = rig.cameras[0].project(X), rig.cameras[1].project(X)
    Y, err = rig.triangulate(uv0, uv1)
    assert np.abs(Y - X).max() < 1e-6 and err.max() < 1e-6
    assert rig.epipolar_distance(uv0, uv1).max() < 1e-6
    # A gross error in one camera shows in the reprojection error and the epipolar distance.
    bad = uv1.copy()
    bad[0] += [15.0, 0.0]  # across the (near-vertical) epipolar line
    _, err = rig.triangulate(uv0, bad)
    assert err[0].max() > 3 and np.median(err[1:]) < 1e-6


@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_synthetic_calibration_at_02px_corner_noise(model: str) -> None:
    rig = hmc_rig(model)
    board = Board.parse("chessboard:9x6:12")
    views = board_corner_views(rig, board, board_poses(rig, board, 20, seed=1), noise_px=0.2, seed=1)
    calib = calibrate_views(views, rig.cameras[0].size, model)
    assert calib.rms_stereo <= 0.3 and max(calib.rms_camera) <= 0.3
    for k in range(2):
        f_true = np.diag(rig.cameras[k].K)[:2]
        f_est = np.diag(calib.K[k])[:2]
        assert np.all(np.abs(f_est / f_true - 1) < 0.005), (f_est, f_true)
    assert abs(calib.baseline_mm - rig.baseline) < 0.5
    R_true, _ = rig.relative()
    angle = np.degrees(np.arccos(np.clip((np.trace(calib.R @ R_true.T) - 1) / 2, -1, 1)))
    assert angle < 0.1


def test_charuco_board_views_calibrate_with_a_second_pass(tmp_path: Path) -> None:
    import cv2

    rig = hmc_rig("pinhole", (960, 768))
    board = Board.parse("charuco:7x5:15:11:DICT_5X5_100")
    br = BoardRenderer(board, px_per_mm=10)
    rng = np.random.default_rng(0)
    for k, pose in enumerate(board_poses(rig, board, 10, seed=3)):
        for c, side in enumerate(("left", "right")):
            cv2.imwrite(str(tmp_path / f"{side}{k:02d}.png"), br.render(rig.cameras[c], pose, rng))
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(tmp_path), "--board", board.spec(), "--out", str(out)]) == 0
    got = StereoRig.load(out)
    for k in range(2):
        assert abs(got.cameras[k].K[0, 0] / rig.cameras[k].K[0, 0] - 1) < 0.005
    assert abs(got.baseline - rig.baseline) < 0.5
    # The fisheye model fits the same views too (no second pass: OpenCV's ChArUco refinement is pinhole).
    calib = calibrate_stereo(tmp_path, board, fisheye=True)
    assert calib.model == "fisheye" and calib.rms_stereo < 1.0


def test_dot_detection_subpixel_and_rejections() -> None:
    import cv2

    rng = np.random.default_rng(0)
    h, w = 240, 320
    img = np.full((h, w), 180.0)
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.column_stack([rng.uniform(20, 300, 12), rng.uniform(20, 120, 12)])
    centres = centres[np.argsort(centres[:, 0])]
    centres[:, 0] = np.linspace(20, 300, 12) + rng.uniform(-0.5, 0.5, 12)
    for cx, cy in centres:
        img -= 150 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * 2.2**2))
    img[170:200, 40:140] = 30  # a large dark region (an eye, the mouth)
    img[150:154, 200:260] = 40  # a thin dark line (a lip line, a brow hair)
    img = np.clip(img, 0, 255)
    cv2.circle(img, (250, 200), 4, 255, -1)  # a specular highlight
    cv2.circle(img, (257, 200), 3, 120, -1)  # and the darker skin at its rim
    img = np.clip(img + rng.normal(0, 1.5, img.shape), 0, 255).astype(np.uint8)
    dots = detect_dots(img)
    assert len(dots) == 12, (dots.xy, dots.rejected)
    d = np.linalg.norm(dots.xy[np.argsort(dots.xy[:, 0])] - centres, axis=1)
    assert d.max() < 0.15
    # The line is seen and rejected as elongated, the highlight's rim as specular; the large dark region is
    # wider than the black-hat kernel and gives no blob at all.
    assert dots.rejected.get("specular", 0) == 1 and dots.rejected.get("elongated", 0) == 1


@pytest.fixture(scope="module")
def hmc_shot(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("hmc")
    # The rig flexes by 0.3 deg after its calibration: the helmet dots must correct it.
    assert main(["synth", "--out", str(out), "--frames", "30", "--vertices", "12000", "--hmc", "--board-views", "8",
                 "--rig-flex", "0.3", "-q"]) == 0
    return out


def test_footage_to_bundles_chain(hmc_shot: Path, capsys) -> None:
    from lgi.capture.bundles import read_bundles

    calib = hmc_shot / "calib.json"
    assert main(["calibrate", str(hmc_shot / "hmc" / "calib"), "--board", "chessboard:9x6:12", "--fisheye",
                 "--out", str(calib)]) == 0
    true = json.loads((hmc_shot / "hmc" / "cameras_true.json").read_text())
    got = json.loads(calib.read_text())
    assert abs(got["baseline_mm"] - true["baseline_mm"]) < 0.5
    truth = read_bundles(hmc_shot / "bundles.csv")
    rms = {}
    for helmet in (False, True):
        out = hmc_shot / "tracked.csv"
        extra = ["--helmet", str(hmc_shot / "hmc" / "helmet.csv")] if helmet else []
        capsys.readouterr()
        assert main(["track", str(hmc_shot / "hmc"), "--calib", str(calib), "--markers",
                     str(hmc_shot / "markers.csv"), "--out", str(out), *extra]) == 0
        # A warning through logging (the CLI prints it on stderr; a flow's log picks it up).
        assert ("lgi track: warning: the median reprojection error" in capsys.readouterr().err) != helmet
        tracked = read_bundles(out)
        idx = [truth.markers.index(m) for m in tracked.markers]
        err_mm = 10 * np.linalg.norm(tracked.positions - truth.positions[:, idx], axis=2)
        rms[helmet] = np.sqrt(np.nanmean(err_mm**2))
    assert rms[True] < 0.5 < rms[False]
    # No label swaps: every 2D observation is nearest to its own marker's true projection, and close to it.
    t2 = np.load(hmc_shot / "hmc" / "truth.npz")
    names = list(t2["markers"])
    table = pd.read_parquet(hmc_shot / "tracked.tracks.parquet")
    m = np.array([names.index(n) for n in table["marker"]])
    xy = table[["x", "y"]].to_numpy()
    all_true = t2["centers"][table["frame"], table["camera"]]  # (N, M, 2)
    nearest = np.nanargmin(np.linalg.norm(all_true - xy[:, None], axis=2), axis=1)
    assert np.all(nearest == m)
    assert np.percentile(np.linalg.norm(xy - all_true[np.arange(len(m)), m], axis=1), 99) < 1.5
    # Visible dots are detected, and nearly all of them tracked.
    from scipy.spatial import cKDTree

    from lgi.capture.footage import detect_footage

    visible = t2["visible"]
    _, dots, _ = detect_footage(hmc_shot / "hmc")
    detected = np.array([[cKDTree(d.xy).query(t2["centers"][f, c])[0] < 2 for c, d in enumerate(pair)]
                         for f, pair in enumerate(dots)])
    assert (detected & visible).sum() / visible.sum() >= 0.98
    found = np.zeros_like(visible)
    found[table["frame"], table["camera"], m] = True
    assert (found & visible).sum() / visible.sum() >= 0.97
    assert {"reprojection_px", "triangulated", "source"} <= set(table.columns)


def test_track_bad_inputs(hmc_shot: Path, tmp_path: Path) -> None:
    import shutil

    markers = str(hmc_shot / "markers.csv")
    true_calib = hmc_shot / "hmc" / "cameras_true.json"
    # A calibration file of the wrong shape.
    bad = tmp_path / "bad.json"
    doc = json.loads(true_calib.read_text())
    doc["cameras"] = doc["cameras"][:1]
    bad.write_text(json.dumps(doc))
    out = tmp_path / "b.csv"
    assert main(["track", str(hmc_shot / "hmc"), "--calib", str(bad), "--markers", markers, "--out", str(out)]) == 2
    with pytest.raises(InputError, match="not a stereo calibration"):
        StereoRig.load(bad)
    doc = json.loads(true_calib.read_text())
    doc["cameras"][0]["K"] = [[1, 0], [0, 1]]
    bad.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="not a stereo calibration"):
        StereoRig.load(bad)
    # An unreadable frame: the error names the file and the frame; nothing is written.
    shot = tmp_path / "shot"
    for c in ("cam0", "cam1"):
        (shot / c).mkdir(parents=True)
        for f in sorted((hmc_shot / "hmc" / c).iterdir())[:6]:
            shutil.copy(f, shot / c)
    (shot / "cam1" / "000003.png").write_bytes(b"broken")
    with pytest.raises(InputError) as e:
        from lgi.capture.footage import detect_footage

        detect_footage(shot)
    assert "000003.png" in str(e.value) and "frame 3" in str(e.value)
    assert main(["track", str(shot), "--calib", str(true_calib), "--markers", markers, "--out", str(out)]) == 2
    assert not out.exists() and not out.with_name("b.tracks.parquet").exists()
    # A frame missing from one camera: named, not silently dropped (later frames would be renumbered).
    (shot / "cam1" / "000003.png").unlink()
    with pytest.raises(InputError, match="no partner") as e:
        detect_footage(shot)
    assert "000003.png" in str(e.value)
    assert main(["track", str(shot), "--calib", str(true_calib), "--markers", markers, "--out", str(out)]) == 2
    assert not out.exists()
    # A label file naming an unknown marker.
    (shot / "cam0" / "000003.png").unlink()
    labels = tmp_path / "labels.csv"
    labels.write_text("camera,x,y,marker\n0,10,10,no_such_marker\n")
    assert main(["track", str(shot), "--calib", str(true_calib), "--markers", markers, "--out", str(out),
                 "--labels", str(labels)]) == 2
    assert not out.exists()


def test_helmet_markers_refine_a_flexed_rig() -> None:
    from scipy.spatial.transform import Rotation

    rig = hmc_rig("fisheye")
    helmet = np.array([[-85, 60, 20], [85, 60, 25], [-90, -40, 10], [90, -45, 5], [-60, -110, 30], [65, -105, 35],
                       [0, 95, 0.0]])
    # The shot's rig: camera 1 turned by 0.4 deg and shifted 0.5 mm on the helmet.
    c1 = rig.cameras[1]
    flex = Rotation.from_rotvec(np.radians([0.3, -0.2, 0.15])).as_matrix()
    shot = StereoRig([rig.cameras[0], c1.with_pose(flex @ c1.R, flex @ c1.t + [0.5, 0, 0])])
    rng = np.random.default_rng(2)
    uv = [c.project(helmet) + rng.normal(0, 0.2, (len(helmet), 2)) for c in shot.cameras]
    refined, rms = rig.refine_with_points(helmet, *uv)
    assert rms[1, 0] > 3 and rms[1, 1] < 0.5 and rms[0, 1] < 0.5
    # Face points triangulate better with the refined rig than with the calibration.
    X = np.random.default_rng(3).uniform([-60, -90, 0], [60, 80, 70], (200, 3))
    obs = [c.project(X) for c in shot.cameras]
    err_old = np.linalg.norm(rig.triangulate(*obs)[0] - X, axis=1)
    err_new = np.linalg.norm(refined.triangulate(*obs)[0] - X, axis=1)
    assert np.median(err_new) < 0.2 * np.median(err_old) and np.median(err_new) < 0.3


def test_track_from_a_label_file(hmc_shot: Path, tmp_path: Path) -> None:
    from lgi.capture.bundles import read_bundles

    t2 = np.load(hmc_shot / "hmc" / "truth.npz")
    names = list(t2["markers"])
    rows = [(c, *t2["centers"][0, c, m], names[m]) for c in range(2) for m in range(len(names))
            if t2["visible"][0, c, m]]
    labels = tmp_path / "labels.csv"
    pd.DataFrame(rows, columns=["camera", "x", "y", "marker"]).to_csv(labels, index=False)
    out = tmp_path / "t.csv"
    assert main(["track", str(hmc_shot / "hmc"), "--calib", str(hmc_shot / "hmc" / "cameras_true.json"),
                 "--markers", str(hmc_shot / "markers.csv"), "--out", str(out), "--labels", str(labels),
                 "--helmet", str(hmc_shot / "hmc" / "helmet.csv")]) == 0
    tracked, truth = read_bundles(out), read_bundles(hmc_shot / "bundles.csv")
    idx = [truth.markers.index(m) for m in tracked.markers]
    err_mm = 10 * np.linalg.norm(tracked.positions - truth.positions[:, idx], axis=2)
    assert np.sqrt(np.nanmean(err_mm**2)) < 0.5 and np.isfinite(err_mm).mean() > 0.95


def test_track_with_the_index_solves_the_head_pose_with_the_face(hmc_shot: Path, tmp_path: Path, capsys) -> None:
    """``lgi track --index``: every frame's pose is solved with the face, the tracks table says so, and the bundles
    land nearer the true markers than with the stable-marker fit (the expression no longer moves the head)."""
    from lgi.capture.bundles import read_bundles

    calib = hmc_shot / "hmc" / "cameras_true.json"
    index = tmp_path / "index"
    assert main(["build", str(hmc_shot / "dataset"), "--markers", str(hmc_shot / "markers.csv"), "--jaw-rig",
                 str(hmc_shot / "jaw_rig.npz"), "--out", str(index), "-q"]) == 0
    truth = read_bundles(hmc_shot / "bundles.csv")
    rms = {}
    for how in ("stable", "joint"):
        out = tmp_path / f"{how}.csv"
        extra = ["--index", str(index)] if how == "joint" else []
        capsys.readouterr()
        assert main(["track", str(hmc_shot / "hmc"), "--calib", str(calib), "--markers", str(hmc_shot / "markers.csv"),
                     "--out", str(out), "--helmet", str(hmc_shot / "hmc" / "helmet.csv"), *extra]) == 0
        text = capsys.readouterr().out
        table = pd.read_parquet(tmp_path / f"{how}.tracks.parquet")
        if how == "joint":
            assert "head pose: solved with the face in 30 of 30 frames" in text, text
            assert set(table["head_pose"]) == {"joint"}
            assert table["head_pose_rms_mm"].between(0.0, 1.0).all()
        else:
            assert set(table["head_pose"]) == {"stable markers"} and table["head_pose_rms_mm"].isna().all()
        tracked = read_bundles(out)
        idx = [truth.markers.index(m) for m in tracked.markers]
        # The rigid part of each frame's error (what a pose error leaves): the rotation (deg) that best carries the
        # tracked markers onto the true ones; the markers' own noise does not rotate them all one way.
        turn = []
        for f in range(len(tracked.frames)):
            ok = np.all(np.isfinite(tracked.positions[f]), axis=1)
            a, b = tracked.positions[f, ok], truth.positions[f, idx][ok]
            u, _, vt = np.linalg.svd((a - a.mean(0)).T @ (b - b.mean(0)))
            r = vt.T @ np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
            turn.append(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
        rms[how] = float(np.median(turn))
    assert rms["joint"] < 0.6 * rms["stable"], rms


def test_track_index_of_another_layout_is_refused(hmc_shot: Path, tmp_path: Path, small_index) -> None:
    from lgi.index.build import LGIIndex

    _, _, _, index, _ = small_index
    other = tmp_path / "other-index"
    renamed = LGIIndex(dict(index.manifest, markers=[f"x{k}" for k in range(index.n_markers)]), index.arrays,
                       index.deltas)
    renamed.save(other)
    out = tmp_path / "t.csv"
    assert main(["track", str(hmc_shot / "hmc"), "--calib", str(hmc_shot / "hmc" / "cameras_true.json"),
                 "--markers", str(hmc_shot / "markers.csv"), "--out", str(out), "--index", str(other)]) == 2
    assert not out.exists()
