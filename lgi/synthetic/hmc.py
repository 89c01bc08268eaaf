"""Synthetic head-mounted camera (HMC) footage of the synthetic actor, with a known truth.

Two cameras stacked vertically on a helmet boom film the face (the helmet frame is the head frame, mm).
Each frame is rendered with a z-buffer, so a dot hidden by the nose or the lips is not drawn; painted
dots are discs of a physical size on the skin (so they foreshorten and are cut by occluders), the skin
has a shaded, mottled albedo with dark eyes, brows and nostrils and specular highlights from the ring
lights, and the image has optical blur and sensor noise. The helmet may slip on the head a little (a
smooth rigid motion) so that stabilisation has work to do. Calibration board images are rendered with
the same cameras.

Layout written by :func:`write_footage` (``OUT/hmc``)::

    cam0/000000.png ...     upper camera, 8-bit grey
    cam1/000000.png ...     lower camera
    calib/left01.png, right01.png ...   board views for ``lgi calibrate``
    cameras_true.json       the true rig in the calibration format (camera 0 frame, mm) plus the head frame
    helmet.csv              the helmet dots (name,x,y,z; mm, calibration frame)
    truth.npz               per frame: head motion (and the jolt frames), true 2D dot centres and visibility per camera
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lgi.capture.calibration import Board
from lgi.capture.camera import Camera, StereoRig
from lgi.dataset.mesh import vertex_normals
from lgi.errors import InputError
from lgi.io.npz import save_npz
from lgi.progress import progress
from lgi.synthetic.actor import EYE_CENTERS, MOUTH_Y

MM_PER_CM = 10.0
# Dots fixed on the helmet (head frame, mm), beside the face: each on a light plate, seen by both cameras.
HELMET_MM = np.array([[82.0, 60, 45], [-82, 60, 40], [88, -20, 35], [-88, -25, 38], [80, -95, 48], [-80, -92, 44]])
HELMET_PLATE_MM = 4.0


def look_at(center: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 1.0, 0.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``center`` looking at ``target`` with image-up along ``up``."""
    z = np.asarray(target, float) - center
    z /= np.linalg.norm(z)
    x = np.cross(-np.asarray(up, float), z)  # OpenCV: x right, y down
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def hmc_rig(model: str = "fisheye", size: tuple[int, int] = (1280, 1024), baseline_mm: float = 70.0) -> StereoRig:
    """The synthetic helmet's cameras in the head frame (mm): upper camera 0 and lower camera 1.

    Both sit 18 cm in front of the face and converge on the mid-face. ``model`` ``"pinhole"`` has
    moderate barrel distortion; ``"fisheye"`` is an equidistant wide lens.
    """
    w, h = size
    s = w / 1280.0
    if model == "fisheye":
        K = np.array([[760.0 * s, 0, w / 2 - 0.5 + 3.1 * s], [0, 758.0 * s, h / 2 - 0.5 - 2.4 * s], [0, 0, 1]])
        dist = np.array([0.045, -0.012, 0.004, -0.0008])
    elif model in ("pinhole", "pinhole-rational"):
        K = np.array([[820.0 * s, 0, w / 2 - 0.5 + 3.1 * s], [0, 818.0 * s, h / 2 - 0.5 - 2.4 * s], [0, 0, 1]])
        dist = np.array([-0.12, 0.05, 0.0004, -0.0003, -0.01])
        model = "pinhole"
    else:
        raise InputError(f"lens model {model!r}: pinhole or fisheye")
    target = np.array([0.0, -5.0, 30.0])
    cams = []
    for sign, k in ((1, 0), (-1, 1)):
        center = np.array([0.0 + 1.5 * k, -5.0 + sign * baseline_mm / 2, 215.0])
        R, t = look_at(center, target)
        cams.append(Camera(K * np.array([[1 + 0.004 * k], [1 + 0.004 * k], [1]]), dist * (1 + 0.05 * k), model, R, t,
                           size))
    return StereoRig(cams)


def calibration_json(rig: StereoRig) -> dict:
    """The rig in ``lgi calibrate``'s JSON format (camera 0 frame)."""
    R, T = rig.relative()
    c0, c1 = rig.cameras
    return {"format": "lgi-stereo-calibration", "format_version": 1, "model": c0.model, "units": "mm",
            "image_size": list(c0.size),
            "cameras": [{"K": c.K.tolist(), "dist": c.dist.tolist()} for c in (c0, c1)],
            "R": R.tolist(), "T": T.tolist(), "baseline_mm": rig.baseline}


