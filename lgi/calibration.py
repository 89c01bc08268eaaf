"""Stereo camera calibration from images of a chessboard (OpenCV 5).

Images are paired by name (``left*``/``right*`` with the same suffix, or ``cam0/``, ``cam1/`` folders with
the same file names). Corners are found and refined to sub-pixel accuracy; each camera is calibrated
(pinhole with OpenCV's distortion, optionally the rational model); views whose reprojection RMS is far
above the others' (more than 3 times the median and 1 px) are rejected, saying which and why, and the
cameras recalibrated; the stereo extrinsics are then fitted with the intrinsics fixed.

Board units: the square size is in mm; distances in the result (translation, baseline) are in mm.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .atomic import atomic_file
from .errors import InputError

IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


@dataclass
class Board:
    """A chessboard: inner corners ``cols x rows``, square size in mm."""

    cols: int
    rows: int
    square_mm: float

    @classmethod
    def parse(cls, spec: str) -> Board:
        """``chessboard:COLSxROWS:SQUARE_MM`` (e.g. ``chessboard:9x6:25``)."""
        m = re.fullmatch(r"chessboard:(\d+)x(\d+):([0-9.]+)", spec.strip())
        if not m:
            raise InputError(f"board {spec!r}: expected chessboard:COLSxROWS:SQUARE_MM (ChArUco is not supported yet)")
        board = cls(int(m[1]), int(m[2]), float(m[3]))
        if board.cols < 2 or board.rows < 2 or board.square_mm <= 0:
            raise InputError(f"board {spec!r}: needs at least 2x2 inner corners and a positive square size")
        return board

    def object_points(self) -> np.ndarray:
        """(N, 3) float32 corner positions on the board plane, mm, in OpenCV's corner order."""
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.column_stack([g * self.square_mm, np.zeros(len(g))]).astype(np.float32)


def pair_images(folder: str | os.PathLike[str]) -> list[tuple[str, Path, Path]]:
    """(name, left, right) image pairs of a folder: ``left*``/``right*`` or ``cam0/``/``cam1/``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("image folder not found", path=folder)
    if (folder / "cam0").is_dir() and (folder / "cam1").is_dir():
        left = {p.name: p for p in (folder / "cam0").iterdir() if p.suffix.lower() in IMAGE_EXT}
        right = {p.name: p for p in (folder / "cam1").iterdir() if p.suffix.lower() in IMAGE_EXT}
        names = sorted(set(left) & set(right))
        pairs = [(n, left[n], right[n]) for n in names]
    else:
        files = [p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXT]
        left = {p.name[4:]: p for p in files if p.name.lower().startswith("left")}
        right = {p.name[5:]: p for p in files if p.name.lower().startswith("right")}
        pairs = [(f"pair{k}", left[k], right[k]) for k in sorted(set(left) & set(right))]
    if not pairs:
        raise InputError("no image pairs (left*/right* files, or cam0/ and cam1/ folders)", path=folder)
    return pairs


def find_corners(path: Path, board: Board) -> tuple[np.ndarray | None, tuple[int, int]]:
    """Sub-pixel chessboard corners (N, 2) float32 of an image (None if the board is not found), and the
    image size (width, height)."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError("unreadable image", path=path)
    ok, corners = cv2.findChessboardCorners(img, (board.cols, board.rows),
                                            flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None, (img.shape[1], img.shape[0])
    corners = np.ascontiguousarray(corners.reshape(-1, 1, 2), np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(img, corners, (11, 11), (-1, -1), crit)
    return corners.reshape(-1, 2), (img.shape[1], img.shape[0])


@dataclass
class StereoCalibration:
    """Result of :func:`calibrate_stereo` (lengths in mm)."""

    image_size: tuple[int, int]
    K: list[np.ndarray]
    dist: list[np.ndarray]
    R: np.ndarray
    T: np.ndarray
    rms_stereo: float
    rms_camera: list[float]
    per_view: dict[str, list[float]]
    rejected: dict[str, str] = field(default_factory=dict)
    used: list[str] = field(default_factory=list)
    model: str = "pinhole"

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.T))

    def to_json(self) -> dict:
        return {
            "format": "lgi-stereo-calibration", "format_version": 1, "model": self.model, "units": "mm",
            "image_size": list(self.image_size),
            "cameras": [{"K": k.tolist(), "dist": d.ravel().tolist(), "rms_px": r}
                        for k, d, r in zip(self.K, self.dist, self.rms_camera, strict=True)],
            "R": self.R.tolist(), "T": self.T.ravel().tolist(), "baseline_mm": self.baseline_mm,
            "rms_stereo_px": self.rms_stereo, "views_used": self.used, "per_view_rms_px": self.per_view,
            "rejected": self.rejected,
        }

    def save(self, path: str | os.PathLike[str], yaml: str | os.PathLike[str] | None = None) -> None:
        """Write the documented JSON (and optionally OpenCV YAML), atomically."""
        with atomic_file(path) as tmp:
            tmp.write_text(json.dumps(self.to_json(), indent=1))
        if yaml:
            import cv2

            with atomic_file(yaml, suffix=".yaml") as tmp:
                fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
                for i in range(2):
                    fs.write(f"K{i}", self.K[i])
                    fs.write(f"dist{i}", self.dist[i])
                fs.write("R", self.R)
                fs.write("T", self.T)
                fs.release()


