"""The whole reconstruct job in this process (``lgi reconstruct``), with the second pass through the rays of
markers seen by one camera."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.outputs import check_output, write_reconstruction
from lgi.jobs.reconstruct.rays import CONSTRAINED
from lgi.jobs.reconstruct.shot import Shot, constrain_to_rays
from lgi.jobs.reconstruct.summary import summarise


def reconstruct(index_dir: str | Path, bundles: str | Path, out: str | Path,
                options: ReconstructOptions | None = None, show_progress: bool = False) -> dict[str, Any]:
    """Reconstruct a shot in this process and write its outputs into ``out``; returns the summary
    (:func:`summarise`; :func:`report_lines` formats it).

    With ``options.observations``, twice: without the markers seen by one camera, then through their points on
    their rays (:func:`constrain_to_rays`)."""
    from lgi._stages import stage

    options = options or ReconstructOptions()
    if options.method == "blendshape":
        from lgi.jobs.reconstruct.blendshape import reconstruct_blendshape

        return reconstruct_blendshape(index_dir, bundles, out, options, show_progress)
    check_output(out, (index_dir, bundles, options.jaw, options.observations, options.calib, options.contours))
    t0 = time.perf_counter()
    shot = Shot(index_dir, bundles, options)
    t1 = time.perf_counter()
    stage("solve")
    res = shot.run(show_progress)
    t2 = time.perf_counter()
    if not options.observations:
        write_reconstruction(out, res, shot.index.arrays, options, noise_estimate=shot.solver.noise_estimate)
        return summarise(res, shot, out, {"load": t1 - t0, "solve": t2 - t1, "write": time.perf_counter() - t2})
    from lgi.io.atomic import make_temp_dir, sweep

    parent, prefix = Path(out).absolute().parent, f".{Path(out).name}.rays-"
    parent.mkdir(parents=True, exist_ok=True)
    sweep(parent, prefix)
    work = make_temp_dir(parent, prefix)
    try:
        counts = constrain_to_rays(shot, res.vertices, work / CONSTRAINED)
        t3 = time.perf_counter()
        shot = Shot(index_dir, work / CONSTRAINED, options)
        res = shot.run(show_progress)
        t4 = time.perf_counter()
        write_reconstruction(out, res, shot.index.arrays, options, shot.constrained_file,
                             noise_estimate=shot.solver.noise_estimate)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    s = summarise(res, shot, out, {"load": t1 - t0, "solve": (t2 - t1) + (t4 - t3), "rays": t3 - t2,
                                   "write": time.perf_counter() - t4})
    return {**s, **counts}
