"""Stereo camera calibration from images of a chessboard or a ChArUco board (OpenCV 5).

Images are paired by name (``left*``/``right*`` with the same suffix, or ``cam0/``, ``cam1/`` folders with
the same file names). Corners are found and refined to sub-pixel accuracy (ChArUco: only the corners seen
by both cameras are used, and with a pinhole model a second detection pass uses the first pass's
intrinsics). Each camera is calibrated: pinhole with OpenCV's distortion (optionally the rational model)
or fisheye (equidistant). Views whose reprojection RMS is far above the others' (more than 3 times the
median and 1 px) are rejected, saying which and why, and the cameras recalibrated; the stereo extrinsics
are then fitted with the intrinsics fixed.

Board units: the square size is in mm; distances in the result (translation, baseline) are in mm.
"""

from __future__ import annotations

import json
import logging
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lgi.capture.camera import StereoRig
from lgi.errors import InputError
from lgi.io.atomic import atomic_file

IMAGE_EXT = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


@dataclass
class Board:
    """A calibration board.

    ``chessboard``: ``cols x rows`` inner corners. ``charuco``: ``cols x rows`` squares with ArUco markers of
    ``marker_mm`` from ``dictionary`` in the white squares (OpenCV's layout). Lengths in mm.
    """

    cols: int
    rows: int
    square_mm: float
    kind: str = "chessboard"
    marker_mm: float = 0.0
    dictionary: str = ""

    @classmethod
    def parse(cls, spec: str) -> Board:
        """``chessboard:COLSxROWS:SQUARE_MM`` or ``charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT``.

        Examples: ``chessboard:9x6:25``, ``charuco:7x5:15:11:DICT_5X5_100``.
        """
        spec = spec.strip()
        m = re.fullmatch(r"chessboard:(\d+)x(\d+):([0-9.]+)", spec)
        if m:
            board = cls(int(m[1]), int(m[2]), float(m[3]))
            if board.cols < 2 or board.rows < 2 or board.square_mm <= 0:
                raise InputError(f"board {spec!r}: needs at least 2x2 inner corners and a positive square size")
            return board
        m = re.fullmatch(r"charuco:(\d+)x(\d+):([0-9.]+):([0-9.]+):(DICT_\w+)", spec)
        if m:
            import cv2

            board = cls(int(m[1]), int(m[2]), float(m[3]), "charuco", float(m[4]), m[5])
            if not hasattr(cv2.aruco, board.dictionary):
                raise InputError(f"board {spec!r}: unknown ArUco dictionary {board.dictionary!r}")
            if board.cols < 3 or board.rows < 3 or not 0 < board.marker_mm < board.square_mm:
                raise InputError(f"board {spec!r}: needs at least 3x3 squares and 0 < MARKER_MM < SQUARE_MM")
            return board
        raise InputError(f"board {spec!r}: expected chessboard:COLSxROWS:SQUARE_MM or "
                         "charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT (e.g. charuco:7x5:15:11:DICT_5X5_100)")

    def spec(self) -> str:
        if self.kind == "charuco":
            return f"charuco:{self.cols}x{self.rows}:{self.square_mm:g}:{self.marker_mm:g}:{self.dictionary}"
        return f"chessboard:{self.cols}x{self.rows}:{self.square_mm:g}"

    def cv_board(self):
        """The ``cv2.aruco.CharucoBoard`` (ChArUco boards only)."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.cols, self.rows), self.square_mm, self.marker_mm, d)

    def object_points(self) -> np.ndarray:
        """(N, 3) float32 corner positions on the board plane, mm; row ``i`` is corner id ``i``."""
        if self.kind == "charuco":
            return np.asarray(self.cv_board().getChessboardCorners(), np.float32).reshape(-1, 3)
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2)
        return np.column_stack([g * self.square_mm, np.zeros(len(g))]).astype(np.float32)

    def extent_mm(self) -> tuple[float, float, float, float]:
        """(u0, v0, u1, v1): the printed pattern's rectangle in board coordinates, mm."""
        s = self.square_mm
        if self.kind == "charuco":
            return 0.0, 0.0, self.cols * s, self.rows * s
        return -s, -s, self.cols * s, self.rows * s

    def image(self, px_per_mm: float, margin_mm: float) -> np.ndarray:
        """(H, W) uint8 picture of the board (white margin included), for rendering synthetic views.

        Pixel centre ``(i, j)`` is at board coordinates ``u0 - margin + (j + 0.5) / px_per_mm`` (same in v).
        """
        u0, v0, u1, v1 = self.extent_mm()
        m = int(round(margin_mm * px_per_mm))
        w, h = int(round((u1 - u0) * px_per_mm)), int(round((v1 - v0) * px_per_mm))
        if self.kind == "charuco":
            return self.cv_board().generateImage((w + 2 * m, h + 2 * m), marginSize=m, borderBits=1)
        img = np.full((h + 2 * m, w + 2 * m), 255, np.uint8)
        jj, ii = np.meshgrid(np.arange(w), np.arange(h))
        sq = ((jj / px_per_mm) // self.square_mm + (ii / px_per_mm) // self.square_mm) % 2
        img[m:m + h, m:m + w] = np.where(sq == 0, 0, 255).astype(np.uint8)
        return img


def pair_images(folder: str | os.PathLike[str], strict: bool = False) -> list[tuple[str, Path, Path]]:
    """(name, left, right) image pairs of a folder: ``left*``/``right*`` or ``cam0/``/``cam1/``.

    ``strict``: an image without its partner is an error (footage, where frames are numbered in order and a
    missing one would shift every later frame), not skipped (calibration views).
    """
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
    if strict and set(left) != set(right):
        lone = sorted(set(left) ^ set(right))[0]
        path = left.get(lone) or right.get(lone)
        raise InputError(f"this image has no partner in the other camera ({len(set(left) ^ set(right))} unpaired)",
                         path=path)
    if not pairs:
        raise InputError("no image pairs (left*/right* files, or cam0/ and cam1/ folders)", path=folder)
    lone = sorted(set(left) ^ set(right))
    if lone:
        first = left.get(lone[0]) or right.get(lone[0])
        logging.getLogger(__name__).warning("%d image%s without a partner in the other camera left out (first: %s)",
                                            len(lone), "s" if len(lone) > 1 else "", first)
    return pairs


def read_gray(path: Path, frame: int | None = None) -> np.ndarray:
    """(H, W) uint8 image; :class:`InputError` naming the file (and ``frame``) if it cannot be read."""
    import cv2

    # OpenCV would also print its own warning for an unreadable file, before lgi's message.
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise InputError("unreadable image (missing, not an image, or damaged)", path=path, frame=frame)
    return img


def detect_board(img: np.ndarray, board: Board, camera=None) -> tuple[np.ndarray, np.ndarray] | None:
    """Sub-pixel board corners in one image.

    Parameters
    ----------
    img : (H, W) uint8
    camera : :class:`lgi.capture.camera.Camera`, optional
        Known pinhole intrinsics: ChArUco corners are then detected a second time with them (wide lenses).

    Returns
    -------
    (ids (N,) int32, corners (N, 2) float32 pixels), or None if the board is not found.
    """
    import cv2

    if board.kind == "charuco":
        det = cv2.aruco.CharucoDetector(board.cv_board())
        if camera is not None and not camera.fisheye:
            p = det.getCharucoParameters()
            p.cameraMatrix = camera.K.copy()
            p.distCoeffs = camera.dist.copy()
            det.setCharucoParameters(p)
        corners, ids, _, _ = det.detectBoard(img)
        if ids is None or len(ids) < 6:
            return None
        return ids.ravel().astype(np.int32), corners.reshape(-1, 2).astype(np.float32)
    ok, corners = cv2.findChessboardCorners(img, (board.cols, board.rows),
                                            flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
    if not ok:
        return None
    corners = np.ascontiguousarray(corners.reshape(-1, 1, 2), np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-3)
    corners = cv2.cornerSubPix(img, corners, (11, 11), (-1, -1), crit)
    return np.arange(len(corners), dtype=np.int32), corners.reshape(-1, 2)


def find_corners(path: Path, board: Board) -> tuple[np.ndarray | None, tuple[int, int]]:
    """Sub-pixel corners (N, 2) float32 of an image file (None if the board is not found), and the image
    size (width, height)."""
    img = read_gray(path)
    found = detect_board(img, board)
    return (None if found is None else found[1]), (img.shape[1], img.shape[0])


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


    def rig(self):
        """The calibrated :class:`lgi.capture.camera.StereoRig` (world frame = camera 0)."""
        return StereoRig.from_calibration(self.to_json())


View = tuple[np.ndarray, np.ndarray, np.ndarray]  # object points (N, 3), left (N, 2), right (N, 2)


def _calibrate_camera(obj: list[np.ndarray], img: list[np.ndarray], size: tuple[int, int], model: str):
    """(rms, K, dist, per-view RMS list) of one camera."""
    import cv2

    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    if model == "fisheye":
        o = [np.ascontiguousarray(x, np.float64).reshape(1, -1, 3) for x in obj]
        i = [np.ascontiguousarray(x, np.float64).reshape(1, -1, 2) for x in img]
        flags = cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
        rms, K, D, rv, tv = cv2.fisheye.calibrate(o, i, size, np.eye(3), np.zeros(4), flags=flags, criteria=crit)
        per = []
        for ob, im, r, t in zip(o, i, rv, tv, strict=True):
            proj, _ = cv2.fisheye.projectPoints(ob, r, t, K, D)
            per.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - im.reshape(-1, 2)) ** 2, axis=1)))))
        return float(rms), K, D.ravel(), per
    o = [np.ascontiguousarray(x, np.float32).reshape(-1, 3) for x in obj]
    i = [np.ascontiguousarray(x, np.float32).reshape(-1, 1, 2) for x in img]
    flags = cv2.CALIB_RATIONAL_MODEL if model == "pinhole-rational" else 0
    rms, K, D, rv, tv = cv2.calibrateCamera(o, i, size, None, None, flags=flags, criteria=crit)
    return float(rms), K, D.ravel(), _per_view_rms(o, i, rv, tv, K, D)