def _per_view_rms(obj, img, rvecs, tvecs, K, d) -> list[float]:
    import cv2

    out = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, d)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    return out


def calibrate_stereo(folder: str | os.PathLike[str], board: Board, rational: bool = False,
                     min_views: int = 5) -> StereoCalibration:
    """Calibrate a stereo pair from chessboard images (see the module docstring)."""
    import cv2

    pairs = pair_images(folder)
    obj = board.object_points()
    detections: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    rejected: dict[str, str] = {}
    size = None
    for name, lp, rp in pairs:
        cl, sl = find_corners(lp, board)
        cr, sr = find_corners(rp, board)
        if sl != sr or (size is not None and sl != size):
            raise InputError(f"image sizes differ: {sl} and {sr} (expected {size or sl})", path=rp)
        size = sl
        if cl is None or cr is None:
            rejected[name] = f"board not found in the {'left' if cl is None else 'right'} image"
            continue
        detections[name] = (cl, cr)
    if len(detections) < min_views:
        raise InputError(f"the board was found in {len(detections)} image pairs, at least {min_views} are needed "
                         f"(board {board.cols}x{board.rows}; rejected: {rejected})", path=folder)
    flags = cv2.CALIB_RATIONAL_MODEL if rational else 0
    names = sorted(detections)

    def calibrate(views: list[str]) -> list:
        o = [obj] * len(views)
        out = []
        for cam in range(2):
            pts = [detections[n][cam] for n in views]
            rms, K, d, rv, tv = cv2.calibrateCamera(o, pts, size, None, None, flags=flags)
            out.append((rms, K, d, _per_view_rms(o, pts, rv, tv, K, d)))
        return out

    for _ in range(3):  # calibrate, reject outlier views, recalibrate
        res = calibrate(names)
        per_view = {n: [res[0][3][k], res[1][3][k]] for k, n in enumerate(names)}
        worst = np.array([max(v) for v in per_view.values()])
        limit = max(3 * float(np.median(worst)), 1.0)
        bad = [n for n, v in per_view.items() if max(v) > limit]
        if not bad or len(names) - len(bad) < min_views:
            break
        for n in bad:
            rejected[n] = (f"reprojection RMS {max(per_view[n]):.2f} px, above the limit of {limit:.2f} px "
                           "(3x the median view's, at least 1 px)")
        names = [n for n in names if n not in bad]
    if len(per_view) != len(names):
        res = calibrate(names)
        per_view = {n: [res[0][3][k], res[1][3][k]] for k, n in enumerate(names)}
    o = [obj] * len(names)
    K1, d1, K2, d2 = res[0][1].copy(), res[0][2].copy(), res[1][1].copy(), res[1][2].copy()
    out = cv2.stereoCalibrate(o, [detections[n][0] for n in names], [detections[n][1] for n in names],
                              K1, d1, K2, d2, size, flags=cv2.CALIB_FIX_INTRINSIC | flags)
    rms = out[0]
    R, T = out[5], out[6]
    return StereoCalibration(size, [res[0][1], res[1][1]], [res[0][2], res[1][2]], R, T, float(rms),
                             [float(res[0][0]), float(res[1][0])], per_view, rejected, names,
                             "pinhole-rational" if rational else "pinhole")
