"""Markers seen by one camera: their 2D observations as rays in the head frame, and bundles on those rays.

``lgi track`` keeps every 2D observation in its tracks table, with the head pose that stabilised each frame
and the rig it triangulated with (:func:`lgi.capture.footage.write_tracks_table`). A marker seen by only one
camera in a frame has no bundle, but it is not unknown: its surface point lies on the viewing ray through
the observation. :func:`read_rays` turns those observations into rays in the bundles' frame (head frame,
cm); :func:`points_on_rays` places each such marker on its ray at the depth a reconstruction without it
gives (the ray's closest point to that surface point), so a second reconstruction passes through it
(:func:`lgi.jobs.reconstruct.reconstruct`). The ray fixes the two directions across it; the depth along it
comes from the surrounding surface, not from interpolating the marker over time.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lgi.capture.camera import StereoRig
from lgi.errors import InputError, cell_text
from lgi.io.csvio import read_table
from lgi.solve.contours import CURVES
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

NEEDED = ("frame", "marker", "camera", "x", "y", "triangulated")


@dataclass
class Rays:
    """Viewing rays of markers seen by one camera, in the bundles' frame.

    Attributes
    ----------
    frame : (R,) int64
        Row of the shot (index into its frames, not the frame number).
    marker : (R,) int64
        Marker, in the index's layout order.
    camera : (R,) int8
    pixel : (R, 2) float64, pixels
    origin : (R, 3) float64, cm
        The camera centre in the head frame of that frame.
    direction : (R, 3) float64
        Unit viewing direction through the observation, head frame.
    """

    frame: np.ndarray
    marker: np.ndarray
    camera: np.ndarray
    pixel: np.ndarray
    origin: np.ndarray
    direction: np.ndarray

    def __len__(self) -> int:
        return len(self.frame)

    def mask(self, n_frames: int, n_markers: int) -> np.ndarray:
        """(F, M) bool: where a ray stands for the marker."""
        out = np.zeros((n_frames, n_markers), bool)
        out[self.frame, self.marker] = True
        return out

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(R,) distance (cm) of points (R, 3), cm, from their rays."""
        v = points - self.origin
        along = np.einsum("ij,ij->i", v, self.direction)
        return np.linalg.norm(v - along[:, None] * self.direction, axis=1)


def read_rig(path: str | os.PathLike[str], calib: str | os.PathLike[str] | None = None):
    """The rig to turn a tracks table's pixels into rays: the one stored in the table by ``lgi track`` (the rig
    it triangulated with, refined by helmet dots if it was), or ``calib``. Given both, ``calib`` is used and a
    warning says the two differ, if they do."""
    import pyarrow.parquet as pq

    from lgi.capture.footage import RIG_METADATA

    try:
        meta = pq.read_schema(str(path)).metadata or {}
    except (OSError, ValueError) as e:
        raise InputError(f"not a readable Parquet tracks table ({e})", path=path) from None
    stored = None
    if RIG_METADATA in meta:
        try:
            stored = StereoRig.from_calibration(json.loads(meta[RIG_METADATA]), path)
        except json.JSONDecodeError as e:
            raise InputError(f"the rig stored in the tracks table is not JSON: {e}", path=path) from None
    if calib is None:
        if stored is None:
            raise InputError("the tracks table holds no rig (it was not written by this lgi track): pass --calib",
                             path=path)
        return stored
    rig = StereoRig.load(calib)
    if stored is not None:
        differ = max(float(np.abs(a.K - b.K).max() + np.abs(a.R - b.R).max() + np.abs(a.t - b.t).max())
                     for a, b in zip(rig.cameras, stored.cameras, strict=True))
        if differ > 1e-6:
            log.warning("%s: the rig the tracks were triangulated with (refined by helmet dots?) differs from %s; "
                        "using %s as asked: rays and bundles may disagree", path, calib, calib)
    return rig