def head_motion(n_frames: int, seed: int = 0, max_deg: float = 1.0, max_mm: float = 1.5
                ) -> tuple[np.ndarray, np.ndarray]:
    """Smooth helmet slip: (F, 3, 3) rotations and (F, 3) translations (mm), identity at frame 0."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed + 101)
    t = np.arange(n_frames) / 30.0
    rv = np.zeros((n_frames, 3))
    tr = np.zeros((n_frames, 3))
    for k in range(3):
        for amp, out in ((np.radians(max_deg), rv), (max_mm, tr)):
            f = rng.uniform(0.05, 0.4, 2)
            ph = rng.uniform(0, 2 * np.pi, 2)
            sig = sum(np.sin(2 * np.pi * fi * t + p) - np.sin(p) for fi, p in zip(f, ph, strict=True))
            out[:, k] = amp * sig / 2
    return Rotation.from_rotvec(rv).as_matrix(), tr


#: Helmet jolts: angle (deg) and shift (mm) ranges of one jolt, the frames it takes, and the frames between jolts.
JOLT_DEG = (0.5, 1.5)
JOLT_MM = (1.0, 3.0)
JOLT_FRAMES = (1, 3)
JOLT_GAP = (30, 90)
#: Helmet vibration on top of the jolts: amplitude (deg, mm) and frequency range (Hz at 30 frames/s).
VIBRATION_DEG = 0.02
VIBRATION_MM = 0.03
VIBRATION_HZ = (6.0, 12.0)


def helmet_jolts(n_frames: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sudden helmet shifts, each then held, with a little vibration: what a helmet does when the actor
    turns or lands a jump.

    A jolt turns the helmet by 0.5-1.5 deg about a random axis through the head and shifts it 1-3 mm, over 1-3
    frames (smoothstep), every 30-90 frames; the helmet then sits in its new place. A vibration of a few
    hundredths of a degree and millimetre (6-12 Hz sinusoids) rides on top.

    Returns
    -------
    R : (F, 3, 3) float64, t : (F, 3) float64 (mm): the motion to compose with :func:`head_motion`'s
    jolting : (F,) bool: frames during a jolt (its ramp)
    """
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed + 303)
    rv = np.zeros((n_frames, 3))
    tr = np.zeros((n_frames, 3))
    jolting = np.zeros(n_frames, bool)
    f0 = int(rng.integers(*JOLT_GAP))
    while f0 < n_frames:
        axis = rng.normal(size=3)
        step_rv = np.radians(rng.uniform(*JOLT_DEG)) * axis / np.linalg.norm(axis)
        d = rng.normal(size=3)
        step_t = rng.uniform(*JOLT_MM) * d / np.linalg.norm(d)
        n = int(rng.integers(JOLT_FRAMES[0], JOLT_FRAMES[1] + 1))
        ramp = np.ones(n_frames - f0)
        k = np.arange(1, n + 1) / n
        ramp[:n] = k * k * (3 - 2 * k)
        rv[f0:] += ramp[:, None] * step_rv  # small angles: rotation vectors add to first order, exact enough here
        tr[f0:] += ramp[:, None] * step_t
        jolting[f0:f0 + n] = True
        f0 += n + int(rng.integers(*JOLT_GAP))
    t = np.arange(n_frames) / 30.0
    for k in range(3):
        for amp, out in ((np.radians(VIBRATION_DEG), rv), (VIBRATION_MM, tr)):
            out[:, k] += amp * np.sin(2 * np.pi * rng.uniform(*VIBRATION_HZ) * t + rng.uniform(0, 2 * np.pi))
    rv -= rv[0]
    tr -= tr[0]
    return Rotation.from_rotvec(rv).as_matrix(), tr, jolting


#: The helmet slips ``lgi synth --hmc --slip`` knows.
SLIPS = ("smooth", "jolts")


