"""HMC footage to bundles: read the frames, detect dots, label and track, triangulate, stabilise.

Footage is a folder of frame pairs: ``cam0/`` and ``cam1/`` with the same file names, or
``left*``/``right*`` files; frames are taken in name order and numbered from 0. A frame missing from one
camera is an error (it would shift every later frame's number).
"""

from __future__ import annotations

import json
import logging
import os
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from lgi.capture.calibration import pair_images, read_gray
from lgi.capture.camera import StereoRig, triangulation_covariance
from lgi.capture.dots import DotOptions, Dots, detect_dots
from lgi.capture.headpose import JOINT, MIN_MARKERS, NONE, STABLE, HeadPoseSolver
from lgi.capture.headstab import stabilise_bundles
from lgi.capture.tracking import Tracker, TrackOptions, Tracks, thumbnail
from lgi.dataset.markers import read_layout
from lgi.errors import InputError
from lgi.index.build import LGIIndex
from lgi.io.csvio import read_table
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)


@dataclass
class ShotTracks:
    """Result of :func:`track_footage`: tracks in the world frame, bundles in the head frame (mm)."""

    names: list[str]
    frames: list[str]
    tracks: Tracks
    head: np.ndarray  # (F, M, 3) mm, head frame
    head_R: np.ndarray
    head_t: np.ndarray
    stable_weights: np.ndarray
    n_detections: np.ndarray  # (F, 2)
    seconds: dict[str, float]
    rig: StereoRig | None = None  # the rig the tracks were triangulated with (refined by helmet dots, if any)
    head_source: np.ndarray | None = None  # (F,) how each frame's pose was found (lgi.capture.headpose)
    head_rms_mm: np.ndarray | None = None  # (F,) the joint fit's inlier RMS, mm (NaN without it)
    # (F, M, 3, 3) mm^2, head frame: each bundle's covariance (head_covariance), NaN where ``head`` is NaN
    head_cov: np.ndarray | None = None


def head_covariance(X: np.ndarray, cameras, R: np.ndarray, pixel_noise: float) -> np.ndarray:
    """The covariance of each triangulated bundle in the head frame (mm^2).

    In the rig's frame, first-order propagation of ``pixel_noise`` (px per image coordinate) through both cameras'
    projections (:func:`lgi.capture.camera.triangulation_covariance`); then carried into the head frame like the
    positions (``x_h = R^T (x - t)``, so ``C_h = R^T C R``). Only triangulated bundles have one: the tracker fills
    no bundle by prediction (a marker not matched in both cameras is a gap, NaN, and so is its covariance), and a
    frame without a head pose has neither. The head pose's own error (shared by a frame's markers) is not in it.

    Parameters
    ----------
    X : (F, M, 3) mm, rig frame (NaN: not triangulated)
    cameras : the rig's cameras the points were triangulated with
    R : (F, 3, 3) head -> rig rotation per frame (NaN: no pose)
    pixel_noise : px

    Returns
    -------
    (F, M, 3, 3) float64, mm^2, head frame
    """
    C = np.einsum("fji,fmjk,fkl->fmil", R, triangulation_covariance(cameras, X, pixel_noise), R)
    return 0.5 * (C + np.swapaxes(C, -1, -2))  # symmetric to the last bit, as the file stores it


def _detect(path: Path, frame: int, size: tuple[int, int] | None, options: DotOptions) -> tuple[Dots, np.ndarray]:
    img = read_gray(path, frame)
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        raise InputError(f"image is {img.shape[1]}x{img.shape[0]}, the calibration is {size[0]}x{size[1]}",
                         path=path, frame=frame)
    return detect_dots(img, options), thumbnail(img)


def detect_footage(folder: str | os.PathLike[str], size: tuple[int, int] | None = None,
                   options: DotOptions | None = None, workers: int = 2
                   ) -> tuple[list[str], list[tuple[Dots, Dots]], np.ndarray]:
    """Detect the dots of every frame (images decoded and searched on ``workers`` threads).

    Returns the frame names, the detections of cameras 0 and 1 per frame, and the camera-0 thumbnails
    (F, P) float32.
    """
    pairs = pair_images(folder, strict=True)
    o = options or DotOptions()
    jobs = [(p, f, size, o) for f, (_, p0, p1) in enumerate(pairs) for p in (p0, p1)]
    with ThreadPoolExecutor(max_workers=workers) as pool:
        res = list(pool.map(lambda a: _detect(*a), jobs))
    dots = [(res[2 * f][0], res[2 * f + 1][0]) for f in range(len(pairs))]
    thumbs = np.stack([res[2 * f][1] for f in range(len(pairs))])
    return [n for n, _, _ in pairs], dots, thumbs


