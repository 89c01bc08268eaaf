"""What a reconstruction writes (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv``, ``run.json`` and the
asked extras): the one writer, its per-frame table, and the output folder's check before any work."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.rays import CONSTRAINED

#: Every entry a reconstruction writes into its output directory (see :func:`lgi.io.atomic.job_outputs`).
OUTPUTS = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json", "per_frame.png", "shot.usdc", "obj",
           "bundles_constrained.parquet")
#: What the output folders hold (anything else there is someone else's: the run refuses to replace it).
OUTPUT_CONTENTS = {"obj": ("frame_*.obj", "*.mtl")}


def check_output(out: str | Path, inputs: tuple[Any, ...] = ()) -> None:
    """Refuse, before any work, an output path that cannot become the job's directory, or whose outputs would
    replace one of the run's ``inputs`` (index, bundles, jaw file)."""
    from lgi.io.atomic import check_contents
    from lgi.io.atomic import check_output as check

    check(out, "dir")
    check_contents(out, OUTPUT_CONTENTS)
    for name in OUTPUTS:
        check(Path(out) / name, "dir" if name == "obj" else "file", inputs=inputs)


def per_frame_table(diagnostics: pd.DataFrame) -> pd.DataFrame:
    """Per frame: share of bundles contained, bundles projected and missing, largest distance to the bundles
    before and after the correction (mm)."""
    d = diagnostics
    frames, inv = np.unique(d.frame.to_numpy(), return_inverse=True)
    n = np.bincount(inv)
    status = d.status.to_numpy()

    def count(mask: np.ndarray) -> np.ndarray:
        return np.bincount(inv, weights=mask.astype(np.float64), minlength=len(frames))

    def worst(col: str) -> np.ndarray:
        out = np.full(len(frames), -np.inf)
        v = d[col].to_numpy(np.float64)
        ok = np.isfinite(v)
        np.maximum.at(out, inv[ok], v[ok])
        return np.where(np.isfinite(out), out, np.nan)

    return pd.DataFrame({"frame": frames, "contained": count(status == "contained") / n,
                         "projected": count(status == "projected").astype(np.int64),
                         "missing": count(np.isin(status, ["missing", "bridged"])).astype(np.int64),
                         "residual_before_mm": worst("residual_before_mm"), "residual_mm": worst("residual_mm")})


def plot_per_frame(per_frame: pd.DataFrame, path: Path) -> None:
    """The per-frame table as a two-panel PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(2, 1, figsize=(8, 4.5), sharex=True)
    ax[0].plot(per_frame.frame, per_frame.residual_before_mm, label="max distance to bundles before correction")
    ax[0].set_ylabel("mm")
    ax[0].legend(fontsize=8)
    ax[1].plot(per_frame.frame, per_frame.projected, label="bundles projected (outside the data)")
    ax[1].plot(per_frame.frame, per_frame.missing, label="bundles missing or bridged")
    ax[1].set_xlabel("frame")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def run_record(options: ReconstructOptions, noise_mm: float | None, estimate=None) -> dict[str, Any]:
    """What a reconstruction was made with, stored beside it as ``run.json`` so that a later ``lgi review`` shows
    it: the method and options (not the scheduling: the results do not depend on it), the noise used and, when
    it was estimated, the estimate (mm, and per axis x, y, z) and its neighbour coherence. Nothing that varies
    between runs of the same job (no times, no absolute paths): the flow and the command line write the same
    file."""
    from lgi import __version__

    def number(x: float | None) -> float | None:  # JSON has no NaN: an estimate that failed is null
        return None if x is None or not math.isfinite(float(x)) else float(x)

    opts = {k: v for k, v in options.to_json().items() if k != "chunk_size"}
    return {"lgi": __version__, "method": options.method, "options": opts, "noise_mm": number(noise_mm),
            "noise_estimated": estimate is not None,
            "noise_estimate_mm": None if estimate is None else number(estimate.noise_mm),
            "noise_estimate_axes_mm": None if estimate is None else [number(v) for v in estimate.axis_mm],
            "noise_coherence": None if estimate is None else number(estimate.coherence)}


def write_reconstruction(out: str | Path, res, arrays: dict[str, np.ndarray], options: ReconstructOptions,
                         constrained: Path | None = None, noise_estimate=None) -> None:
    """The one writer of a reconstruction: ``meshes.npz`` (vertices (F, V, 3) float32 cm, frames, jaw (F, 4)
    with a rig), ``diagnostics.csv``, ``per_frame.csv``, ``run.json`` (:func:`run_record`; ``noise_estimate``
    is the solver's :class:`~lgi.solve.noise.NoiseEstimate` when it estimated one) and, as asked, ``obj/``,
    ``shot.usdc``,
    ``per_frame.png`` and ``bundles_constrained.parquet`` (the bundles with the rays' points: ``constrained``);
    through :func:`lgi.io.atomic.job_outputs` (an earlier run's outputs not written now are
    removed)."""
    from lgi._stages import stage as debug_stage
    from lgi.io.atomic import job_outputs
    from lgi.io.csvio import write_csv
    from lgi.io.npz import save_npz

    with job_outputs(out, OUTPUTS, OUTPUT_CONTENTS) as stage:
        debug_stage("write")
        extra = {} if res.jaw is None else {"jaw": res.jaw.astype(np.float32)}
        save_npz(stage / "meshes.npz", vertices=res.vertices, frames=res.frames, **extra)
        write_csv(res.diagnostics, stage / "diagnostics.csv")
        per_frame = per_frame_table(res.diagnostics)
        per_frame.to_csv(stage / "per_frame.csv", index=False, float_format="%.6g")
        record = run_record(options, getattr(res, "noise", None), noise_estimate)
        (stage / "run.json").write_text(json.dumps(record, indent=1, sort_keys=True, allow_nan=False) + "\n")
        if options.plot:
            plot_per_frame(per_frame, stage / "per_frame.png")
        if options.obj:
            from lgi.io.obj import write_obj

            (stage / "obj").mkdir()
            for f, frame in enumerate(res.frames):
                write_obj(stage / "obj" / f"frame_{int(frame):05d}.obj", res.vertices[f], arrays["face_vertices"],
                          arrays["face_offsets"], arrays.get("uvs"), arrays.get("face_uvs"))
        if constrained is not None:
            shutil.copyfile(constrained, stage / CONSTRAINED)
        if options.usd:
            from lgi.export.formats import write_usd

            write_usd(stage / "shot.usdc", res.vertices, arrays["face_vertices"], arrays["face_offsets"],
                      arrays.get("uvs"), arrays.get("face_uvs"), res.frames, fps=options.fps)
