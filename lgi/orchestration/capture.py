"""A capture session as one flow: calibration images and each shot's stereo footage to meshes and exports.

``capture-session`` calibrates the head-mounted camera pair once (a cached stage: the same images and options
reuse the calibration), then runs one ``reconstruct-shot`` subflow per shot (track and triangulate the
footage, reconstruct, write USD), and exports EXR displacement maps when asked. A shot that fails does not
stop the others: the session's summary and its report artifact list every shot with its status and, for a
failed one, the error. The rig solve (with ``rig``) has a status of its own (``rig_status``, ``rig_error``): a
shot whose reconstruction was written but whose solve failed is reconstructed (``status`` done) with its rig
solve failed, and a warning in the flow run's logs says so. The jobs are the command line's (``lgi calibrate``,
``lgi track``, ``lgi reconstruct``, ``lgi export``, ``lgi rig-solve``) with the same options.

Layout of ``out``::

    calibration.json            the session's stereo calibration
    shots/<shot>/bundles.csv    tracked bundles (cm) and bundles.tracks.parquet (2D tracks)
    shots/<shot>/recon/         lgi reconstruct's outputs (meshes.npz, diagnostics, shot.usdc, ...)
    shots/<shot>/exr/           displacement maps (with exr_size)
    shots/<shot>/anim/          lgi rig-solve's outputs (with rig): curves.csv, residuals.csv, ...
    shots/<shot>/anim.usda      the shot as a UsdSkel animation of the rig (with rig and rig_usd)
    .cache/                     the cached calibration (lgi cache ls / prune)
"""

from __future__ import annotations

import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, task
from prefect.artifacts import create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE
from prefect.states import Completed

from lgi.errors import InputError
from lgi.io.atomic import atomic_file, check_output
from lgi.io.cache import StageCache, hash_tree
from lgi.io.csvio import read_table
from lgi.jobs.capture import CalibrateOptions, TrackFootageOptions, calibrate
from lgi.jobs.compare import IN_SHOT, SHOT_SCAN_OPTIONS, CompareOptions
from lgi.jobs.export import ExportOptions, export
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.review import ReviewOptions, review_beside
from lgi.jobs.rig_solve import RigSolveOptions
from lgi.options import Subset, flow_parameters, params, take
from lgi.orchestration import artifact_key, capture_library_logs, transient_only
from lgi.orchestration.deploy import run_paths
from lgi.orchestration.params import described
from lgi.orchestration.reconstruct import reconstruct_shot
from lgi.orchestration.rig import rig_solve_shot


def shot_folders(shots: str | list[str]) -> list[Path]:
    """The shots of a session: a list of footage folders, or one folder whose subfolders are the shots (those
    holding ``cam0/`` and ``cam1/``, or ``left*``/``right*`` images), in name order."""
    if isinstance(shots, (list, tuple)):
        folders = [Path(s) for s in shots]
    else:
        root = Path(shots)
        if not root.is_dir():
            raise InputError("shots folder not found", path=root)
        folders = sorted(p for p in root.iterdir() if p.is_dir() and (
            (p / "cam0").is_dir() or any(p.glob("left*"))))
    if not folders:
        raise InputError("no shots (folders with cam0/ and cam1/, or left*/right* images)", path=shots)
    names = [f.name for f in folders]
    if len(set(names)) != len(names):
        raise InputError(f"two shots share a folder name: {sorted(n for n in names if names.count(n) > 1)}")
    return folders