def helmet_slip(n_frames: int, seed: int = 0, slip: str = "smooth", max_deg: float = 1.0, max_mm: float = 1.5
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The helmet's motion on the head over the shot: ``smooth`` (:func:`head_motion`) or ``jolts`` (the smooth
    slip with :func:`helmet_jolts` on top). Returns R (F, 3, 3), t (F, 3) mm and the jolt frames (F,) bool."""
    R, t = head_motion(n_frames, seed, max_deg, max_mm)
    if slip == "smooth":
        return R, t, np.zeros(n_frames, bool)
    if slip != "jolts":
        raise InputError(f"unknown slip {slip!r}: {', '.join(SLIPS)}")
    Rj, tj, jolting = helmet_jolts(n_frames, seed)
    # The jolt moves the helmet on the head, then the slow slip carries both.
    return np.einsum("fij,fjk->fik", R, Rj), np.einsum("fij,fj->fi", R, tj) + t, jolting


@dataclass
class Renderer:
    """Renders the actor's face with painted dots through one camera.

    Parameters
    ----------
    triangles : (T, 3) int
    neutral_cm : (V, 3) neutral positions (cm, for the albedo pattern)
    dot_vertices : (D, 3) int, dot_weights : (D, 3): the painted dots' triangles and barycentric weights
    dot_radius_mm : painted dot radius
    noise : sensor noise, grey levels (0-255)
    blur_px : optical blur (Gaussian sigma, pixels)
    """

    triangles: np.ndarray
    neutral_cm: np.ndarray
    dot_vertices: np.ndarray
    dot_weights: np.ndarray
    dot_radius_mm: float = 1.1
    noise: float = 2.0
    blur_px: float = 0.7
    seed: int = 0
    albedo: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        x, y = self.neutral_cm[:, 0], self.neutral_cm[:, 1]
        rng = np.random.default_rng(self.seed + 7)
        a = np.full(len(x), 0.74)
        for _ in range(6):  # low-frequency mottling fixed to the skin
            k = rng.normal(0, 0.9, 2)
            a += 0.02 * np.sin(k[0] * x + k[1] * y + rng.uniform(0, 6.3))
        ax = np.abs(x)
        for ex, ey in EYE_CENTERS:  # eyes: large dark regions
            a = np.where(((x - ex) / 1.3) ** 2 + ((y - ey) / 0.55) ** 2 < 1, 0.12, a)
        brow = (ax > 1.4) & (ax < 5.0) & (np.abs(y - (4.0 + 0.05 * (ax - 3) ** 2)) < 0.25)
        a = np.where(brow, 0.3, a)
        nostril = ((ax - 0.75) / 0.42) ** 2 + ((y + 1.95) / 0.17) ** 2 < 1
        a = np.where(nostril, 0.1, a)
        lips = (np.abs(y - MOUTH_Y) < 0.7) & (ax < 2.3)
        a = np.where(lips, a * 0.8, a)
        self.albedo = a

    def dots(self, vertices: np.ndarray) -> np.ndarray:
        """(D, 3) dot centres on the surface ``vertices`` (V, 3)."""
        return np.einsum("dk,dkx->dx", self.dot_weights, vertices[self.dot_vertices])

    def render(self, camera: Camera, vertices_mm: np.ndarray, rng: np.random.Generator,
               dot_jitter_px: float = 0.0, helmet_mm: np.ndarray | None = None,
               plate_towards: np.ndarray | None = None, points_mm: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                      np.ndarray]:
        """Render one image.

        Parameters
        ----------
        vertices_mm : (V, 3) face in the world (helmet) frame, mm
        dot_jitter_px : random displacement of each painted dot (pixels, per axis, Gaussian): how far the
            paint's centre is from the marker's true point, as seen by this camera
        helmet_mm : (H, 3), optional: helmet dots (world frame), drawn on light plates facing ``plate_towards``
        points_mm : (P, 3), optional: surface points (world frame) whose visibility is returned too

        Returns
        -------
        image : (H, W) uint8
        centers : (D, 2) float64 true projections of the dot centres, px
        visible : (D,) bool: centre and rim unoccluded and the dot facing the camera
        points_visible : (P,) bool, with ``points_mm``: in the image and not behind the surface (0.5 mm)
        """
        import cv2

        from lgi.synthetic import _raster

        w, h = camera.size
        tris = np.ascontiguousarray(self.triangles, np.int64)
        dots_mm = self.dots(vertices_mm)
        Xc = camera.to_camera(vertices_mm)
        uv = camera.project(vertices_mm)
        zbuf, tid, bary = _raster.rasterize(uv, Xc[:, 2].copy(), tris, h, w)
        n = vertex_normals(vertices_mm, tris)
        view = camera.center - vertices_mm
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        cos = np.sum(n * view, axis=1)
        # Ring light at the camera: diffuse plus a tight specular lobe.
        value = self.albedo * (0.3 + 0.75 * np.clip(cos, 0, 1)) + 0.9 * np.clip(cos, 0, 1) ** 120
        yy = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
        background = np.broadcast_to(0.32 + 0.08 * yy, (h, w)).astype(np.float32).copy()
        img, pos = _raster.shade(tid, bary, tris, value.astype(np.float32), Xc.astype(np.float32), background)
        centers = camera.project(dots_mm)
        dc = camera.to_camera(dots_mm)
        if dot_jitter_px > 0:
            off = rng.normal(0, dot_jitter_px, (len(dots_mm), 2)) * dc[:, 2:3] / camera.K[0, 0]
            dc = dc + np.column_stack([off, np.zeros(len(dc))])
        pix = dc[:, 2] / camera.K[0, 0]  # mm per pixel at the dot
        rpx = self.dot_radius_mm / pix
        painted_px = camera.project((dc - camera.t) @ camera.R)  # jittered centres back in the world frame
        _raster.paint_dots(img, pos, dc.astype(np.float32), painted_px, self.dot_radius_mm, rpx,
                           pix.astype(np.float64), 0.08)
        if helmet_mm is not None:
            self._paint_helmet(img, camera, helmet_mm, plate_towards)
        img = cv2.GaussianBlur(img, (0, 0), self.blur_px)
        img = img * 255.0 + rng.normal(0, self.noise, img.shape)
        image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        visible = self._visible(camera, dots_mm, n, zbuf)
        if points_mm is None:
            return image, centers, visible
        return image, centers, visible, _unoccluded(camera, points_mm, zbuf)

    def _paint_helmet(self, img: np.ndarray, camera: Camera, helmet_mm: np.ndarray, towards: np.ndarray) -> None:
        h, w = img.shape
        for P in helmet_mm:
            n = towards - P
            n /= np.linalg.norm(n)
            Pc, nc = camera.to_camera(P[None])[0], camera.R @ n
            c = camera.project(P[None])[0]
            r = 1.5 * HELMET_PLATE_MM * camera.K[0, 0] / Pc[2] + 2
            x0, x1 = max(int(c[0] - r), 0), min(int(c[0] + r) + 1, w - 1)
            y0, y1 = max(int(c[1] - r), 0), min(int(c[1] + r) + 1, h - 1)
            if x1 <= x0 or y1 <= y0:
                continue
            yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
            xy = camera.normalized(np.column_stack([xx.ravel(), yy.ravel()]))
            d = np.column_stack([xy, np.ones(len(xy))])
            X = d * ((nc @ Pc) / (d @ nc))[:, None]
            dist = np.linalg.norm(X - Pc, axis=1).reshape(xx.shape)
            pix = Pc[2] / camera.K[0, 0]
            plate = np.clip((HELMET_PLATE_MM - dist) / pix + 0.5, 0, 1)
            dot = np.clip((self.dot_radius_mm - dist) / pix + 0.5, 0, 1)
            win = img[y0:y1 + 1, x0:x1 + 1]
            win[:] = win * (1 - plate) + 0.85 * plate
            win *= 1 - 0.92 * dot

    def _visible(self, camera: Camera, dots_mm: np.ndarray, normals: np.ndarray, zbuf: np.ndarray) -> np.ndarray:
        w, h = camera.size
        nrm = self.dots(normals)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        view = camera.center - dots_mm
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        facing = np.sum(nrm * view, axis=1) > 0.25
        # Centre and 8 rim points must all pass the depth test.
        a = np.cross(nrm, [0.0, 0.0, 1.0])
        a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
        b = np.cross(nrm, a)
        ok = facing.copy()
        for ang in [None, *np.linspace(0, 2 * np.pi, 8, endpoint=False)]:
            p = dots_mm if ang is None else dots_mm + self.dot_radius_mm * (np.cos(ang) * a + np.sin(ang) * b)
            uv = camera.project(p)
            z = camera.to_camera(p)[:, 2]
            inside = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (
                uv[:, 1] <= h - 1)
            ix = np.clip(np.rint(np.nan_to_num(uv)).astype(int), 0, [w - 1, h - 1])
            ok &= inside & (z <= zbuf[ix[:, 1], ix[:, 0]] + 0.5)
        return ok


def _unoccluded(camera: Camera, points_mm: np.ndarray, zbuf: np.ndarray, tol_mm: float = 0.5) -> np.ndarray:
    """(P,) bool: points inside the image and not behind the rendered surface (depth buffer ``zbuf``)."""
    w, h = camera.size
    uv = camera.project(points_mm)
    z = camera.to_camera(points_mm)[:, 2]
    inside = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (
        uv[:, 1] <= h - 1)
    ix = np.clip(np.rint(np.nan_to_num(uv)).astype(int), 0, [w - 1, h - 1])
    return inside & (z <= zbuf[ix[:, 1], ix[:, 0]] + tol_mm)


def board_poses(rig: StereoRig, board, n: int, seed: int = 0, margin_px: float = 30.0) -> list[np.ndarray]:
    """``n`` random board poses (4x4, board -> world) whose whole pattern is seen by both cameras."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed + 5)
    obj = np.asarray(board.object_points(), np.float64)
    u0, v0, u1, v1 = board.extent_mm()
    corners = np.array([[u0, v0, 0], [u1, v0, 0], [u1, v1, 0], [u0, v1, 0]], float)
    centre = np.array([(u0 + u1) / 2, (v0 + v1) / 2, 0.0])
    out = []
    for _ in range(200 * n):
        if len(out) == n:
            break
        rot = Rotation.from_euler("xyz", [rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-25, 25)],
                                  degrees=True).as_matrix()
        # OpenCV's board frame seen unmirrored: x right, y down in the image, z away from the cameras.
        rot = rot @ np.diag([1.0, -1.0, -1.0])
        pos = np.array([rng.uniform(-50, 50), rng.uniform(-60, 50), rng.uniform(-10, 90)])
        T = np.eye(4)
        T[:3, :3] = rot
        T[:3, 3] = pos - rot @ centre
        ok = True
        for cam in rig.cameras:
            pts = np.vstack([obj, corners]) @ T[:3, :3].T + T[:3, 3]
            uv = cam.project(pts)
            w, h = cam.size
            ok &= bool(np.all(np.isfinite(uv)) and uv[:, 0].min() > margin_px and uv[:, 1].min() > margin_px
                       and uv[:, 0].max() < w - margin_px and uv[:, 1].max() < h - margin_px)
            normal = T[:3, :3] @ [0, 0, 1.0]
            ok &= bool(np.dot(normal, pts.mean(0) - cam.center) > 0.35 * np.linalg.norm(cam.center - pts.mean(0)))
        if ok:
            out.append(T)
    if len(out) < n:
        raise RuntimeError(f"found only {len(out)} board poses seen by both cameras")
    return out


