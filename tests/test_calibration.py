import shutil
from pathlib import Path

import numpy as np
import pytest

from lgi.capture.calibration import Board, calibrate_stereo, find_corners, pair_images
from lgi.cli import main
from lgi.errors import InputError
from lgi.paths import shared_data

IMAGES = shared_data("stereo-chessboard")


@pytest.fixture(scope="module")
def images() -> Path:
    if not (IMAGES / "left01.jpg").is_file():
        pytest.skip(f"stereo chessboard images not found at {IMAGES}")
    return IMAGES


def test_real_images_match_a_direct_stereo_calibration(images: Path, tmp_path: Path) -> None:
    import cv2

    assert main(["calibrate", str(images), "--board", "chessboard:9x6:1", "--out", str(tmp_path / "c.json"),
                 "--yaml", str(tmp_path / "c.yaml")]) == 0
    board = Board.parse("chessboard:9x6:1")
    calib = calibrate_stereo(images, board)
    assert len(calib.used) >= 10 and calib.rms_stereo < 0.5
    pairs = {n: (lp, rp) for n, lp, rp in pair_images(images)}
    left = [find_corners(pairs[n][0], board)[0] for n in calib.used]
    right = [find_corners(pairs[n][1], board)[0] for n in calib.used]
    obj = [board.object_points()] * len(left)
    k = [cv2.calibrateCamera(obj, pts, calib.image_size, None, None)[1:3] for pts in (left, right)]
    direct = cv2.stereoCalibrate(obj, left, right, k[0][0].copy(), k[0][1].copy(), k[1][0].copy(), k[1][1].copy(),
                                 calib.image_size, flags=cv2.CALIB_USE_INTRINSIC_GUESS)[0]
    assert abs(calib.rms_stereo - direct) / direct < 0.05
    fs = cv2.FileStorage(str(tmp_path / "c.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("K0").mat(), calib.K[0], rtol=1e-6)


def test_bad_inputs(images: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="expected chessboard"):
        Board.parse("chessboard:9by6")
    # Unreadable image.
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "left01.png").write_bytes(b"not an image")
    (bad / "right01.png").write_bytes(b"not an image")
    with pytest.raises(InputError, match="unreadable image"):
        calibrate_stereo(bad, Board.parse("chessboard:9x6:1"))
    # Board not found in any view (wrong size), and fewer views than needed: nothing written.
    out = tmp_path / "c.json"
    assert main(["calibrate", str(images), "--board", "chessboard:7x4:1", "--out", str(out)]) == 2
    assert not out.exists()
    few = tmp_path / "few"
    few.mkdir()
    for n in ("01", "03"):
        shutil.copy(images / f"left{n}.jpg", few)
        shutil.copy(images / f"right{n}.jpg", few)
    with pytest.raises(InputError, match="at least 5 are needed"):
        calibrate_stereo(few, Board.parse("chessboard:9x6:1"))
    with pytest.raises(InputError, match="no image pairs"):
        pair_images(tmp_path / "bad" / "..")