def calibrate_views(views: dict[str, View], size: tuple[int, int], model: str = "pinhole", min_views: int = 5,
                    rejected: dict[str, str] | None = None, source: str | os.PathLike[str] | None = None
                    ) -> StereoCalibration:
    """Calibrate a stereo pair from board detections.

    Each camera is calibrated alone; views whose reprojection RMS is far above the others' (more than 3
    times the median view's and at least 1 px) are rejected, saying why, and the cameras recalibrated;
    the stereo extrinsics are then fitted with the intrinsics fixed.

    Parameters
    ----------
    views : name -> (object points (N, 3) mm, left corners (N, 2) px, right corners (N, 2) px)
    size : (width, height), pixels
    model : ``"pinhole"``, ``"pinhole-rational"`` or ``"fisheye"``
    """
    import cv2

    rejected = dict(rejected or {})
    names = sorted(views)
    if len(names) < min_views:
        shown = "; ".join(f"{k}: {v}" for k, v in list(rejected.items())[:3])
        more = f"; and {len(rejected) - 3} more" if len(rejected) > 3 else ""
        raise InputError(f"{len(names)} usable image pair{'s' if len(names) != 1 else ''}, at least {min_views} are "
                         f"needed" + (f" (rejected: {shown}{more})" if rejected else ""), path=source)

    def calibrate(use: list[str]) -> list:
        obj = [views[n][0] for n in use]
        return [_calibrate_camera(obj, [views[n][1 + cam] for n in use], size, model) for cam in range(2)]

    res = None
    for _ in range(3):  # calibrate, reject outlier views, recalibrate
        try:
            res = calibrate(names)
        except cv2.error as e:
            raise InputError(f"calibration failed ({model} model, {len(names)} views): {e.err}", path=source) from e
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
        res = None
    if res is None:
        res = calibrate(names)
        per_view = {n: [res[0][3][k], res[1][3][k]] for k, n in enumerate(names)}
    K1, d1, K2, d2 = res[0][1].copy(), res[0][2].copy(), res[1][1].copy(), res[1][2].copy()
    if model == "fisheye":
        o = [np.ascontiguousarray(views[n][0], np.float64).reshape(1, -1, 3) for n in names]
        i0 = [np.ascontiguousarray(views[n][1], np.float64).reshape(1, -1, 2) for n in names]
        i1 = [np.ascontiguousarray(views[n][2], np.float64).reshape(1, -1, 2) for n in names]
        crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        out = cv2.fisheye.stereoCalibrate(o, i0, i1, K1, d1.reshape(4, 1), K2, d2.reshape(4, 1), size,
                                          flags=cv2.CALIB_FIX_INTRINSIC, criteria=crit)
    else:
        o = [np.ascontiguousarray(views[n][0], np.float32).reshape(-1, 3) for n in names]
        i0 = [np.ascontiguousarray(views[n][1], np.float32).reshape(-1, 1, 2) for n in names]
        i1 = [np.ascontiguousarray(views[n][2], np.float32).reshape(-1, 1, 2) for n in names]
        flags = cv2.CALIB_FIX_INTRINSIC | (cv2.CALIB_RATIONAL_MODEL if model == "pinhole-rational" else 0)
        out = cv2.stereoCalibrate(o, i0, i1, K1, d1, K2, d2, size, flags=flags)
    rms, R, T = out[0], out[5], out[6]
    return StereoCalibration(size, [res[0][1], res[1][1]], [res[0][2], res[1][2]], np.asarray(R, np.float64),
                             np.asarray(T, np.float64).reshape(3, 1), float(rms), [res[0][0], res[1][0]], per_view,
                             rejected, names, model)