def read_rays(path: str | os.PathLike[str], marker_names: list[str], frames: np.ndarray,
              seen: np.ndarray, calib: str | os.PathLike[str] | None = None) -> Rays:
    """Rays of the observations in a tracks table that stand alone: a marker seen by exactly one camera in a
    frame where the shot has no bundle for it.

    Parameters
    ----------
    path : path
        The tracks table (Parquet) ``lgi track`` wrote.
    marker_names : list of str, length M
        The index's markers.
    frames : (F,) int
        The shot's frame numbers.
    seen : (F, M) bool
        Where the shot has a bundle (those keep it; their observations add nothing).
    calib : path, optional
        Calibration to use instead of the rig stored in the table (:func:`read_rig`).

    Returns
    -------
    Rays
        In the shot's head frame, cm. Frames of the table outside the shot, and frames whose head pose is
        unknown, give no rays (a warning counts them).
    """
    from scipy.spatial.transform import Rotation

    from lgi.capture.footage import HEAD_POSE_COLUMNS

    path = Path(path)
    rig = read_rig(path, calib)
    try:
        df = pd.read_parquet(path)
    except (OSError, ValueError) as e:
        raise InputError(f"not a readable Parquet tracks table ({e})", path=path) from None
    missing = [c for c in NEEDED if c not in df.columns]
    if missing:
        raise InputError(f"missing columns {missing} (a tracks table from lgi track has {list(NEEDED)})", path=path)
    if not set(HEAD_POSE_COLUMNS) <= set(df.columns):
        raise InputError("the tracks table has no head pose columns (head_qx..head_tz): it was written by an "
                         "older lgi track; track the footage again", path=path)

    def bad(r: int, why: str) -> InputError:
        return InputError(why, path=f"{path} (row {r})", frame=_int_or_none(df["frame"].iloc[r]),
                          marker=str(df["marker"].iloc[r]))

    for col in ("frame", "camera", "x", "y", *HEAD_POSE_COLUMNS):
        v = pd.to_numeric(df[col], errors="coerce").to_numpy(np.float64)
        text = pd.isna(v) & df[col].notna().to_numpy()
        if text.any():
            r = int(np.flatnonzero(text)[0])
            raise bad(r, f"{col} is not a number ({cell_text(df[col].iloc[r])})")
        if col in ("frame", "camera", "x", "y"):
            wrong = ~np.isfinite(v) | ((v != np.round(v)) if col in ("frame", "camera") else False)
            if col == "camera":
                wrong |= ~np.isin(v, (0, 1))
            if np.any(wrong):
                r = int(np.flatnonzero(wrong)[0])
                what = {"frame": "a whole number", "camera": "0 or 1", "x": "a finite pixel coordinate",
                        "y": "a finite pixel coordinate"}[col]
                raise bad(r, f"{col} must be {what}, not {cell_text(df[col].iloc[r])}")
    name_of = {n: i for i, n in enumerate(marker_names)}
    marker = df["marker"].map(name_of)
    if marker.isna().any():
        r = int(np.flatnonzero(marker.isna().to_numpy())[0])
        raise bad(r, "unknown marker name (not in the index's layout)")
    key = df[["frame", "marker", "camera"]].duplicated()
    if key.any():
        r = int(np.flatnonzero(key.to_numpy())[0])
        raise bad(r, "a second observation of this marker by this camera in this frame")
    row_of = {int(f): k for k, f in enumerate(np.asarray(frames))}
    f_row = df["frame"].map(lambda f: row_of.get(int(f), -1)).to_numpy(np.int64)
    m = marker.to_numpy(np.int64)
    cams = df["camera"].to_numpy(np.int64)
    tri = df["triangulated"].astype(bool).to_numpy()
    n_cam = df.groupby(["frame", "marker"])["camera"].transform("size").to_numpy()
    alone = (n_cam == 1) & ~tri
    outside = alone & (f_row < 0)
    alone &= f_row >= 0
    alone[alone] &= ~seen[f_row[alone], m[alone]]
    pose = df[HEAD_POSE_COLUMNS].to_numpy(np.float64)
    no_pose = alone & ~np.all(np.isfinite(pose), axis=1)
    if no_pose.any() or outside.any():
        log.warning("%s: %d one-camera observations in frames outside the shot and %d in frames without a head "
                    "pose give no rays", path, int(outside.sum()), int(no_pose.sum()))
    alone &= ~no_pose
    q = pose[alone, :4]
    norm = np.linalg.norm(q, axis=1)
    if np.any(np.abs(norm - 1) > 1e-3):
        r = int(np.flatnonzero(alone)[np.flatnonzero(np.abs(norm - 1) > 1e-3)[0]])
        raise bad(r, f"the head pose quaternion is not a unit quaternion (norm {norm.max():.4f})")
    R = Rotation.from_quat(q).as_matrix() if len(q) else np.zeros((0, 3, 3))
    t = pose[alone, 4:]
    uv = df[["x", "y"]].to_numpy(np.float64)[alone]
    c = cams[alone]
    origin = np.zeros((len(c), 3))
    direction = np.zeros((len(c), 3))
    for k, cam in enumerate(rig.cameras):
        sel = c == k
        if sel.any():
            d_world = cam.rays(uv[sel]) @ cam.R  # camera -> rig frame: R^T d, row-wise
            origin[sel] = np.einsum("nji,nj->ni", R[sel], cam.center - t[sel])  # head frame: R^T (x - t)
            direction[sel] = np.einsum("nji,nj->ni", R[sel], d_world)
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return Rays(f_row[alone], m[alone], c.astype(np.int8), uv, origin / MM_PER_CM, direction)