def read_labels(path: str | os.PathLike[str], names: list[str], dots: tuple[Dots, Dots],
                max_px: float = 3.0) -> np.ndarray:
    """Reference-frame labels from a CSV ``camera,x,y,marker`` (camera 0 or 1, pixels).

    Each labelled point takes the nearest detection within ``max_px``; a label with none is left out with a
    warning, unless most are (then the file is refused). Returns (M, 2, 2), NaN where unlabelled.
    """

    df = read_table(path, "label file", ("camera", "x", "y", "marker"), numeric=("camera", "x", "y"), key="marker")

    index = {n: i for i, n in enumerate(names)}
    uv = np.full((len(names), 2, 2), np.nan)
    misses = []
    for r, row in enumerate(df.itertuples(index=False), start=2):
        if row.marker not in index:
            raise InputError("unknown marker", path=path, line=r, marker=str(row.marker))
        if row.camera not in (0, 1):
            raise InputError(f"camera must be 0 or 1, not {row.camera:g}", path=path, line=r, marker=str(row.marker))
        xy = dots[int(row.camera)].xy
        d = np.linalg.norm(xy - [row.x, row.y], axis=1) if len(xy) else np.array([np.inf])
        if d.min() > max_px:
            misses.append(InputError(f"no dot detected within {max_px} px of ({row.x:g}, {row.y:g}) in camera "
                                     f"{int(row.camera)}", path=path, line=r, marker=str(row.marker)))
            continue
        uv[index[row.marker], int(row.camera)] = xy[int(np.argmin(d))]
    # A few labels on dots the detector missed are left to the tracker; most of them missing means the
    # labels are for another frame or another shot.
    if misses and len(misses) > 0.5 * len(df):
        raise InputError(f"{len(misses)} of {len(df)} labels have no detected dot near them (wrong reference frame "
                         f"or shot?); first: {misses[0]}", path=path)
    for m in misses:
        logging.getLogger(__name__).warning("%s (left unlabelled)", m)
    return uv


def read_helmet(path: str | os.PathLike[str]) -> np.ndarray:
    """Helmet marker positions (H, 3), mm in the calibration's frame, from a CSV ``name,x,y,z``."""
    df = read_table(path, "helmet marker file", ("name", "x", "y", "z"), numeric=("x", "y", "z"), key="name")
    pts = df[["x", "y", "z"]].to_numpy(np.float64)
    if len(pts) < 4:
        raise InputError(f"{len(pts)} helmet markers, at least 4 are needed", path=path)
    return pts


def refine_rig(rig: StereoRig, helmet: np.ndarray, dots: list[tuple[Dots, Dots]], gate_px: float = 15.0
               ) -> tuple[StereoRig, np.ndarray]:
    """Refine the rig's extrinsics from helmet markers seen in the shot.

    Each helmet marker takes, per frame and camera, the nearest detection to its projection through the
    calibrated rig (within ``gate_px``); the median over the frames is its observation.
    """
    obs = []
    for c, cam in enumerate(rig.cameras):
        pred = cam.project(helmet)
        per = np.full((len(dots), len(helmet), 2), np.nan)
        for f, pair in enumerate(dots):
            xy = pair[c].xy
            if len(xy) == 0:
                continue
            d = np.linalg.norm(pred[:, None] - xy[None], axis=2)
            j = np.argmin(d, axis=1)
            hit = d[np.arange(len(helmet)), j] <= gate_px
            per[f, hit] = xy[j[hit]]
        with warnings.catch_warnings():  # a marker never found is NaN, and counted below
            warnings.simplefilter("ignore", RuntimeWarning)
            obs.append(np.nanmedian(per, axis=0))
    for c in (0, 1):
        seen = int(np.isfinite(obs[c]).all(1).sum())
        if seen < 4:
            raise InputError(f"only {seen} of {len(helmet)} helmet markers were found in camera {c} within "
                             f"{gate_px:g} px of where the calibration projects them (at least 4 are needed): the "
                             "calibration is too far off, or the helmet file is not this rig's")
    refined, rms = rig.refine_with_points(helmet, obs[0], obs[1])
    after = rms[:, 1]
    if not np.all(np.isfinite(after)) or np.any(after > np.maximum(5.0, 2.0 * rms[:, 0])):
        raise InputError("refining the rig from the helmet markers failed (reprojection RMS per camera "
                         f"{rms[0, 0]:.2f}/{rms[1, 0]:.2f} px before, {after[0]:.2f}/{after[1]:.2f} px after): the "
                         "calibration is too far off for them; re-calibrate, or track without --helmet")
    return refined, rms