def session_scans(path: str, shots: list[str]) -> dict[str, list[tuple[int, str]]]:
    """Per shot name, its ``(frame, scan path)`` pairs from a session's scans CSV (columns ``shot, frame, scan``;
    scan paths relative to the CSV's folder); a shot the session does not have is refused."""
    d = read_table(path, "scans file", ("shot", "frame", "scan"), numeric=("frame",))
    out: dict[str, list[tuple[int, str]]] = {}
    for r, (shot, f, scan) in enumerate(zip(d["shot"].astype(str), d["frame"], d["scan"].astype(str), strict=True)):
        if shot not in shots:
            raise InputError(f"shot {shot!r} is not one of the session's ({', '.join(shots)})", path=path, line=r + 2)
        if f != int(f):
            raise InputError(f"frame {f!r} is not a whole number", path=path, line=r + 2)
        p = Path(scan.strip())
        out.setdefault(shot, []).append((int(f), str(p if p.is_absolute() else Path(path).parent / p)))
    return out


@task(name="calibrate-session", cache_policy=NO_CACHE, persist_result=False, retries=1,
      retry_condition_fn=transient_only, timeout_seconds=3600)
def calibrate_session(images: str, options: dict, out: str, cache_dir: str):
    """Calibrate the camera pair (``lgi calibrate``), cached by the images' content and the options; the result
    is copied to ``out``. A cache hit ends in a state named Cached."""
    opts = CalibrateOptions(**options)

    def make(d: Path) -> None:
        calibrate(images, d / "calibration.json", opts)

    path, hit = StageCache(cache_dir).run("calibrate", {"images": hash_tree(images), "options": opts.to_json()},
                                          make, ("lgi.jobs.capture",))
    with atomic_file(out) as tmp:
        shutil.copyfile(path / "calibration.json", tmp)
    value = (out, hit)
    return Completed(data=value, name="Cached", message="calibration reused from the cache") if hit else value


@task(name="export-shot", cache_policy=NO_CACHE, persist_result=False, timeout_seconds=6 * 3600)
def export_shot(recon: str, index_dir: str, exr: str, exr_size: int, fps: float) -> dict:
    """Displacement maps of a reconstructed shot (``lgi export --exr``)."""
    return export(recon, index_dir, ExportOptions(exr=exr, exr_size=exr_size, fps=fps))


def solve_rig_row(row: dict, recon: str, rig: str, shot_dir: Path, rig_usd: str | None, fps: float,
                  logger) -> None:
    """Solve a reconstructed shot onto the rig and record it in the shot's ``row``: ``rig_status`` done, with
    ``anim`` and ``rig_rms_mm``, or failed, with ``rig_error`` and a warning. A failed solve does not fail the
    shot: its reconstruction is written and usable."""

    try:
        anim = rig_solve_shot(recon, rig, str(shot_dir / "anim"), str(shot_dir / "anim.usda") if rig_usd else None,
                              rig_usd, asdict(RigSolveOptions(fps=fps)))
    except Exception as exc:  # noqa: BLE001 - the reconstruction stands; the solve's failure is reported
        row.update(rig_status="failed", rig_error=f"{type(exc).__name__}: {exc}")
        logger.warning("shot %s was reconstructed but its rig solve failed: %s", row["shot"], row["rig_error"])
        return
    row.update(rig_status="done", anim=anim["out"], rig_rms_mm=round(anim["rms_mm"], 4))


def rig_review(row: dict, summary: dict, index_dir: str, fps: float, logger) -> None:
    """Write the shot's review page again with the rig map (where the rig falls short, lgi review --rig-solve)
    and its scans; the page reconstruct-shot wrote stays when this fails (said in the log)."""
    scans = Path(summary["out"]) / IN_SHOT
    done = summary.get("compare", {}).get("status") == "done"
    try:
        review_beside(summary["out"], index_dir, summary, ReviewOptions(fps=fps, scans=str(scans) if done else None,
                                                                        rig_solve=row["anim"]))
    except Exception as exc:  # noqa: BLE001 - the shot and its solve stand; the page without the rig map stays
        logger.warning("shot %s: the review page was not rewritten with the rig map: %s: %s", row["shot"],
                       type(exc).__name__, exc)