def board_corner_views(rig: StereoRig, board, poses: list[np.ndarray], noise_px: float, seed: int = 0) -> dict:
    """Views for :func:`lgi.capture.calibration.calibrate_views`: projected corners plus Gaussian noise (px)."""
    rng = np.random.default_rng(seed + 9)
    obj = np.asarray(board.object_points(), np.float64)
    views = {}
    for k, T in enumerate(poses):
        pts = obj @ T[:3, :3].T + T[:3, 3]
        uvs = [c.project(pts) + rng.normal(0, noise_px, (len(pts), 2)) for c in rig.cameras]
        views[f"view{k:02d}"] = (obj.astype(np.float32), uvs[0].astype(np.float32), uvs[1].astype(np.float32))
    return views


class BoardRenderer:
    """Renders a calibration board through a camera (2x2 supersampled, rays cached per camera)."""

    def __init__(self, board, px_per_mm: float = 12.0, margin_mm: float | None = None) -> None:
        self.board = board
        self.px_per_mm = px_per_mm
        self.margin_mm = board.square_mm if margin_mm is None else margin_mm
        self.texture = board.image(px_per_mm, self.margin_mm).astype(np.float32) / 255.0
        self._rays: dict[int, list[np.ndarray]] = {}

    def _camera_rays(self, camera: Camera) -> list[np.ndarray]:
        key = id(camera)
        if key not in self._rays:
            w, h = camera.size
            yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
            rays = []
            for dy in (-0.25, 0.25):
                for dx in (-0.25, 0.25):
                    xy = camera.normalized(np.column_stack([(xx + dx).ravel(), (yy + dy).ravel()]))
                    rays.append(np.column_stack([xy, np.ones(len(xy))]).reshape(h, w, 3).astype(np.float32))
            self._rays[key] = rays
        return self._rays[key]

    def render(self, camera: Camera, pose: np.ndarray, rng: np.random.Generator, noise: float = 2.0) -> np.ndarray:
        """(H, W) uint8 view of the board at ``pose`` (4x4 board -> world, mm)."""
        import cv2

        # Board pose in camera coordinates.
        R = camera.R @ pose[:3, :3]
        t = camera.R @ pose[:3, 3] + camera.t
        n = R[:, 2]
        u0, v0, _, _ = self.board.extent_mm()
        acc = None
        for d in self._camera_rays(camera):
            s = (n @ t) / (d @ n)
            X = d * s[..., None] - t
            uv = X @ R[:, :2]  # board coordinates, mm
            mx = ((uv[..., 0] - u0 + self.margin_mm) * self.px_per_mm - 0.5).astype(np.float32)
            my = ((uv[..., 1] - v0 + self.margin_mm) * self.px_per_mm - 0.5).astype(np.float32)
            mx[s <= 0] = -1e6
            sample = cv2.remap(self.texture, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
            acc = sample if acc is None else acc + sample
        img = acc / 4
        out = np.where(img < 0, 0.25, 0.15 + 0.7 * img)  # dark surround, board lit
        out = cv2.GaussianBlur(out.astype(np.float32), (0, 0), 0.7) * 255 + rng.normal(0, noise, out.shape)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def write_json(path: str | os.PathLike[str], doc: dict) -> None:
    Path(path).write_text(json.dumps(doc, indent=1))


@dataclass(frozen=True)
class FootageSettings:
    """How :func:`write_footage` films the performance."""

    model: str = "fisheye"  # the cameras' lens model (:func:`hmc_rig`)
    size: tuple[int, int] = (1280, 1024)  # px
    seed: int = 0
    dot_noise_px: float = 0.3  # the paint's jitter of each dot's centre
    board_views: int = 15  # calibration board views per camera
    slip_deg: float = 1.0  # the helmet's slip on the head, largest turn
    slip_mm: float = 1.5  # and shift
    #: the rig flexed since its calibration: during the shot camera 1 is turned by this angle (the board views are
    #: rendered with the calibrated rig)
    flex_deg: float = 0.0
    contour_noise_px: float = 0.0  # Gaussian pixel noise of each lip contour point
    slip: str = "smooth"  # how the helmet moves on the head (:func:`helmet_slip`: smooth or jolts)


def write_footage(out: str | os.PathLike[str], actor, layout, activations: np.ndarray,
                  settings: FootageSettings | None = None, show_progress: bool = True) -> dict:
    """Render the performance (activations (F, C)) and board views into ``out`` (see the module docstring).

    ``helmet.csv`` gives the helmet dots in the calibration's frame, for ``lgi track --helmet``.
    ``lip_contours.csv`` gives the lips' inner contours as each camera sees them (:func:`contour_rows`).

    Returns a summary: the rig, the head motion and per-camera visibility counts.
    """
    import cv2

    st = settings or FootageSettings()
    model, size, seed, dot_noise_px, board_views = st.model, st.size, st.seed, st.dot_noise_px, st.board_views
    flex_deg, contour_noise_px = st.flex_deg, st.contour_noise_px
    out = Path(out)
    for sub in ("cam0", "cam1", "calib"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    rig = hmc_rig(model, size)
    shot_rig = rig
    if flex_deg:
        from scipy.spatial.transform import Rotation

        c1 = rig.cameras[1]
        turn = Rotation.from_rotvec(np.radians(flex_deg) * np.array([0.6, -0.64, 0.48])).as_matrix()
        shot_rig = StereoRig([rig.cameras[0], c1.with_pose(turn @ c1.R, turn @ c1.t)])  # about its own centre
    towards = 0.5 * (rig.cameras[0].center + rig.cameras[1].center)
    rng = np.random.default_rng(seed + 11)
    renderer = Renderer(actor.triangles, actor.neutral, layout.vertices, layout.weights, seed=seed)
    F, D = len(activations), len(layout)
    R, t, jolting = helmet_slip(F, seed, st.slip, st.slip_deg, st.slip_mm)
    centers = np.full((F, 2, D, 2), np.nan)
    visible = np.zeros((F, 2, D), bool)
    png = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    lips = actor.lip_contours()
    lip_ids = np.concatenate(list(lips.values()))
    contours = []
    contour_rng = np.random.default_rng(seed + 23)
    for f in progress(range(F), total=F, desc="HMC frames", disable=not show_progress):
        v = actor.evaluate(activations[f]) * MM_PER_CM @ R[f].T + t[f]
        for c, cam in enumerate(shot_rig.cameras):
            img, ctr, vis, seen = renderer.render(cam, v, rng, dot_noise_px, HELMET_MM, towards, v[lip_ids])
            centers[f, c], visible[f, c] = ctr, vis
            cv2.imwrite(str(out / f"cam{c}" / f"{f:06d}.png"), img, png)
            contours.append(contour_rows(f, c, cam, v, lips, seen, contour_noise_px, contour_rng))
    board = Board.parse("chessboard:9x6:12")
    br = BoardRenderer(board)
    for k, pose in enumerate(board_poses(rig, board, board_views, seed)):
        for c, side in enumerate(("left", "right")):
            cv2.imwrite(str(out / "calib" / f"{side}{k + 1:02d}.png"), br.render(rig.cameras[c], pose, rng), png)
    doc = calibration_json(rig)
    doc["board"] = board.spec()
    doc["head_frame"] = {"note": "the true cameras in the head (helmet) frame, mm", **rig.to_json()}
    doc["shot_head_frame"] = {"note": f"the cameras during the shot (camera 1 flexed by {flex_deg} deg)",
                              **shot_rig.to_json()}
    write_json(out / "cameras_true.json", doc)
    import pandas as pd

    hc = rig.cameras[0].to_camera(HELMET_MM)
    pd.DataFrame({"name": [f"helmet_{k + 1}" for k in range(len(hc))], "x": hc[:, 0], "y": hc[:, 1],
                  "z": hc[:, 2]}).to_csv(out / "helmet.csv", index=False)
    table = pd.concat(contours, ignore_index=True)
    table.to_csv(out / "lip_contours.csv", index=False, float_format="%.4f")

    save_npz(out / "truth.npz", head_rotation=R, head_translation=t, jolting=jolting, slip=np.asarray(st.slip),
             centers=centers.astype(np.float32), visible=visible, markers=np.asarray(layout.names),
             units=np.asarray("mm"))
    seen = {k: float(table[table.curve == k].shape[0] / (2 * F * len(ids))) for k, ids in lips.items()}
    return {"rig": rig, "shot_rig": shot_rig, "visible": visible, "frames": F, "board": board.spec(),
            "lip_contour_visible": seen}


def contour_rows(frame: int, camera: int, cam: Camera, vertices_mm: np.ndarray, lips: dict[str, np.ndarray],
                 seen: np.ndarray, noise_px: float, rng: np.random.Generator):
    """The rows of ``lip_contours.csv`` for one frame and camera: ``frame, camera, curve, point, x, y`` (px),
    the visible vertices of each lip edge (``lips``: curve name -> vertex ids in order; ``seen``: their
    visibility, concatenated) projected, numbered along the edge (a gap in ``point`` is a hidden stretch)."""
    import pandas as pd

    parts, k = [], 0
    for name, ids in lips.items():
        vis = seen[k:k + len(ids)]
        k += len(ids)
        uv = cam.project(vertices_mm[ids[vis]])
        if noise_px > 0:
            uv = uv + rng.normal(0.0, noise_px, uv.shape)
        parts.append(pd.DataFrame({"frame": frame, "camera": camera, "curve": name, "point": np.flatnonzero(vis),
                                   "x": uv[:, 0], "y": uv[:, 1]}))
    return pd.concat(parts, ignore_index=True)