def track_footage(folder: str | os.PathLike[str], rig: StereoRig, layout_mm: np.ndarray, names: list[str],
                  labels: str | os.PathLike[str] | None = None, reference: int = 0,
                  options: TrackOptions | None = None, dot_options: DotOptions | None = None,
                  workers: int = 2, helmet: np.ndarray | None = None, pose_model=None) -> ShotTracks:
    """Footage -> labelled tracks -> triangulated, head-stabilised bundles (mm). See :mod:`lgi.capture.tracking`.

    With ``helmet`` (H, 3) marker positions (mm, calibration frame), the rig's extrinsics are first
    refined from those markers as seen in this shot (:func:`refine_rig`). With ``pose_model`` (a
    :class:`~lgi.capture.headpose.HeadPoseSolver` and, per tracked marker, its row in the model or -1), each
    frame's head pose is solved with the face, starting from the stable-marker pose.
    """
    t0 = time.perf_counter()
    frames, dots, thumbs = detect_footage(folder, rig.cameras[0].size, dot_options, workers)
    if helmet is not None:
        try:
            rig, _ = refine_rig(rig, helmet, dots)
        except InputError:
            raise  # says what is wrong with the helmet markers itself
        except ValueError as e:
            raise InputError(f"helmet markers: {e}", path=folder) from e
    t1 = time.perf_counter()
    if not 0 <= reference < len(frames):
        raise InputError(f"reference frame {reference} is outside the shot (0-{len(frames) - 1})", path=folder)
    tracker = Tracker(rig, layout_mm, names, options)
    ref_uv = read_labels(labels, names, dots[reference]) if labels else None
    try:
        tracks = tracker.track(dots, thumbs, reference, ref_uv)
    except ValueError as e:
        raise InputError(str(e), path=folder, frame=reference) from e
    t2 = time.perf_counter()
    head, R, t, w = stabilise_bundles(tracks.X, layout_mm)
    source = rms = None
    if pose_model is not None:
        solver, rows = pose_model
        X = np.full((len(frames), solver.n_markers, 3), np.nan)
        known = rows >= 0
        X[:, rows[known]] = tracks.X[:, known]
        from lgi.capture.headpose import triangulation_information

        poses = solver.solve(X, R, t, triangulation_information(X, rig.cameras))
        R, t, source, rms = poses.R, poses.t, poses.source, poses.rms_mm
        head = np.einsum("fmi,fij->fmj", tracks.X - t[:, None], R)  # R^T (x - t)
    cov = head_covariance(tracks.X, rig.cameras, R, tracker.o.pixel_noise_px)
    cov[~np.all(np.isfinite(head), axis=2)] = np.nan
    t3 = time.perf_counter()
    n_det = np.array([[len(d0), len(d1)] for d0, d1 in dots])
    return ShotTracks(names, frames, tracks, head, R, t, w, n_det,
                      {"detect": t1 - t0, "track": t2 - t1, "stabilise": t3 - t2}, rig, source, rms, cov)


#: Parquet schema metadata key of the tracks table: the rig the tracks were triangulated with (JSON).
RIG_METADATA = b"lgi.rig"
HEAD_POSE_COLUMNS = ["head_qx", "head_qy", "head_qz", "head_qw", "head_tx", "head_ty", "head_tz"]


def tracks_table(shot: ShotTracks) -> pd.DataFrame:
    """Long table of every 2D observation: frame, marker, camera, x, y, reprojection error (px),
    source (forward/backward/anchor), triangulated (False: seen by this camera only), and the frame's head
    pose that stabilised the bundles: ``head_qx..qw`` (unit quaternion) and ``head_tx..tz`` (mm), mapping the
    head frame (the bundles') to the rig's frame (NaN where the frame had too few markers to fit it), with
    ``head_pose`` saying how it was found (``joint``: with the face, ``stable markers``, ``none``) and
    ``head_pose_rms_mm`` the joint fit's residual (NaN without it)."""
    tr = shot.tracks
    f, m, c = np.nonzero(np.isfinite(tr.uv[..., 0]))
    src = np.array(["none", "forward", "backward", "anchor"])
    ok = np.all(np.isfinite(shot.head_R), axis=(1, 2))
    quat = np.full((len(shot.head_R), 4), np.nan)
    if ok.any():
        quat[ok] = Rotation.from_matrix(shot.head_R[ok]).as_quat()
    pose = np.column_stack([quat, shot.head_t])[f]
    how = shot.head_source if shot.head_source is not None else np.where(ok, "stable markers", "none")
    how = np.asarray(how, dtype=object)
    pose_rms = shot.head_rms_mm if shot.head_rms_mm is not None else np.full(len(ok), np.nan)
    return pd.DataFrame({
        "frame": f.astype(np.int64), "marker": np.asarray(shot.names)[m], "camera": c.astype(np.int8),
        "x": tr.uv[f, m, c, 0], "y": tr.uv[f, m, c, 1], "reprojection_px": tr.error[f, m, c],
        "source": src[tr.source[f, m, c]], "triangulated": np.isfinite(tr.X[f, m, 0]),
        **{name: pose[:, k] for k, name in enumerate(HEAD_POSE_COLUMNS)},
        "head_pose": how[f], "head_pose_rms_mm": pose_rms[f],
    })


