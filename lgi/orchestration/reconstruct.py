"""The per-shot reconstruction as Prefect tasks and a flow: the stages of :mod:`lgi.jobs.reconstruct`.

Frames are chosen in chunks chained one after another (each continues from the last choice of the chunk
before, as a single pass does), then finished in chunks mapped over the task runner (a frame's surface
depends only on the choices in its smoothing windows), then assembled and written by the job's one writer.
So any chunk size and any task runner (threads, or Dask through prefect-dask: ``reconstruct_shot.with_options(
task_runner=DaskTaskRunner(...))``) give the files ``lgi reconstruct`` writes, bit for bit (tested).
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from prefect import flow, get_run_logger, task
from prefect.artifacts import (
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed

from lgi.errors import InputError
from lgi.io.atomic import RESUME_FILE, make_temp_dir, output_lock, staged_key, stopped, sweep
from lgi.io.npz import npz_member
from lgi.jobs import reconstruct as job
from lgi.jobs.capture import TrackFootageOptions, track
from lgi.jobs.compare import (
    REGIONS,
    SHOT_SCAN_OPTIONS,
    CompareOptions,
    compare,
    compare_shot,
    shot_scan_options,
)
from lgi.jobs.review import ReviewOptions, review_beside
from lgi.options import flow_parameters, take
from lgi.orchestration import INTERRUPTED, artifact_key, capture_library_logs, embedded_png
from lgi.orchestration.deploy import run_paths
from lgi.orchestration.params import described

_T = {"cache_policy": NO_CACHE, "persist_result": False}


@task(name="track-footage", **_T)
def track_footage(footage: str, calib: str, markers: str, bundles: str, dataset: str | None = None,
                  units: str = "cm", helmet: str | None = None, labels: str | None = None, reference: int = 0,
                  index: str | None = None) -> dict:
    """Stereo footage to the bundles file and the 2D tracks table: ``lgi track``'s job
    (:func:`lgi.jobs.capture.track`); with ``index``, the head pose solved with the face."""
    return track(footage, calib, markers, bundles, TrackFootageOptions(
        dataset=dataset, units=units, labels=labels, reference_frame=reference, helmet=helmet, index=index))


_STOP = ".stopped"


def _stopped(out: str) -> bool:
    """True once the flow has been interrupted: its chunk tasks still queued then return at once instead of
    running (or failing on the working folder the flow is about to remove)."""
    return INTERRUPTED.is_set() or (Path(out).parent / _STOP).exists()


@task(name="choose-chunk", **_T)
def choose_chunk(index_dir: str, bundles: str, options: dict, lo: int, hi: int, out: str,
                 previous: str | None = None) -> str:
    """Choose shapes and weights for frames lo:hi (see :func:`lgi.jobs.reconstruct.choose_chunk`)."""
    if _stopped(out):
        return ""
    return job.choose_chunk(index_dir, bundles, job.ReconstructOptions.from_json(options), lo, hi, out, previous)


@task(name="finish-chunk", **_T)
def finish_chunk(index_dir: str, bundles: str, options: dict, choices: list[str], lo: int, hi: int,
                 out: str, first: int = 0, keep: bool = False) -> str:
    """Blend, skin and correct frames lo:hi (see :func:`lgi.jobs.reconstruct.finish_chunk`)."""
    if _stopped(out):
        return ""
    return job.finish_chunk(index_dir, bundles, job.ReconstructOptions.from_json(options), choices, lo, hi, out,
                            first, keep)


@task(name="rays", **_T)
def rays_task(index_dir: str, bundles: str, options: dict, first: str, out: str) -> dict:
    """Markers seen by one camera onto their rays, from the first pass's meshes (see
    :func:`lgi.jobs.reconstruct.constrain_to_rays`)."""
    shot = job.prepared_shot(index_dir, bundles, job.ReconstructOptions.from_json(options))
    return job.constrain_to_rays(shot, npz_member(Path(first) / "meshes.npz", "vertices"), out)


@task(name="write-shot", **_T)
def write_shot(index_dir: str, bundles: str, options: dict, parts: list[str], out: str) -> dict:
    """Join the finished chunks and write the outputs (see :func:`lgi.jobs.reconstruct.assemble`)."""
    return job.assemble(index_dir, bundles, job.ReconstructOptions.from_json(options), parts, out)


@task(name="review-page", **_T)
def review_task(out: str, index_dir: str, summary: dict, fps: float, scans: str | None = None,
                warnings: list[str] | None = None) -> str:
    """The shot's review page in ``out/review`` (see :func:`lgi.jobs.review.review`), with the scan map of the
    compare folder ``scans``; returns its path."""
    return review_beside(out, index_dir, summary, ReviewOptions(fps=fps, scans=scans), warnings)["page"]


@task(name="compare-scans", **_T)
def compare_task(recon: str, options: dict) -> dict:
    """The shot's frames against their scans: ``lgi compare``'s job (:func:`lgi.jobs.compare.compare`), its
    tables and heat maps in ``options["out"]``."""
    return compare(recon, CompareOptions.from_json(options))


@flow(name="reconstruct-shot")
@described(job.ReconstructOptions, SHOT_SCAN_OPTIONS, index_dir="LGI index folder (lgi build).",
           bundles="Bundles file (CSV or Parquet: frame, marker, x, y, z in cm, head frame); written first when "
                   "footage is given.",
           out="Output folder: meshes.npz, diagnostics.csv, per_frame.csv (and obj/, shot.usdc, per_frame.png "
               "when asked).",
           footage="Stereo frames (cam0/, cam1/): track them into bundles first (needs calib and markers).",
           calib="Stereo calibration JSON (lgi calibrate): tracks the footage, and turns the observations into rays "
                 "(for rays, default: the rig stored in the tracks table).",
           markers="Marker layout CSV with neutral positions, with footage.",
           helmet="Helmet marker CSV (name, x, y, z in mm): refine the rig per shot, with footage.",
           dask_address="Run the chunk tasks on Dask: a scheduler address (tcp://host:8786), or local:N for a "
                        "local cluster of N worker processes (null: threads in this process). Results are the "
                        "same bit for bit.",
           review="Also write the shot's review page into OUT/review (index.html: the shot in 3D with its "
                  "markers, colour maps and curves; opens from the file system) and link it in the report.",
           scans="Scans of some of the shot's moments to compare the reconstruction with (lgi compare): a pairs "
                 "CSV (columns frame, scan; paths relative to the CSV) or a list of [frame, scan] pairs. Written "
                 "to OUT/compare, linked in the report and shown on the review page. A scan that does not load or "
                 "covers no part of the face is reported (table artifact, error log, report, page) and the "
                 "reconstruction kept; a missing scan file or frame is refused before any work.",
)
@flow_parameters(job.ReconstructOptions, SHOT_SCAN_OPTIONS, after=3)
def reconstruct_shot(
    index_dir: str,
    bundles: str,
    out: str,
    footage: str | None = None,
    markers: str | None = None,
    helmet: str | None = None,
    dask_address: str | None = None,
    review: bool = True,
    scans: str | list[tuple[int, str]] | None = None,
    **options: Any,
) -> dict:
    """Reconstruct a shot into ``out``: the options of ``lgi reconstruct`` (:class:`~lgi.jobs.reconstruct.
    ReconstructOptions`), with the work in chunks of ``chunk_size`` frames.

    With ``footage`` (stereo frames), ``calib`` and ``markers``, the shot starts from the cameras: the
    ``track-footage`` task writes ``bundles`` (and its 2D tracks table) first, with ``helmet`` dots if given.
    """
    capture_library_logs()
    at = run_paths()  # a deployment run's relative paths go under the data root, never the worker's cwd
    footage, markers, helmet = at(footage, "footage"), at(markers, "markers"), at(helmet, "helmet")
    index_dir, out = at(index_dir, "index_dir"), at(out, "out", output=True)
    bundles = at(bundles, "bundles", output=bool(footage))  # from footage, the tracked bundles are written there
    options["jaw"] = at(options.get("jaw", "auto"), "jaw", ("auto", "none"))
    for name in ("observations", "calib", "contours"):
        options[name] = at(options.get(name), name)
    calib = options["calib"]
    if scans is not None:
        scans = at(scans, "scans") if isinstance(scans, str) else [(f, at(s, "scans")) for f, s in scans]
    scan = take(SHOT_SCAN_OPTIONS, options)
    region = scan.get("region")
    if isinstance(region, str) and region.strip() not in REGIONS and not re.fullmatch(r"\s*\d+\s*:\s*\d+\s*", region):
        scan["region"] = at(region, "scan_region")  # a vertex index file
    if footage and not (calib and markers):
        raise InputError("a shot from footage needs calib and markers")
    if footage and not options["observations"]:
        options["calib"] = None  # it calibrates the tracking; without observations there are no rays to make
    opts = job.ReconstructOptions.from_json(options)
    # Scans are checked before any work (files there, frames in the shot), their loading and coverage after.
    shot_job = job.ReconstructJob(index_dir, bundles, out, opts, shot_scan_options(scans, index_dir, out, **scan),
                                  review, (footage, calib, markers, helmet))
    steps = FlowSteps(footage, calib, markers, helmet, dask_address)
    # One run at a time in OUT (lgi reconstruct holds it already; a deployment's run takes it here).
    with output_lock(out):
        summary = shot_job.run(steps)
    _report(summary, out)
    logger = get_run_logger()
    for line in job.report_lines(summary):
        logger.info(line)
    if steps.tracking:
        summary["tracking"] = steps.tracking
    return summary


class FlowSteps:
    """The reconstruct job's steps in the flow (:class:`lgi.jobs.reconstruct.ReconstructJob`): the footage tracked
    first when given, the shot in chunk tasks (Prefect's threads, or Dask at ``dask_address``), the comparison and
    the page as tasks."""

    def __init__(self, footage: str | None, calib: str | None, markers: str | None, helmet: str | None,
                 dask_address: str | None):
        self.footage, self.calib, self.markers, self.helmet = footage, calib, markers, helmet
        self.dask_address = dask_address
        self.tracking: dict | None = None

    def before(self, shot_job) -> None:
        if not self.footage:
            return
        # The actor's index is at hand: the head pose is solved with the face (lgi track --index).
        self.tracking = track_footage(self.footage, self.calib, self.markers, shot_job.bundles,
                                      helmet=self.helmet, index=shot_job.index_dir)
        create_table_artifact(table=[{k: v for k, v in self.tracking.items() if not isinstance(v, (list, dict))}],
                              key=artifact_key("shot-tracking", shot_job.out),
                              description="footage to bundles: tracking summary")

    def reconstruct(self, shot_job) -> dict:
        return _reconstruct_in_chunks(shot_job, task_runner(self.dask_address))

    def compare(self, shot_job, pairs: list[tuple[int, Path]]) -> dict:
        return _compare_scans(shot_job.out, shot_job.scans, pairs)

    def review(self, shot_job, summary: dict, scans: str | None, warnings: list[str]) -> str:
        return review_task(shot_job.out, shot_job.index_dir, summary, shot_job.options.fps, scans, warnings)


def _reconstruct_in_chunks(shot_job, runner) -> dict:
    """The shot in chunk tasks, both passes with observations; a stopped run's chunks of the same job are not done
    again."""
    index_dir, bundles, out, opts = shot_job.index_dir, shot_job.bundles, shot_job.out, shot_job.options
    n = job.preflight(index_dir, bundles, opts)
    # One working folder per run: two runs into the same OUT never touch each other's chunk files. A stopped run's
    # folder (its process gone) is this run's when it was the same job in the same chunks: the chunks it finished
    # are not done again; any other is removed.
    work = _chunk_folder(Path(out), f"{job.resume_key(index_dir, bundles, opts)}:{opts.chunk_size}")
    # What a stopped run of this job left (both passes' chunks, with markers on rays), for the report.
    kept = {"chosen": len(list(work.rglob("choice_*.npz"))), "finished": len(list(work.rglob("part_*.npz"))),
            "chunks": len(chunk_bounds(n, opts.chunk_size))}
    # One progress artifact per shot (keyed by OUT, so `prefect artifact ls` lists it), updated by both passes.
    progress_key = artifact_key("shot-progress", out)

    def chunks(bundles_file: str, options: dict, into: str, folder: Path) -> dict:
        folder.mkdir(exist_ok=True)
        if runner is None:
            # Prefect's threads in this process: the flow's own task runner, and the finished chunks handed to
            # the writer in memory.
            return chunk_work(index_dir, bundles_file, options, n, opts.chunk_size, str(folder), into, keep=True,
                              progress_key=progress_key)
        return reconstruct_chunks.with_options(task_runner=runner)(index_dir, bundles_file, options, n,
                                                                   opts.chunk_size, str(folder), into, progress_key)

    try:
        if opts.observations:
            # As lgi reconstruct does: the shot without the markers seen by one camera, then through their points
            # on their rays.
            first = job.replace_outputs(opts)
            said = chunks(bundles, first.to_json(), str(work / "first"), work / "pass1")["chunk_warnings"]
            constrained = str(work / job.CONSTRAINED)
            counts = rays_task(index_dir, bundles, opts.to_json(), str(work / "first"), constrained)
            summary = {**chunks(constrained, opts.to_json(), out, work / "pass2"), **counts}
            summary["chunk_warnings"] = said + summary["chunk_warnings"]
        else:
            summary = chunks(bundles, opts.to_json(), out, work)
    except (KeyboardInterrupt, SystemExit):
        job.forget_parts(work)  # stopped: the chunks written wait for the same run again
        raise
    except BaseException:
        job.forget_parts(work)
        shutil.rmtree(work, ignore_errors=True)
        raise
    job.forget_parts(work)
    shutil.rmtree(work, ignore_errors=True)
    if kept["chosen"] or kept["finished"]:
        summary["resumed_chunks"] = kept
    return summary


def _chunk_folder(out: Path, key: str) -> Path:
    """The flow's working folder for its chunk files beside ``out``: a stopped run's of the same job ``key`` (its
    process gone) taken over, else a new one; the other stopped runs' are removed."""

    parent, prefix = out.absolute().parent, f".{out.name}.chunks-"
    parent.mkdir(parents=True, exist_ok=True)
    left = [d for d in parent.glob(f"{prefix}*") if stopped(d.name, prefix) and d.is_dir() and staged_key(d) == key]
    work = make_temp_dir(parent, prefix)
    if left:
        newest = max(left, key=lambda d: max((f.stat().st_mtime_ns for f in d.iterdir()), default=0))
        work.rmdir()
        os.replace(newest, work)
        done = len(list(work.glob("choice_*.npz")))
        if done:
            get_run_logger().info("resuming a stopped run of this shot: %d chunks already chosen", done)
    else:
        (work / RESUME_FILE).write_text(json.dumps({"key": key}))
    sweep(parent, prefix)
    return work


def _compare_scans(out: str, options: CompareOptions, pairs: list[tuple[int, Path]]) -> dict:
    """The compare job on the reconstructed shot, as a task (:func:`lgi.jobs.compare.compare_shot`: a scan that
    fails is logged and returned as ``status: failed``; the reconstruction stays)."""
    return compare_shot(out, options, pairs, get_run_logger(),
                        run=lambda recon, o: compare_task(recon, o.to_json()))


def task_runner(dask_address: str | None):
    """The task runner of the chunk work: None (Prefect's threads), or Dask at ``dask_address`` (``local:N``: a
    local cluster of N single-threaded worker processes)."""
    if not dask_address:
        return None
    from prefect_dask import DaskTaskRunner

    if dask_address.startswith("local"):
        n = dask_address.partition(":")[2] or "2"
        if not n.isdigit() or not 1 <= int(n) <= 256:
            raise InputError(f"dask_address {dask_address!r}: local:N takes a number of workers from 1 to 256")
        import dask

        # A local cluster's workers get this process's Dask configuration. Their statistical profiler (for the
        # dashboard, which nobody reads here) keeps an hour of samples: it grew each worker of a 36,000-frame ICT
        # take by 1.3x that of 1,000 frames (9,000 frames: 942 MiB with it, 850 without).
        dask.config.set({"distributed.worker.profile.enabled": False})
        return DaskTaskRunner(cluster_kwargs={"n_workers": int(n), "threads_per_worker": 1, "processes": True})
    return DaskTaskRunner(address=dask_address)


@flow(name="reconstruct-chunks")
def reconstruct_chunks(index_dir: str, bundles: str, options: dict, n_frames: int, chunk_size: int, work: str,
                       out: str, progress_key: str | None = None) -> dict:
    """:func:`chunk_work` on the task runner this subflow was given (Dask), the chunks passed as files."""
    return chunk_work(index_dir, bundles, options, n_frames, chunk_size, work, out, progress_key=progress_key)


#: On the flow's own threads, chunks submitted to be finished and not yet finished, and the same of the chain of
#: choices: two each, as lgi reconstruct's schedule (one choosing, one finishing) with one more ready, so that the
#: cores never wait.
FINISHING = 2
CHOOSING = 2
#: On Dask, chunks submitted to be finished and not yet finished: enough to keep a cluster of that many workers
#: busy. Every task submitted keeps its state on the scheduler and its result on a worker until released.
DASK_FINISHING = 32
#: Dask's priority of the chain of choices over the chunks waiting to be finished: the chain is the shot's
#: critical path, and each link is submitted only when the one before has ended.
CHAIN_PRIORITY = 1


def chunk_bounds(n_frames: int, chunk_size: int) -> list[tuple[int, int]]:
    """The chunks' frame ranges, ``[(lo, hi), ...]``: ``chunk_size`` frames each, the last one shorter."""
    return [(lo, min(lo + chunk_size, n_frames)) for lo in range(0, n_frames, chunk_size)]


def chunk_work(index_dir: str, bundles: str, options: dict, n_frames: int, chunk_size: int, work: str, out: str,
               keep: bool = False, progress_key: str | None = None) -> dict:
    """The chunk work of :func:`reconstruct_shot`, on the task runner of the flow that calls it: frames chosen
    in chunks chained one after another, then finished in chunks mapped over the runner, then written.
    ``keep``: the flow's own threads, the finished chunks kept in memory for the writer; otherwise Dask, every
    chunk passed as a file. ``progress_key``: the key of the progress artifact (default: one made from ``out``)."""
    from threadpoolctl import threadpool_limits

    bounds = chunk_bounds(n_frames, chunk_size)
    work_dir = Path(work)
    opts = job.ReconstructOptions.from_json(options)

    def needed(i: int) -> list[int]:
        a, b = job.chunk_needs(opts, n_frames, *bounds[i])
        return [k for k, (c0, c1) in enumerate(bounds) if c1 > a and c0 < b]

    # BLAS limits are process-wide: a chunk task leaving its one-thread limit would give the tasks still running
    # on the other threads a multithreaded BLAS that fights numba for the cores (lgi.threads). One limit for the
    # whole chunk work keeps every task at one BLAS thread.
    blas = threadpool_limits(limits=1, user_api="blas")
    running: set = set()  # the tasks submitted and not yet taken
    try:
        progress = create_progress_artifact(progress=0.0, key=progress_key or artifact_key("shot-progress", out),
                                            description=f"{n_frames} frames chosen, in {len(bounds)} chunks")

        def chosen(k: int) -> None:
            update_progress_artifact(progress, progress=100.0 * (k + 1) / len(bounds))

        run = _on_threads if keep else _on_dask
        parts = run(index_dir, bundles, options, bounds, work_dir, needed, chosen, running)
        return write_shot(index_dir, bundles, options, parts, out)
    except BaseException:
        # Interrupted (or a chunk failed): the tasks already submitted keep running on the task runner, so stop
        # them at their next start and let the running ones end before their folder goes.
        (work_dir / _STOP).touch()
        for fut in list(running):
            try:
                fut.wait(timeout=120)
            except BaseException:  # noqa: BLE001 - a second Ctrl-C or a failed task: stop waiting, clean up
                break
        raise
    finally:
        blas.restore_original_limits()


def _on_threads(index_dir: str, bundles: str, options: dict, bounds: list[tuple[int, int]], work_dir: Path,
                needed, chosen, running: set) -> list:
    """The chunks on the flow's own threads: each task handed the futures it reads, a few ahead of need. Returns
    the finished chunks, in order (in memory)."""
    futures, parts = [], []

    def submit(fut) -> object:
        running.add(fut)
        return fut

    def take(fut):
        running.discard(fut)
        return _result(fut)

    def choose(k: int) -> None:
        # The chain of choices, each continuing from the last: at most CHOOSING submitted and unfinished (each
        # holds a thread waiting for the one before). A finished task's future gives way to its result.
        if k >= CHOOSING:
            futures[k - CHOOSING] = take(futures[k - CHOOSING])
        lo, hi = bounds[k]
        path = work_dir / f"choice_{lo:06d}.npz"
        # A chunk a stopped run of this job chose (its file is whole or absent) is not chosen again.
        futures.append(str(path) if path.is_file() else submit(choose_chunk.submit(
            index_dir, bundles, options, lo, hi, str(path), futures[-1] if futures else None)))

    # Each chunk is finished as soon as the choices its windows read are made (Shot.needs), while the chain goes
    # on choosing: the two overlap as in lgi reconstruct's two-thread schedule. The work is handed out a little
    # ahead of need, not all at once: every task submitted holds a thread (a 9,000-frame ICT take's 300 threads
    # peaked at 5 GB).
    for i, (lo, hi) in enumerate(bounds):
        want = needed(i)
        while len(futures) < min(len(bounds), want[-1] + 1 + CHOOSING):
            choose(len(futures))
        if i >= FINISHING:
            parts[i - FINISHING] = take(parts[i - FINISHING])
        part = work_dir / f"part_{lo:06d}.npz"
        parts.append(str(part) if part.is_file() else submit(finish_chunk.submit(
            index_dir, bundles, options, [futures[k] for k in want], lo, hi, str(part), bounds[want[0]][0], True)))
    for k, fut in enumerate(futures):
        take(fut)
        chosen(k)
    return [take(p) for p in parts]


def _on_dask(index_dir: str, bundles: str, options: dict, bounds: list[tuple[int, int]], work_dir: Path,
             needed, chosen, running: set) -> list[str]:
    """The chunks on Dask: each task submitted once the files it reads are written, and handed their names, never
    a future. (A future passed as a task's parameter ties the tasks into one graph, which the scheduler kept
    whole: its tasks, and the workers' memory, grew with the shot.) Returns the finished chunks' files, in order."""
    import dask

    n = len(bounds)
    choices: list[str | None] = [None] * n
    parts: list[str | None] = [None] * n
    link, k = None, 0  # the chain's task in flight, and the chunk it chooses
    finishing: dict = {}  # chunk -> its task in flight
    i = 0  # the next chunk to finish
    while link is not None or finishing or k < n or i < n:
        if link is not None and link.wrapped_future.done():
            running.discard(link)
            choices[k - 1] = link.result()
            chosen(k - 1)
            link = None
        while link is None and k < n:
            lo, hi = bounds[k]
            path = work_dir / f"choice_{lo:06d}.npz"
            k += 1
            if path.is_file():  # a stopped run of this job chose it (its file is whole or absent)
                choices[k - 1] = str(path)
                chosen(k - 1)
                continue
            with dask.annotate(priority=CHAIN_PRIORITY):
                link = choose_chunk.submit(index_dir, bundles, options, lo, hi, str(path),
                                           choices[k - 2] if k > 1 else None)
            running.add(link)
        for j in [j for j, fut in finishing.items() if fut.wrapped_future.done()]:
            running.discard(finishing[j])
            parts[j] = finishing.pop(j).result()
        while i < n and len(finishing) < DASK_FINISHING and all(choices[c] for c in needed(i)):
            want = needed(i)
            lo, hi = bounds[i]
            part = work_dir / f"part_{lo:06d}.npz"
            if part.is_file():
                parts[i] = str(part)
            else:
                finishing[i] = finish_chunk.submit(index_dir, bundles, options, [choices[c] for c in want], lo, hi,
                                                   str(part), bounds[want[0]][0], False)
                running.add(finishing[i])
            i += 1
        if running:
            next(as_completed(list(running)))  # the first to end
        elif i < n:  # a task stopped before its work (_stopped) left a choice unmade
            raise RuntimeError(f"frames {bounds[i][0]}-{bounds[i][1] - 1}: the choices they read were not made")
    return parts


def _result(fut):
    """A task's result, or the file a stopped run left for it."""
    return fut if isinstance(fut, str) else fut.result()


#: Heat maps carried inside the report (each about a hundred kB); the others are linked.
EMBEDDED_HEATMAPS = 3


def _scan_report(summary: dict, out: str) -> str:
    """The scan comparison's table artifact (a row per pair: its figures, or that it failed) and its section of
    the shot's report ("" without scans)."""
    c = summary.get("compare")
    if not c:
        return ""
    cols = ("covered_share", "rms_mm", "p95_mm", "max_mm", "hausdorff_mm")
    rows = [{"frame": r["frame"], "scan": str(r["scan"]), "status": r.get("status", "done"),
             **{k: round(float(r[k]), 4) for k in cols if k in r}} for r in c["pairs"]]
    for r in rows:
        r["error"] = c["error"] if r["status"] == "failed" else ""
    create_table_artifact(table=rows, key=artifact_key("shot-compare", out),
                          description="the shot's frames against their scans (lgi compare; mm)" if c["status"] ==
                          "done" else f"scan comparison FAILED: {c['error']}")
    if c["status"] != "done":
        return f"\n## Scans\n\n**The scan comparison failed** (the reconstruction is kept): {c['error']}\n"
    folder = Path(c["out"])
    table = folder / "summary.csv"
    lines = ["", "## Scans", "", f"lgi compare's tables: [{table}]({table.as_uri()})", "",
             "| frame | scan | covered | RMS mm | p95 mm | max mm | Hausdorff mm |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['frame']} | {Path(r['scan']).name} | {r['covered_share']:.1%} | {r['rms_mm']:.3f} | "
              f"{r['p95_mm']:.3f} | {r['max_mm']:.3f} | {r['hausdorff_mm']:.3f} |" for r in c["pairs"]]
    lines.append("")
    for k, r in enumerate(c["pairs"]):
        png = folder / r["heatmap"] if r.get("heatmap") else None
        if png is not None and png.is_file():
            lines.append(embedded_png(png, f"frame {r['frame']} against {Path(r['scan']).name}")
                         if k < EMBEDDED_HEATMAPS else f"- heat map: [{png.name}]({png.as_uri()})")
    return "\n".join(lines) + "\n"


def _per_marker(path: Path, rows: int = 50_000):
    """Per marker (sorted by name): the share of frames contained, the frames projected, taking a neighbour's
    blend and missing or bridged, and the median projection (mm) of ``diagnostics.csv``, read ``rows`` at a time
    (a 36,000-frame ICT take's table is millions of rows; read whole, it was most of the flow's peak)."""
    counts: dict[str, np.ndarray] = {}
    projections: dict[str, list[np.ndarray]] = {}
    kinds = ("contained", "projected", "neighbour", "missing", "bridged")
    for d in pd.read_csv(path, usecols=["marker", "status", "projection_mm"], chunksize=rows,
                         dtype={"marker": str, "status": str}):
        for m, g in d.groupby("marker", sort=False):
            c = counts.setdefault(m, np.zeros(len(kinds) + 1, np.int64))
            st = g["status"].to_numpy()
            c[0] += len(st)
            for k, name in enumerate(kinds, 1):
                c[k] += int((st == name).sum())
            p = g["projection_mm"].to_numpy(np.float64)
            projections.setdefault(m, []).append(p[np.isfinite(p)])
    table = []
    for m in sorted(counts):
        n, contained, projected, neighbour, missing, bridged = counts[m]
        p = np.concatenate(projections[m])
        table.append({"marker": m, "contained": round(float(contained / n), 3), "projected": int(projected),
                      "neighbour": int(neighbour), "missing": int(missing + bridged),
                      "median_projection_mm": float(np.median(p)) if p.size else float("nan")})
    return pd.DataFrame(table)


def _report(summary: dict, out: str) -> None:
    """Per-marker table and a markdown report as artifacts."""
    per_marker = _per_marker(Path(out) / "diagnostics.csv")
    create_table_artifact(table=per_marker.to_dict(orient="records"), key=artifact_key("shot-markers", out),
                          description="per marker: share of frames contained in the data; frames projected, "
                                      "taking a neighbour's blend, missing")
    png = Path(out) / "per_frame.png"
    if png.is_file():
        plot = f"{embedded_png(png, 'per-frame plot')}\n\n"
    else:
        # Not asked for in OUT (plot false): drawn for the report only, from the per-frame table.
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            job.plot_per_frame(pd.read_csv(Path(out) / "per_frame.csv"), Path(tmp) / "per_frame.png")
            plot = f"{embedded_png(Path(tmp) / 'per_frame.png', 'per-frame plot')}\n\n"
    create_markdown_artifact(key=artifact_key("shot-report", out),
                             description="the shot's report: bundle status shares and the per-frame plot", markdown=(
        f"# Shot reconstruction\n\n{summary['frames']} frames x {summary['markers']} markers -> `{summary['out']}`\n\n"
        "| contained | projected | neighbour's blend | missing or bridged | max bundle residual |\n"
        "|---|---|---|---|---|\n"
        f"| {summary['contained_share']:.1%} | {summary['projected_share']:.1%} | {summary['neighbour_share']:.1%} "
        f"| {summary['missing_share']:.1%} | {summary['max_residual_mm']:.2e} mm |\n\n"
        f"{plot}Diagnostics: `diagnostics.csv`, `per_frame.csv`\n" + _scan_report(summary, out)
        + (f"\nReview page (open in a browser): [{summary['review']}]({Path(summary['review']).as_uri()})\n"
           if summary.get("review") else "")))