#: The reconstruct options a capture session passes to each shot's reconstruction.
SESSION_SHOT_OPTIONS = Subset(ReconstructOptions, only=("smooth", "fps", "chunk_size"))
#: The one scan option a session takes (its scans CSV gives the rest per shot).
SHOT_SCAN_UNITS = Subset(CompareOptions, SHOT_SCAN_OPTIONS.prefix, ("units",))
#: The lens model of the session's calibration (its board is the flow's second parameter).
SESSION_LENS = Subset(CalibrateOptions, only=("rational", "fisheye"))
#: The helmet dots that refine the rig per shot (lgi track --helmet).
SESSION_HELMET = Subset(TrackFootageOptions, only=("helmet",))


@flow(name="capture-session")
@described(
    SESSION_SHOT_OPTIONS, SHOT_SCAN_UNITS, SESSION_LENS, SESSION_HELMET,
    calibration_images="Folder of stereo board images (left*/right* or cam0/ and cam1/), as lgi calibrate reads.",
    board="Board spec for lgi calibrate, e.g. chessboard:9x6:25 or charuco:7x5:30:22:DICT_5X5_100 (mm).",
    shots="A folder whose subfolders are the shots (each with cam0/ and cam1/ frames), or a list of shot folders.",
    index_dir="The actor's LGI index (lgi build or the rebuild-dataset flow).",
    markers="Marker layout CSV with neutral positions (x, y, z), as lgi track reads.",
    out="Session output folder: calibration.json, shots/<shot>/ (bundles, recon/, exr/).",
    usd="Write each shot's shot.usdc.",
    exr_size="Also write EXR displacement maps of this many texels square per frame (null: none).",
    dask_address="Run the reconstruction chunks on Dask (see reconstruct-shot); null: threads.",
    rig="The actor's rig dataset (lgi rig-generate): each shot is also solved onto it (lgi rig-solve; a failed "
        "solve is reported in rig_status and rig_error, the shot stays reconstructed); null: none.",
    rig_usd="The rig's USD (lgi rig-generate --usd): each shot also gets anim.usda, its animation; null: none.",
    scans="A CSV of scans to compare shots with (columns shot, frame, scan; scan paths relative to the CSV): each "
          "shot's pairs go to its reconstruct-shot run (shots/<shot>/recon/compare, and its review page); a scan "
          "that fails is reported in the session's table (column scans); null: none.",
)
@flow_parameters(SESSION_LENS, SESSION_HELMET, SESSION_SHOT_OPTIONS, SHOT_SCAN_UNITS, after=6)
def capture_session(
    calibration_images: str,
    board: str,
    shots: str | list[str],
    index_dir: str,
    markers: str,
    out: str,
    usd: bool = True,
    exr_size: int | None = None,
    dask_address: str | None = None,
    rig: str | None = None,
    rig_usd: str | None = None,
    scans: str | None = None,
    **options: Any,
) -> dict:
    """Calibrate once, then track, reconstruct and export every shot; returns the session summary (``shots``:
    per shot its status, frames, outputs, or the error)."""
    capture_library_logs()
    shot_options = take(SESSION_SHOT_OPTIONS, options)  # by field name, for each shot's reconstruct-shot run
    fps = shot_options["fps"]
    scan = params(SHOT_SCAN_OPTIONS, take(SHOT_SCAN_UNITS, options))
    at = run_paths()  # a deployment run's relative paths go under the data root, never the worker's cwd
    calibration_images, index_dir = at(calibration_images, "calibration_images"), at(index_dir, "index_dir")
    helmet = at(take(SESSION_HELMET, options)["helmet"], "helmet")
    markers, out = at(markers, "markers"), at(out, "out", output=True)
    shots = [at(s, "shots") for s in shots] if isinstance(shots, (list, tuple)) else at(shots, "shots")

    cal_opts = CalibrateOptions(board=board, **take(SESSION_LENS, options))
    if exr_size is not None:
        ExportOptions(exr="x", exr_size=exr_size, fps=fps)  # the values checked before any work
    folders = shot_folders(shots)
    scans = at(scans, "scans")
    shot_scans = session_scans(scans, [f.name for f in folders]) if scans else {}
    out_dir = Path(out)
    rig, rig_usd = at(rig, "rig"), at(rig_usd, "rig_usd")
    if rig is not None:
        from lgi.jobs.rig_solve import load_rig

        load_rig(rig)  # a bad rig is refused before any shot is reconstructed
    check_output(out_dir, "dir", inputs=[calibration_images, index_dir, markers, helmet, rig, rig_usd, *folders])
    out_dir.mkdir(parents=True, exist_ok=True)
    calib, cal_hit = calibrate_session(calibration_images, cal_opts.to_json(), str(out_dir / "calibration.json"),
                                       str(out_dir / ".cache"), return_state=True).result()
    logger = get_run_logger()
    rows = []
    for folder in folders:
        shot_dir = out_dir / "shots" / folder.name
        row: dict = {"shot": folder.name, "status": "failed", "frames": 0, "error": "", "review": "",
                     "rig_status": "" if rig is None else "not run", "rig_error": ""}
        state = reconstruct_shot(index_dir, str(shot_dir / "bundles.csv"), str(shot_dir / "recon"), **shot_options,
                                 usd=usd, footage=str(folder), calib=calib,
                                 markers=markers, helmet=helmet, dask_address=dask_address,
                                 scans=shot_scans.get(folder.name), **scan, return_state=True)
        try:
            summary = state.result()
            row.update(status="done", frames=summary["frames"], recon=summary["out"], review=summary.get("review", ""))
            if "compare" in summary:
                c = summary["compare"]
                row["scans"] = f"{len(c['pairs'])} compared" if c["status"] == "done" else f"failed: {c['error']}"
            if exr_size is not None:
                export_shot(summary["out"], index_dir, str(shot_dir / "exr"), exr_size, fps)
                row["exr"] = str((shot_dir / "exr").resolve())
            if rig is not None:
                solve_rig_row(row, summary["out"], rig, shot_dir, rig_usd, fps, logger)
                if row["rig_status"] == "done" and summary.get("review"):
                    rig_review(row, summary, index_dir, fps, logger)
        except Exception as exc:  # noqa: BLE001 - a failed shot is reported, the session goes on
            row["error"] = f"{type(exc).__name__}: {exc}"
            logger.error("shot %s failed: %s", folder.name, row["error"])
        rows.append(row)
    failed = [r for r in rows if r["status"] != "done"]
    rig_failed = [r for r in rows if r["rig_status"] == "failed"]
    key = artifact_key("session", out_dir)
    create_table_artifact(table=rows, key=key, description="capture session: every shot, its status and error")
    create_markdown_artifact(key=f"{key}-report", markdown=(
        f"# Capture session\n\ncalibration: `{calib}` ({'cached' if cal_hit else 'computed'})\n\n"
        f"{len(rows) - len(failed)} of {len(rows)} shots reconstructed"
        + ("".join(f"\n- **{r['shot']}** failed: {r['error']}" for r in failed) if failed else "")
        + "".join(f"\n- **{r['shot']}**: scan comparison {r['scans']}" for r in rows
                  if r.get("scans", "").startswith("failed"))
        + "".join(f"\n- **{r['shot']}** reconstructed, rig solve failed: {r['rig_error']}" for r in rig_failed)
        + "".join(f"\n- {r['shot']}: review page [{r['review']}]({Path(r['review']).as_uri()})"
                  for r in rows if r.get("review")) + "\n"))
    logger.info("%d of %d shots reconstructed%s%s", len(rows) - len(failed), len(rows),
                f"; failed: {', '.join(r['shot'] for r in failed)}" if failed else "",
                f"; rig solve failed: {', '.join(r['shot'] for r in rig_failed)}" if rig_failed else "")
    return {"calibration": calib, "calibration_cached": cal_hit, "shots": rows, "failed": [r["shot"] for r in failed],
            "rig_failed": [r["shot"] for r in rig_failed]}