def _per_view_rms(obj, img, rvecs, tvecs, K, d) -> list[float]:
    import cv2

    out = []
    for o, i, r, t in zip(obj, img, rvecs, tvecs, strict=True):
        proj, _ = cv2.projectPoints(o, r, t, K, d)
        out.append(float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - i.reshape(-1, 2)) ** 2, axis=1)))))
    return out


def _detect_pairs(pairs, board: Board, cameras=None) -> tuple[dict[str, View], dict[str, str], tuple[int, int]]:
    obj_all = board.object_points()
    views: dict[str, View] = {}
    rejected: dict[str, str] = {}
    size = None
    for name, lp, rp in pairs:
        imgs = [read_gray(lp), read_gray(rp)]
        sl, sr = (imgs[0].shape[1], imgs[0].shape[0]), (imgs[1].shape[1], imgs[1].shape[0])
        if size is not None:
            for path, s in ((lp, sl), (rp, sr)):
                if s != size:
                    raise InputError(f"image is {s[0]}x{s[1]}, the images before it are {size[0]}x{size[1]}",
                                     path=path)
        elif sl != sr:
            raise InputError(f"image is {sr[0]}x{sr[1]}, its left partner {Path(lp).name} is {sl[0]}x{sl[1]}",
                             path=rp)
        size = sl
        found = [detect_board(im, board, None if cameras is None else cameras[k]) for k, im in enumerate(imgs)]
        if found[0] is None or found[1] is None:
            rejected[name] = f"board not found in the {'left' if found[0] is None else 'right'} image"
            continue
        common, i0, i1 = np.intersect1d(found[0][0], found[1][0], return_indices=True)
        if len(common) < 6:
            rejected[name] = f"only {len(common)} corners seen by both cameras (at least 6 needed)"
            continue
        # A copy of an earlier view (the same file twice, or a frame grabbed twice from a still board) adds no
        # constraint but makes the fit look better determined than it is.
        copy = next((other for other, v in views.items() if len(v[0]) == len(common)
                     and np.array_equal(v[0], obj_all[common]) and np.abs(v[1] - found[0][1][i0]).max() < 0.5
                     and np.abs(v[2] - found[1][1][i1]).max() < 0.5), None)
        if copy is not None:
            rejected[name] = f"the same board position as {copy} (within 0.5 px): a copy adds nothing"
            continue
        views[name] = (obj_all[common], found[0][1][i0], found[1][1][i1])
    return views, rejected, size


def calibrate_stereo(folder: str | os.PathLike[str], board: Board, rational: bool = False, fisheye: bool = False,
                     min_views: int = 5) -> StereoCalibration:
    """Calibrate a stereo pair from board images (see the module docstring).

    ChArUco boards with a pinhole model are detected twice: the second pass uses the first calibration's
    intrinsics, which places corners better under strong distortion.
    """
    if rational and fisheye:
        raise InputError("--rational and --fisheye are different lens models: choose one")
    model = "fisheye" if fisheye else "pinhole-rational" if rational else "pinhole"
    pairs = pair_images(folder)
    views, rejected, size = _detect_pairs(pairs, board)
    calib = calibrate_views(views, size, model, min_views, rejected, folder)
    if board.kind == "charuco" and not fisheye:
        cams = calib.rig().cameras
        views2, rejected2, _ = _detect_pairs(pairs, board, cams)
        if len(views2) >= min_views:
            calib = calibrate_views(views2, size, model, min_views, rejected2, folder)
    return calib