def points_on_rays(rays: Rays, surface: np.ndarray) -> np.ndarray:
    """Each ray's point closest to a surface point: (R, 3), cm.

    Parameters
    ----------
    rays : Rays
    surface : (R, 3) float, cm
        The marker's surface point in a reconstruction without it (the depth to take along the ray).
    """
    along = np.einsum("ij,ij->i", surface - rays.origin, rays.direction)
    return rays.origin + np.maximum(along, 0.0)[:, None] * rays.direction


def _int_or_none(v) -> int | None:
    try:
        return int(v)
    except (TypeError, ValueError):
        return None


def read_head_poses(path: str | os.PathLike[str], frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each shot frame's head pose from a tracks table: R (F, 3, 3) head -> rig frame and t (F, 3) mm (NaN for
    frames the table does not cover or could not stabilise)."""
    from scipy.spatial.transform import Rotation

    from lgi.capture.footage import HEAD_POSE_COLUMNS

    df = pd.read_parquet(path, columns=["frame", *HEAD_POSE_COLUMNS]).drop_duplicates("frame")
    R = np.full((len(frames), 3, 3), np.nan)
    t = np.full((len(frames), 3), np.nan)
    row = {int(f): k for k, f in enumerate(np.asarray(frames))}
    for fr, *pose in df.itertuples(index=False):
        k = row.get(int(fr))
        if k is not None and np.all(np.isfinite(pose)):
            R[k] = Rotation.from_quat(pose[:4]).as_matrix()
            t[k] = pose[4:]
    return R, t


CONTOUR_COLUMNS = ("frame", "camera", "curve", "point", "x", "y")


def read_contours(path: str | os.PathLike[str], frames: np.ndarray) -> dict[int, list[tuple[int, str, np.ndarray]]]:
    """A lip contours table (CSV: ``frame, camera, curve, point, x, y``, pixels; ``curve`` one of
    :data:`lgi.solve.contours.CURVES`): per shot row, its (camera, curve, (P, 2) points in ``point`` order).

    Refused, naming the line: text or non-finite numbers, a camera other than 0 or 1, an unknown curve, a
    repeated point. Frames outside the shot are left out with a warning; a curve of one point is left out."""
    df = read_table(path, "lip contours file", CONTOUR_COLUMNS, numeric=("frame", "camera", "point", "x", "y"))

    def bad(r: int, why: str) -> InputError:
        return InputError(why, path=path, line=r + 2, frame=_int_or_none(df["frame"].iloc[r]))

    for col in ("frame", "camera", "point"):
        v = df[col].to_numpy()
        wrong = v != np.round(v)
        if col == "camera":
            wrong |= ~np.isin(v, (0, 1))
        if wrong.any():
            r = int(np.flatnonzero(wrong)[0])
            raise bad(r, f"{col} must be {'0 or 1' if col == 'camera' else 'a whole number'}, not "
                         f"{cell_text(df[col].iloc[r])}")
    unknown = ~df["curve"].isin(CURVES).to_numpy()
    if unknown.any():
        r = int(np.flatnonzero(unknown)[0])
        raise bad(r, f"unknown curve {df['curve'].iloc[r]!r} (expected one of {', '.join(CURVES)})")
    dup = df.duplicated(["frame", "camera", "curve", "point"]).to_numpy()
    if dup.any():
        r = int(np.flatnonzero(dup)[0])
        raise bad(r, "a second row for this frame, camera, curve and point")
    row = {int(f): k for k, f in enumerate(np.asarray(frames))}
    out: dict[int, list[tuple[int, str, np.ndarray]]] = {}
    outside = 0
    for (fr, cam, curve), g in df.groupby(["frame", "camera", "curve"], sort=True):
        k = row.get(int(fr))
        if k is None:
            outside += 1
            continue
        g = g.sort_values("point")
        if len(g) >= 2:
            out.setdefault(k, []).append((int(cam), str(curve), g[["x", "y"]].to_numpy(np.float64)))
    if outside:
        log.warning("%s: %d traced curves are in frames outside the shot: left out", path, outside)
    if not out:
        raise InputError("no traced curve of two points or more falls in the shot's frames", path=path)
    return out
