"""The capture jobs: ``lgi calibrate`` (a stereo pair from board images) and ``lgi track`` (stereo footage to
bundles and a 2D tracks table)."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from lgi.capture.settings import DOT_SIZE_PX, GATE_PX, PIXEL_NOISE_PX
from lgi.errors import InputError
from lgi.options import REQUIRED, declared, option

log = logging.getLogger(__name__)

#: Median reprojection error (px) above which a shot's calibration is suspect.
MOVED_RIG_PX = 0.5


@declared
@dataclass(frozen=True)
class CalibrateOptions:
    """Options of ``lgi calibrate`` (:mod:`lgi.options`); ``board`` as :meth:`lgi.capture.calibration.Board.parse`
    reads it."""

    board: str = option(
        REQUIRED, "chessboard:COLSxROWS:SQUARE_MM (inner corners) or charuco:COLSxROWS:SQUARE_MM:MARKER_MM:DICT "
        "(squares; e.g. charuco:7x5:15:11:DICT_5X5_100)", group="inputs", metavar="BOARD")
    rational: bool = option(False, "OpenCV's rational distortion model (wide lenses)", group="lens model")
    fisheye: bool = option(False, "fisheye (equidistant) lens model", group="lens model")
    yaml: str | None = option(None, "also write OpenCV YAML (K0, dist0, K1, dist1, R, T)", group="outputs",
                              metavar="FILE")

    def __post_init__(self) -> None:
        from lgi.capture.calibration import Board

        Board.parse(self.board)
        if self.rational and self.fisheye:
            raise InputError("--rational and --fisheye are two lens models: choose one")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def calibrate(images_dir: str | Path, out: str | Path, options: CalibrateOptions) -> dict[str, Any]:
    """``lgi calibrate``: detect the board, calibrate both cameras and the pair; write the JSON (and YAML)."""
    from lgi.capture.calibration import Board, calibrate_stereo
    from lgi.io.atomic import IMAGES, check_distinct, check_output, files_in

    o = options
    check_distinct({"--out": out, "--yaml": o.yaml})
    for path in (out, o.yaml):
        if path:
            check_output(path, "file", inputs=[images_dir, *files_in(images_dir, IMAGES)])
    calib = calibrate_stereo(images_dir, Board.parse(o.board), rational=o.rational, fisheye=o.fisheye)
    calib.save(out, o.yaml)
    return {"path": str(Path(out).resolve()), "yaml": str(Path(o.yaml).resolve()) if o.yaml else None,
            "views": len(calib.used), "image_size": list(calib.image_size), "model": calib.model,
            "rms_camera_px": [float(v) for v in calib.rms_camera], "rms_stereo_px": float(calib.rms_stereo),
            "baseline_mm": float(calib.baseline_mm),
            "per_view_px": {k: [float(a), float(b)] for k, (a, b) in calib.per_view.items()},
            "rejected": dict(calib.rejected)}


def calibrate_report(s: dict[str, Any]) -> list[str]:
    lines = [f"stereo calibration from {s['views']} image pairs ({s['image_size'][0]}x{s['image_size'][1]}, "
             f"{s['model']}): RMS left {s['rms_camera_px'][0]:.3f} px, right {s['rms_camera_px'][1]:.3f} px, "
             f"stereo {s['rms_stereo_px']:.3f} px; baseline {s['baseline_mm']:.3f} mm"]
    lines += [f"  {name}: {el:.3f} / {er:.3f} px" for name, (el, er) in s["per_view_px"].items()]
    lines += [f"  rejected {name}: {why}" for name, why in s["rejected"].items()]
    lines.append(f"calibration: {s['path']}" + (f", {s['yaml']}" if s["yaml"] else ""))
    return lines


@declared
@dataclass(frozen=True)
class TrackFootageOptions:
    """Options of ``lgi track`` (:mod:`lgi.options`)."""

    tracks: str | None = option(None, "2D tracks table (default: OUT's stem + .tracks.parquet)", group="outputs",
                                metavar="PARQUET")
    dataset: str | None = option(None, "dataset whose neutral places the markers (and sets the units)",
                                 group="inputs", metavar="DIR")
    units: str = option(
        "cm", "units of the marker file's positions without --dataset (default %(default)s); the bundles are written "
        "in cm, as datasets are stored", group="inputs", choices=("mm", "cm", "m"))
    labels: str | None = option(None, "labels of the reference frame's dots: camera,x,y,marker (px) (default: "
                                "fitted)", group="inputs", metavar="CSV")
    reference_frame: int = option(0, "frame to label (default %(default)s)", group="tracking", metavar="F")
    helmet: str | None = option(
        None, "markers fixed on the helmet (name,x,y,z in mm, calibration frame): refine the extrinsics for this "
        "shot from them", group="inputs", metavar="CSV")
    gate: float = option(GATE_PX, "tracking search radius, px (default %(default)s)", group="tracking", metavar="PX",
                         units="px")
    dot_size: float = option(
        DOT_SIZE_PX, "typical painted dot diameter in the images, px: sets the detector's scale (default %(default)s)",
        group="tracking", metavar="PX", units="px")
    index: str | None = option(
        None, "the actor's LGI index (lgi build): solve each frame's head pose with the face (the jaw and the shape "
        "weights) instead of assuming the least-moving markers rigid; the bundles are then in the index's head "
        "frame (default: none, the stable-marker fit)", group="inputs", metavar="INDEX_DIR")
    pixel_noise: float = option(
        PIXEL_NOISE_PX, "the dot detector's centre error per image coordinate, px (one standard deviation): sets each "
        "bundle's covariance, written as the bundles file's cov_* columns (cm^2, head frame); the default was "
        "measured on lgi synth --hmc footage (default %(default)s)", group="tracking", metavar="PX", units="px")

    def __post_init__(self) -> None:
        from lgi.units import check_units

        check_units(self.units, "--units")
        for name in ("gate", "dot_size", "pixel_noise"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise InputError(f"--{name.replace('_', '-')} must be a positive number of px, not {v!r}")
        if isinstance(self.reference_frame, bool) or not isinstance(self.reference_frame, int) or \
                self.reference_frame < 0:
            raise InputError(f"--reference-frame must be a frame number >= 0, not {self.reference_frame!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def track(footage_dir: str | Path, calib: str | Path, markers: str | Path, out: str | Path,
          options: TrackFootageOptions | None = None) -> dict[str, Any]:
    """``lgi track``: footage to the bundles file (cm, with each bundle's covariance) and the 2D tracks table;
    returns the summary of :func:`track_shot`. A median reprojection error above
    :data:`MOVED_RIG_PX` is logged as a warning (the rig may have moved since its calibration) and flagged in the
    summary. The outputs are checked first (:func:`track_shot` does not)."""
    from lgi.io.atomic import IMAGES, check_distinct, check_output, files_in

    o = options or TrackFootageOptions()
    out = Path(out)
    tracks = o.tracks or out.with_name(out.stem + ".tracks.parquet")
    check_distinct({"--out": out, "--tracks": tracks})
    for path in (out, tracks):
        check_output(path, "file", inputs=[footage_dir, calib, markers, o.dataset, o.labels, o.helmet, o.index,
                                           *files_in(footage_dir, IMAGES, recursive=True)])
    _, r = track_shot(footage_dir, calib, markers, out, o)
    r["rig_may_have_moved"] = bool(r["reprojection_median_px"] > MOVED_RIG_PX)
    r["helmet"] = bool(o.helmet)
    if r["rig_may_have_moved"]:
        log.warning("the median reprojection error is %.2f px: the rig may have moved since its calibration%s",
                    r["reprojection_median_px"],
                    "" if o.helmet else " (pass --helmet to refine it from the helmet markers)")
    return r


def track_shot(footage_dir: str | Path, calib: str | Path, markers: str | Path, out: str | Path,
               options: TrackFootageOptions | None = None):
    """Footage to the bundles file ``out`` (cm, the library's unit, whatever ``units`` the marker file's positions
    are in) and the 2D tracks table (Parquet). With ``options.index`` (the actor's LGI index), the head pose is
    solved with the face (:mod:`lgi.capture.headpose`) and the layout's neutral positions are the index's. The
    bundles file carries each bundle's covariance (``cov_*`` columns, cm^2, head frame:
    :func:`lgi.capture.footage.head_covariance` with ``options.pixel_noise`` px).

    Returns the tracks (:class:`lgi.capture.footage.ShotTracks`) and a summary (counts, reprojection error,
    anchors, rejections, speed, paths).
    """
    import time

    import numpy as np

    from lgi.capture.bundles import Bundles, write_bundles
    from lgi.capture.camera import StereoRig
    from lgi.capture.dots import DotOptions
    from lgi.capture.footage import (
        bundle_precision,
        head_pose_counts,
        head_pose_model,
        neutral_layout,
        read_helmet,
        track_footage,
        write_tracks_table,
    )
    from lgi.capture.tracking import TrackOptions
    from lgi.io.atomic import atomic_file
    from lgi.units import MM_PER_CM, check_units

    o = options or TrackFootageOptions()
    rig = StereoRig.load(calib)
    names, neutral, units = neutral_layout(markers, o.dataset, o.units)
    neutral_mm = neutral * check_units(units, "--units") * MM_PER_CM  # the cameras are calibrated in mm
    pose_model = None
    if o.index is not None:
        pose_model, neutral_mm = head_pose_model(o.index, names, neutral_mm, markers)
    t0 = time.perf_counter()
    shot = track_footage(footage_dir, rig, neutral_mm, names, labels=o.labels, reference=o.reference_frame,
                         options=TrackOptions(gate_px=o.gate, pixel_noise_px=o.pixel_noise),
                         helmet=read_helmet(o.helmet) if o.helmet else None,
                         dot_options=DotOptions.for_size(o.dot_size), pose_model=pose_model)
    dt = time.perf_counter() - t0
    out = Path(out)
    tracks_out = Path(o.tracks) if o.tracks else out.with_name(out.stem + ".tracks.parquet")
    F, M = shot.head.shape[:2]
    with atomic_file(tracks_out) as tmp:
        write_tracks_table(tmp, shot)
    try:
        write_bundles(out, Bundles(frames=np.arange(F), markers=names, positions=shot.head / MM_PER_CM,
                                   covariance=shot.head_cov / MM_PER_CM**2))
    except BaseException:
        tracks_out.unlink(missing_ok=True)  # the two files go together, or neither is left
        raise
    tr = shot.tracks
    err = tr.error[np.isfinite(tr.error)]
    summary = {
        "frames": F, "markers": M, "triangulated_share": float(np.isfinite(shot.head[..., 0]).mean()),
        "one_camera_observations": int((np.isfinite(tr.uv[..., 0]).sum(axis=2) == 1).sum()),
        "anchors": len(tr.anchors), "reprojection_median_px": float(np.median(err)) if len(err) else float("nan"),
        "reprojection_p95_px": float(np.percentile(err, 95)) if len(err) else float("nan"),
        "rejected_epipolar": int((tr.rejected == 1).sum()), "rejected_neighbour": int((tr.rejected == 2).sum()),
        "stable_markers": [n for n, w in zip(names, shot.stable_weights, strict=True) if w > 0.5],
        "frames_per_second": F / dt, "seconds": shot.seconds, "units": "cm",
        "head_pose": head_pose_counts(shot), "pixel_noise_px": float(o.pixel_noise), **bundle_precision(shot.head_cov),
        "bundles": str(out.resolve()), "tracks": str(tracks_out.resolve()),
    }
    return shot, summary


def track_report(r: dict[str, Any]) -> list[str]:
    sec = r["seconds"]
    return [f"{r['frames']} frames x {r['markers']} markers: {r['triangulated_share']:.1%} triangulated, "
            f"{r['one_camera_observations']} observations in one camera only (kept in the tracks table), "
            f"{r['anchors']} anchor frames",
            f"reprojection error: median {r['reprojection_median_px']:.3f} px, p95 {r['reprojection_p95_px']:.3f} px; "
            f"rejected {r['rejected_epipolar']} epipolar, {r['rejected_neighbour']} neighbour inconsistencies",
            f"stable markers for head stabilisation: {', '.join(r['stable_markers'])}",
            head_pose_line(r["head_pose"]),
            f"bundle covariance (pixel noise {r['pixel_noise_px']:g} px): median std {r['bundle_std_depth_mm']:.3f} mm "
            f"along the rays, {r['bundle_std_across_mm']:.3f} mm across (cov_* columns, cm^2)",
            f"{r['frames_per_second']:.1f} frames/s (detect {sec['detect']:.2f} s, track {sec['track']:.2f} s, "
            f"stabilise {sec['stabilise']:.2f} s)",
            f"bundles ({r['units']}): {r['bundles']}", f"2D tracks: {r['tracks']}"]


def head_pose_line(h: dict[str, Any]) -> str:
    """The summary's head-pose line: how many frames' poses were solved with the face."""
    n = h["joint"] + h["stable"] + h["none"]
    if not h["joint"]:
        return f"head pose: stable markers in {h['stable']} of {n} frames, none in {h['none']} (--index solves it " \
               "with the face)"
    return (f"head pose: solved with the face in {h['joint']} of {n} frames (median residual "
            f"{h['joint_rms_median_mm']:.3f} mm), stable markers in {h['stable']}, none in {h['none']}")