def write_tracks_table(path: str | os.PathLike[str], shot: ShotTracks) -> None:
    """Write :func:`tracks_table` as Parquet, with the rig it was triangulated with in the schema metadata
    (:data:`RIG_METADATA`), so the observations can be turned into rays later without the calibration file."""

    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(tracks_table(shot), preserve_index=False)
    if shot.rig is not None:
        meta = dict(table.schema.metadata or {})
        meta[RIG_METADATA] = json.dumps(shot.rig.to_json()).encode()
        table = table.replace_schema_metadata(meta)
    pq.write_table(table, str(path))


def neutral_layout(markers: str | os.PathLike[str], dataset: str | os.PathLike[str] | None = None,
                   units: str = "cm") -> tuple[list[str], np.ndarray, str]:
    """Marker names, neutral positions (M, 3) and their units: from ``dataset``'s neutral if given, else the
    marker file's ``x, y, z`` columns (in ``units``)."""
    if dataset:
        from lgi.dataset.shapes import ShapeDataset

        ds = ShapeDataset.load(dataset)
        layout = read_layout(markers, ds.triangles)
        return layout.names, layout.evaluate(ds.neutral[None].astype(np.float64))[0], ds.units

    layout = read_layout(markers)
    head = read_table(markers, "marker file", ("name",), need_rows=False)
    if not {"x", "y", "z"} <= set(head.columns):
        raise InputError("the marker file has no neutral positions (x, y, z): pass a dataset", path=markers)
    df = read_table(markers, "marker file", ("name", "x", "y", "z"), numeric=("x", "y", "z"), key="name")
    return layout.names, df[["x", "y", "z"]].to_numpy(np.float64), units


def head_pose_model(index: str | os.PathLike[str], names: list[str], neutral_mm: np.ndarray,
                    markers: str | os.PathLike[str]):
    """The joint head-pose solver of an index and, per tracked marker, its row in the index (-1: not in it);
    with the tracking layout's neutral positions replaced by the index's (the head frame the bundles are
    written in, mm) where the index has the marker."""
    idx = LGIIndex.load(index)
    where = {n: k for k, n in enumerate(idx.marker_names)}
    rows = np.array([where.get(n, -1) for n in names], np.int64)
    if (rows >= 0).sum() < MIN_MARKERS:
        raise InputError(f"only {(rows >= 0).sum()} of the marker file's {len(names)} markers are in the index "
                         f"(at least {MIN_MARKERS} are needed to solve the head pose with the face): is it this "
                         "actor's index and layout?", path=markers)
    missing = [n for n, r in zip(names, rows, strict=True) if r < 0]
    if missing:
        log.warning(
            "%d markers are not in the index and do not inform the head pose: %s", len(missing),
            ", ".join(missing[:10]) + (" ..." if len(missing) > 10 else ""))
    neutral_mm = neutral_mm.copy()
    neutral_mm[rows >= 0] = idx.arrays["ptab"][0][rows[rows >= 0]] * MM_PER_CM
    return (HeadPoseSolver.from_index(idx), rows), neutral_mm


def bundle_precision(cov_mm2: np.ndarray) -> dict:
    """The bundles' median standard deviation along their covariance's long axis (the depth) and across it (mm),
    for the summary (NaN without any bundle)."""
    ok = np.all(np.isfinite(cov_mm2), axis=(-2, -1))
    if not ok.any():
        return {"bundle_std_depth_mm": float("nan"), "bundle_std_across_mm": float("nan")}
    w = np.sqrt(np.clip(np.linalg.eigvalsh(cov_mm2[ok]), 0, None))
    return {"bundle_std_depth_mm": float(np.median(w[:, 2])), "bundle_std_across_mm": float(np.median(w[:, :2]))}


def head_pose_counts(shot: ShotTracks) -> dict:
    """Frames per head-pose source and the joint fit's median residual (mm), for the summary."""
    ok = np.all(np.isfinite(shot.head_R), axis=(1, 2))
    how = shot.head_source if shot.head_source is not None else np.where(ok, STABLE, NONE)
    rms = shot.head_rms_mm if shot.head_rms_mm is not None else np.full(len(ok), np.nan)
    joint = np.asarray(how) == JOINT
    return {"joint": int(joint.sum()), "stable": int((np.asarray(how) == STABLE).sum()),
            "none": int((np.asarray(how) == NONE).sum()),
            "joint_rms_median_mm": float(np.median(rms[joint])) if joint.any() else float("nan")}
