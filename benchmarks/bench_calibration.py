"""`lgi calibrate` on the real stereo chessboard images against a direct cv2.stereoCalibrate.

    python benchmarks/bench_calibration.py [--images ../shared/data/stereo-chessboard]

Both run on the same corner detections (the views lgi kept), in the same run. lgi calibrates each camera,
rejects outlier views and fits the extrinsics with the intrinsics fixed; the direct recipe calibrates
each camera and then refines intrinsics and extrinsics jointly with cv2.stereoCalibrate. The stereo
RMS reprojection errors are compared.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from lgi.paths import shared_data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--images", type=Path, default=shared_data("stereo-chessboard"))
    args = ap.parse_args()
    if not args.images.is_dir():
        print(f"skipped: stereo images not found at {args.images}")
        return
    import cv2

    from lgi.capture.calibration import Board, calibrate_stereo, find_corners, pair_images

    board = Board.parse("chessboard:9x6:1")
    t = time.perf_counter()
    calib = calibrate_stereo(args.images, board)
    dt = time.perf_counter() - t
    pairs = {n: (lp, rp) for n, lp, rp in pair_images(args.images)}
    left, right = [], []
    for n in calib.used:
        left.append(find_corners(pairs[n][0], board)[0])
        right.append(find_corners(pairs[n][1], board)[0])
    obj = [board.object_points()] * len(left)
    # The usual direct recipe: each camera calibrated on the same detections, then everything refined
    # jointly (stereoCalibrate's default flags would fix the intrinsics instead).
    k = [cv2.calibrateCamera(obj, pts, calib.image_size, None, None)[1:3] for pts in (left, right)]
    direct = cv2.stereoCalibrate(obj, left, right, k[0][0].copy(), k[0][1].copy(), k[1][0].copy(), k[1][1].copy(),
                                 calib.image_size, flags=cv2.CALIB_USE_INTRINSIC_GUESS)
    rms_direct = float(direct[0])
    t_direct = np.asarray(direct[6]).ravel()
    print(f"{len(calib.used)} pairs used, {len(calib.rejected)} rejected ({', '.join(calib.rejected)})")
    print(f"lgi calibrate:           stereo RMS {calib.rms_stereo:.4f} px, baseline {calib.baseline_mm:.4f} squares "
          f"({dt:.2f} s)")
    print(f"cv2.stereoCalibrate:     stereo RMS {rms_direct:.4f} px, baseline {np.linalg.norm(t_direct):.4f} squares")
    rel = abs(calib.rms_stereo - rms_direct) / rms_direct * 100
    print(f"relative RMS difference: {rel:.2f} % (target: within 5 %)")


if __name__ == "__main__":
    main()
