"""Camera models and stereo triangulation.

A :class:`Camera` is OpenCV's pinhole model with its distortion (5, 8 or 14 coefficients, the rational
model included) or its fisheye model (equidistant projection ``r = f * theta`` with four polynomial terms).
``R, t`` map world points into the camera: ``X_cam = R @ X + t``. Lengths are in the calibration's units
(mm for :mod:`lgi.capture.calibration`); image points are pixels with OpenCV's convention (the centre of the
top-left pixel is (0, 0)).

A :class:`StereoRig` holds two cameras in one world frame (by default camera 0's) and triangulates:
linear (DLT on undistorted, normalised coordinates), then refined by Gauss-Newton on the reprojection
error with a Huber loss, and reports the per-point reprojection error in pixels through the full lens
model.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field

import numpy as np

from lgi.errors import InputError
from lgi.io.atomic import atomic_file

MODELS = ("pinhole", "pinhole-rational", "fisheye")


@dataclass
class Camera:
    """One calibrated camera.

    Attributes
    ----------
    K : (3, 3) float64
        Intrinsics, pixels.
    dist : (n,) float64
        Distortion: OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]]) or fisheye (k1, k2, k3, k4).
    model : str
        ``"pinhole"``, ``"pinhole-rational"`` or ``"fisheye"``.
    R : (3, 3) float64; t : (3,) float64
        World to camera.
    size : (width, height) in pixels
    """

    K: np.ndarray
    dist: np.ndarray
    model: str = "pinhole"
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size: tuple[int, int] = (1280, 1024)

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, np.float64).reshape(3, 3)
        self.dist = np.asarray(self.dist, np.float64).ravel()
        self.R = np.asarray(self.R, np.float64).reshape(3, 3)
        self.t = np.asarray(self.t, np.float64).reshape(3)
        self.size = (int(self.size[0]), int(self.size[1]))
        if self.model not in MODELS:
            raise InputError(f"camera model {self.model!r}: expected one of {MODELS}")
        if self.fisheye and self.dist.size != 4:
            raise InputError(f"a fisheye camera has 4 distortion coefficients, not {self.dist.size}")
        if not self.fisheye and self.dist.size not in (0, 4, 5, 8, 12, 14):
            raise InputError(f"{self.dist.size} distortion coefficients: OpenCV takes 4, 5, 8, 12 or 14")

    @property
    def fisheye(self) -> bool:
        return self.model == "fisheye"

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.R.T @ self.t

    def to_camera(self, X: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> camera coordinates."""
        return np.asarray(X, np.float64) @ self.R.T + self.t

    def project(self, X: np.ndarray) -> np.ndarray:
        """Project world points.

        Parameters
        ----------
        X : (N, 3) float, world units

        Returns
        -------
        (N, 2) float64, pixels. Points behind the camera give NaN.
        """
        import cv2

        Xc = self.to_camera(X).reshape(-1, 3)
        out = np.full((len(Xc), 2), np.nan)
        front = Xc[:, 2] > 1e-9
        if not front.any():
            return out
        pts = np.ascontiguousarray(Xc[front])
        zero = np.zeros(3)
        if self.fisheye:
            uv, _ = cv2.fisheye.projectPoints(pts.reshape(1, -1, 3), zero, zero, self.K, self.dist)
        else:
            uv, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), zero, zero, self.K, self.dist)
        out[front] = uv.reshape(-1, 2)
        return out

    def normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalised image coordinates ``(x/z, y/z)`` of pixels.

        Parameters
        ----------
        uv : (N, 2) float, pixels

        Returns
        -------
        (N, 2) float64
        """
        import cv2

        uv = np.ascontiguousarray(np.asarray(uv, np.float64).reshape(-1, 2))
        if len(uv) == 0:
            return np.zeros((0, 2))
        if self.fisheye:
            xy = cv2.fisheye.undistortPoints(uv.reshape(1, -1, 2), self.K, self.dist)
        else:
            crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
            xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist, None, None, None, crit)
        return xy.reshape(-1, 2).astype(np.float64)

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """(N, 3) unit viewing directions in camera coordinates of pixels ``uv`` (N, 2)."""
        xy = self.normalized(uv)
        d = np.column_stack([xy, np.ones(len(xy))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def projection_jacobian(self, X: np.ndarray, step: float = 1e-5) -> np.ndarray:
        """The Jacobian of :meth:`project` (the full lens model) at world points, by central differences.

        Parameters
        ----------
        X : (N, 3) float, world units
        step : the difference step, as a fraction of each point's distance from the camera

        Returns
        -------
        (N, 2, 3) float64, pixels per world unit (NaN for points behind the camera or not finite).
        """
        X = np.asarray(X, np.float64).reshape(-1, 3)
        h = step * np.linalg.norm(X - self.center, axis=1)
        J = np.empty((len(X), 2, 3))
        for k in range(3):
            d = np.zeros((len(X), 3))
            d[:, k] = h
            J[:, :, k] = (self.project(X + d) - self.project(X - d)) / (2 * h[:, None])
        return J

    def with_pose(self, R: np.ndarray, t: np.ndarray) -> Camera:
        return Camera(self.K.copy(), self.dist.copy(), self.model, np.asarray(R), np.asarray(t), self.size)

    def to_json(self) -> dict:
        return {"model": self.model, "size": list(self.size), "K": self.K.tolist(), "dist": self.dist.tolist(),
                "R": self.R.tolist(), "t": self.t.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> Camera:
        return cls(np.array(d["K"]), np.array(d["dist"]), d.get("model", "pinhole"), np.array(d["R"]),
                   np.array(d["t"]), tuple(d["size"]))


def triangulation_covariance(cameras: list[Camera], X: np.ndarray, pixel_noise: float) -> np.ndarray:
    """First-order covariance of points triangulated from the given cameras, each image coordinate measured with
    independent noise of ``pixel_noise`` px (one standard deviation).

    ``Cov = (sum_cam J^T J / pixel_noise^2)^-1`` with ``J`` each camera's projection Jacobian through its full lens
    model (:meth:`Camera.projection_jacobian`): the covariance of the maximum-likelihood (least reprojection
    error) point. A stereo pair places a point several times less precisely along its viewing rays (depth) than
    across them.

    Parameters
    ----------
    cameras : the cameras that see every point (a stereo rig's two)
    X : (..., 3) float, world units (NaN: not triangulated)
    pixel_noise : px

    Returns
    -------
    (..., 3, 3) float64, world units squared, NaN where ``X`` is not finite.
    """
    X = np.asarray(X, np.float64)
    flat = X.reshape(-1, 3)
    cov = np.full((len(flat), 3, 3), np.nan)
    ok = np.all(np.isfinite(flat), axis=1)
    if ok.any():
        info = np.zeros((int(ok.sum()), 3, 3))
        for cam in cameras:
            J = cam.projection_jacobian(flat[ok])
            info += np.einsum("nki,nkj->nij", J, J)
        info /= float(pixel_noise) ** 2
        good = np.all(np.isfinite(info), axis=(1, 2))
        good[good] = np.linalg.cond(info[good]) < 1e12  # a point on the baseline: no depth at all
        idx = np.flatnonzero(ok)[good]
        c = np.linalg.inv(info[good])
        cov[idx] = 0.5 * (c + c.transpose(0, 2, 1))
    return cov.reshape(*X.shape, 3)


def _huber_weights(r: np.ndarray, delta: float) -> np.ndarray:
    return np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))


@dataclass
class StereoRig:
    """Two cameras in one world frame."""

    cameras: list[Camera]

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.cameras[0].center - self.cameras[1].center))

    def relative(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, T) of camera 1 relative to camera 0 (OpenCV's ``stereoCalibrate`` convention)."""
        c0, c1 = self.cameras
        R = c1.R @ c0.R.T
        return R, c1.t - R @ c0.t

    def epipolar_distance(self, uv0: np.ndarray, uv1: np.ndarray) -> np.ndarray:
        """(N,) symmetric distance (pixels, approximate) of matched points to each other's epipolar line.

        Computed on undistorted normalised coordinates and scaled by the mean focal length.
        """
        x0 = self.cameras[0].normalized(uv0)
        x1 = self.cameras[1].normalized(uv1)
        return self.epipolar_distance_normalized(x0, x1)

    def essential(self) -> np.ndarray:
        R, T = self.relative()
        tx = np.array([[0, -T[2], T[1]], [T[2], 0, -T[0]], [-T[1], T[0], 0]])
        return tx @ R

    def epipolar_distance_normalized(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        E = self.essential()
        h0 = np.column_stack([x0, np.ones(len(x0))])
        h1 = np.column_stack([x1, np.ones(len(x1))])
        l1 = h0 @ E.T  # lines in image 1
        l0 = h1 @ E  # lines in image 0
        num = np.abs(np.sum(h1 * l1, axis=1))
        d1 = num / np.maximum(np.hypot(l1[:, 0], l1[:, 1]), 1e-12)
        d0 = num / np.maximum(np.hypot(l0[:, 0], l0[:, 1]), 1e-12)
        f = 0.5 * (self.cameras[0].K[0, 0] + self.cameras[1].K[0, 0])
        return 0.5 * (d0 + d1) * f

    def triangulate(self, uv0: np.ndarray, uv1: np.ndarray, iterations: int = 5,
                    huber_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Triangulate matched pixels.

        Linear (DLT) triangulation on undistorted normalised coordinates, then Gauss-Newton on the
        reprojection error measured in the undistorted image plane (scaled by each camera's focal length,
        so it is in pixels up to the local distortion scale) with Huber weights.

        Parameters
        ----------
        uv0, uv1 : (N, 2) float, pixels in cameras 0 and 1

        Returns
        -------
        X : (N, 3) float64, world units
        error : (N, 2) float64
            Reprojection error in each camera, pixels, through the full lens model.
        """
        uv0 = np.asarray(uv0, np.float64).reshape(-1, 2)
        uv1 = np.asarray(uv1, np.float64).reshape(-1, 2)
        n = len(uv0)
        if n == 0:
            return np.zeros((0, 3)), np.zeros((0, 2))
        xs = [self.cameras[0].normalized(uv0), self.cameras[1].normalized(uv1)]
        Ps = [np.column_stack([c.R, c.t]) for c in self.cameras]
        A = np.empty((n, 4, 4))
        for k, (x, P) in enumerate(zip(xs, Ps, strict=True)):
            A[:, 2 * k] = x[:, :1] * P[2] - P[0]
            A[:, 2 * k + 1] = x[:, 1:2] * P[2] - P[1]
        _, _, vt = np.linalg.svd(A)
        h = vt[:, -1]
        X = h[:, :3] / h[:, 3:4]
        fs = [0.5 * (c.K[0, 0] + c.K[1, 1]) for c in self.cameras]
        for _ in range(iterations):
            JtJ = np.zeros((n, 3, 3))
            Jtr = np.zeros((n, 3))
            for c, x, f in zip(self.cameras, xs, fs, strict=True):
                Xc = X @ c.R.T + c.t
                z = Xc[:, 2:3]
                p = Xc[:, :2] / z
                r = f * (p - x)
                w = _huber_weights(np.linalg.norm(r, axis=1), huber_px)
                # d p / d Xc, then chain through R.
                J = np.zeros((n, 2, 3))
                J[:, 0, 0] = 1 / z[:, 0]
                J[:, 1, 1] = 1 / z[:, 0]
                J[:, 0, 2] = -Xc[:, 0] / z[:, 0] ** 2
                J[:, 1, 2] = -Xc[:, 1] / z[:, 0] ** 2
                J = f * (J @ c.R)
                JtJ += w[:, None, None] * np.einsum("nki,nkj->nij", J, J)
                Jtr += w[:, None] * np.einsum("nki,nk->ni", J, r)
            step = np.linalg.solve(JtJ + 1e-12 * np.eye(3), Jtr[..., None])[..., 0]
            X = X - step
            if np.max(np.abs(step)) < 1e-9:
                break
        err = np.column_stack([np.linalg.norm(c.project(X) - uv, axis=1)
                               for c, uv in zip(self.cameras, (uv0, uv1), strict=True)])
        return X, err

    def refine_with_points(self, points: np.ndarray, uv0: np.ndarray, uv1: np.ndarray
                           ) -> tuple[StereoRig, np.ndarray]:
        """Re-estimate both cameras' poses from points fixed on the helmet (the rig may flex in a shot).

        Parameters
        ----------
        points : (H, 3) float, known positions in the rig frame (at least 4, not all on a line)
        uv0, uv1 : (H, 2) float, their pixels in cameras 0 and 1 (NaN where not seen)

        Returns
        -------
        rig : the refined rig (intrinsics unchanged, world frame = the points' frame)
        rms : (2, 2) reprojection RMS (px) of each camera, before and after
        """
        import cv2

        points = np.asarray(points, np.float64)
        cams, rms = [], np.zeros((2, 2))
        for k, (cam, uv) in enumerate(zip(self.cameras, (uv0, uv1), strict=True)):
            uv = np.asarray(uv, np.float64)
            ok = np.all(np.isfinite(uv), axis=1)
            if ok.sum() < 4:
                raise InputError(f"camera {k} sees {int(ok.sum())} helmet markers, at least 4 are needed")
            rms[k, 0] = np.sqrt(np.mean(np.sum((cam.project(points[ok]) - uv[ok]) ** 2, axis=1)))
            # Pose from undistorted normalised coordinates: the same for every lens model.
            x = cam.normalized(uv[ok])
            rvec, _ = cv2.Rodrigues(cam.R)
            _, rvec, tvec = cv2.solvePnP(points[ok], x, np.eye(3), None, rvec.copy(), cam.t.reshape(3, 1).copy(),
                                         True, cv2.SOLVEPNP_ITERATIVE)
            new = cam.with_pose(cv2.Rodrigues(rvec)[0], tvec.ravel())
            rms[k, 1] = np.sqrt(np.mean(np.sum((new.project(points[ok]) - uv[ok]) ** 2, axis=1)))
            cams.append(new)
        return StereoRig(cams), rms

    # ------------------------------------------------------------------ file
    def to_json(self) -> dict:
        return {"format": "lgi-stereo-rig", "format_version": 1, "cameras": [c.to_json() for c in self.cameras]}

    @classmethod
    def from_calibration(cls, calib: dict, path: str | os.PathLike[str] | None = None) -> StereoRig:
        """A rig from a calibration JSON document (:mod:`lgi.capture.calibration`'s format) or a rig document."""
        try:
            if calib.get("format") == "lgi-stereo-rig":
                cams = [Camera.from_json(c) for c in calib["cameras"]]
            else:
                size = tuple(calib["image_size"])
                model = calib.get("model", "pinhole")
                c0, c1 = calib["cameras"]
                cams = [Camera(np.array(c0["K"]), np.array(c0["dist"]), model, np.eye(3), np.zeros(3), size),
                        Camera(np.array(c1["K"]), np.array(c1["dist"]), model, np.array(calib["R"]),
                               np.array(calib["T"]), size)]
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not a stereo calibration: {type(e).__name__}: {e}", path=path) from e
        if len(cams) != 2:
            raise InputError(f"a stereo calibration has 2 cameras, this one has {len(cams)}", path=path)
        for c in cams:
            if not (np.all(np.isfinite(c.K)) and c.K[0, 0] > 0 and c.K[1, 1] > 0 and c.K[2, 2] == 1):
                raise InputError("camera matrix K is not a valid intrinsic matrix", path=path)
            if not np.allclose(c.R @ c.R.T, np.eye(3), atol=1e-6):
                raise InputError("camera rotation R is not a rotation matrix", path=path)
            if not np.all(np.isfinite(np.asarray(c.dist, float))):
                raise InputError("distortion coefficients are not all finite", path=path)
            if not np.all(np.isfinite(np.asarray(c.t, float))):
                raise InputError("camera translation T is not finite", path=path)
            size = np.asarray(c.size, float)
            if size.shape != (2,) or not np.all(size >= 1) or not np.all(size == np.round(size)):
                raise InputError(f"image size {list(c.size)} is not two positive whole numbers", path=path)
        return cls(cams)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> StereoRig:
        try:
            doc = json.loads(open(path, encoding="utf-8").read())
        except FileNotFoundError as e:
            raise InputError("calibration file not found", path=path) from e
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise InputError(f"calibration file is not JSON: {e}", path=path) from e
        if not isinstance(doc, dict):
            raise InputError("calibration file is not a JSON object", path=path)
        return cls.from_calibration(doc, path)

    def save(self, path: str | os.PathLike[str]) -> None:
        with atomic_file(path) as tmp:
            tmp.write_text(json.dumps(self.to_json(), indent=1))
