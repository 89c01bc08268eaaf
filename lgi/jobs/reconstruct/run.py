"""The whole reconstruct job in this process (``lgi reconstruct``), with the second pass through the rays of
markers seen by one camera."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

from lgi._debug_stages import stage
from lgi.io.atomic import make_temp_dir, sweep
from lgi.io.npz import npz_member
from lgi.jobs.reconstruct.chunks import forget_shots, prepared_shot, replace_outputs
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.outputs import check_outputs, reconstruction_outputs, resume_key
from lgi.jobs.reconstruct.rays import CONSTRAINED
from lgi.jobs.reconstruct.shot import Shot, constrain_to_rays
from lgi.jobs.reconstruct.summary import ShotSummary

#: Frames solved and written at a time by the job in this process: a long take's memory is bounded by a block of
#: surfaces (ICT, 26,719 vertices: 38 MB), whatever its length.
BLOCK_FRAMES = 120
#: A take's progress is made durable after a block at most this often (seconds): the same command run again after
#: a stop (killed, or interrupted) goes on from there (:meth:`ReconstructionWriter.checkpoint`).
CHECKPOINT_SECONDS = 10.0


def reconstruct(index_dir: str | Path, bundles: str | Path, out: str | Path,
                options: ReconstructOptions | None = None, show_progress: bool = False) -> dict[str, Any]:
    """Reconstruct a shot in this process and write its outputs into ``out``; returns the summary
    (:class:`ShotSummary`; :func:`report_lines` formats it). The shot is solved and written in blocks of
    :data:`BLOCK_FRAMES` frames.

    With ``options.observations``, twice: without the markers seen by one camera, then through their points on
    their rays (:func:`constrain_to_rays`). A shot already prepared in this process (:func:`prepared_shot`, by
    the job's checks) is taken, and dropped at the end."""
    options = options or ReconstructOptions()
    try:
        return _reconstruct(index_dir, bundles, out, options, show_progress)
    finally:
        forget_shots()


def _reconstruct(index_dir: str | Path, bundles: str | Path, out: str | Path, options: ReconstructOptions,
                 show_progress: bool) -> dict[str, Any]:
    if options.method == "blendshape":
        from lgi.jobs.reconstruct.blendshape import reconstruct_blendshape

        return reconstruct_blendshape(index_dir, bundles, out, options, show_progress)
    check_outputs(out, (index_dir, bundles, options.jaw, options.observations, options.calib, options.contours))
    t0 = time.perf_counter()
    shot = prepared_shot(index_dir, bundles, options)
    t1 = time.perf_counter()
    stage("solve")
    if not options.observations:
        tally, solve, write = write_shot(shot, out, options, show_progress=show_progress,
                                         resume=resume_key(index_dir, bundles, options))
        return tally.result(shot, out, {"load": t1 - t0, "solve": solve, "write": write})

    parent, prefix = Path(out).absolute().parent, f".{Path(out).name}.rays-"
    parent.mkdir(parents=True, exist_ok=True)
    sweep(parent, prefix)
    work = make_temp_dir(parent, prefix)
    try:
        _, solve1, write1 = write_shot(shot, work / "first", replace_outputs(options), show_progress=show_progress)
        t2 = time.perf_counter()
        counts = constrain_to_rays(shot, npz_member(work / "first" / "meshes.npz", "vertices"), work / CONSTRAINED)
        t3 = time.perf_counter()
        forget_shots()  # the first pass's shot: not kept beside the second's
        shot = Shot(index_dir, work / CONSTRAINED, options)
        tally, solve2, write2 = write_shot(shot, out, options, shot.constrained_file, show_progress)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    s = tally.result(shot, out, {"load": t1 - t0, "solve": solve1 + solve2, "rays": t3 - t2,
                                 "write": write1 + write2})
    return {**s, **counts}


def write_shot(shot: Shot, out: str | Path, options: ReconstructOptions, constrained: Path | None = None,
               show_progress: bool = False, resume: str | None = None) -> tuple[ShotSummary, float, float]:
    """Solve ``shot`` in blocks of :data:`BLOCK_FRAMES` frames and write each as it comes
    (:func:`reconstruction_outputs`); returns the summary gathered on the way and the seconds spent solving and
    writing. With ``resume`` (the job's key, :func:`~lgi.jobs.reconstruct.outputs.resume_key`), a checkpoint
    every :data:`CHECKPOINT_SECONDS`, and a stopped run of the same job goes on from its last one: the outputs
    are those of a run never stopped, bit for bit."""
    writing = 0.0
    tally = ShotSummary(shot.index.n_markers)
    start = time.perf_counter()
    with reconstruction_outputs(out, shot.frames, shot.index.arrays, options, shot.index.jaw_rig() is not None,
                                constrained, resume) as writer:
        first, carried = 0, None
        if writer.resumed is not None:
            tally.restore(*writer.resumed["summary"])
            first, carried = writer.resumed["done"], writer.resumed["carried"]
            tally.resumed_from = first
        saved = time.monotonic()
        for res, carry in shot.stream_from(BLOCK_FRAMES, show_progress, first, carried):
            t = time.perf_counter()
            writer.append(res)
            tally.add(res)
            if resume and writer.done < shot.n_frames and time.monotonic() - saved >= CHECKPOINT_SECONDS:
                writer.checkpoint(tally.state(), carry)
                saved = time.monotonic()
            writing += time.perf_counter() - t
        t = time.perf_counter()
        writer.close(shot.solver.noise, shot.noise.estimate)
    end = time.perf_counter()
    writing += end - t
    return tally, end - start - writing, writing
