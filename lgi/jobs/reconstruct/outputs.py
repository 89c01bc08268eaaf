"""What a reconstruction writes (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv``, ``run.json`` and the
asked extras): the one writer, its per-frame table, and the output folder's check before any work."""

from __future__ import annotations

import contextlib
import json
import math
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.export.clips import USD_CLIP_CONTENTS
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.rays import CONSTRAINED

#: Every entry a reconstruction writes into its output directory (see :func:`lgi.io.atomic.job_outputs`).
OUTPUTS = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json", "per_frame.png", "shot.usdc", "shot.clips",
           "obj", "bundles_constrained.parquet")
#: What the output folders hold (anything else there is someone else's: the run refuses to replace it).
OUTPUT_CONTENTS = {"obj": ("frame_*.obj", "*.mtl"), "shot.clips": USD_CLIP_CONTENTS}


def check_output(out: str | Path, inputs: tuple[Any, ...] = ()) -> None:
    """Refuse, before any work, an output path that cannot become the job's directory, or whose outputs would
    replace one of the run's ``inputs`` (index, bundles, jaw file)."""
    from lgi.io.atomic import check_contents
    from lgi.io.atomic import check_output as check

    check(out, "dir")
    check_contents(out, OUTPUT_CONTENTS)
    for name in OUTPUTS:
        check(Path(out) / name, "dir" if name in OUTPUT_CONTENTS else "file", inputs=inputs)


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
    """A whole reconstruction ``res`` (a :class:`~lgi.solve.results.SequenceResult`) written into ``out`` as one
    block of :class:`ReconstructionWriter` (see there for the files)."""
    with reconstruction_outputs(out, res.frames, arrays, options, res.jaw is not None, constrained) as writer:
        writer.append(res)
        writer.close(getattr(res, "noise", None), noise_estimate)


@contextlib.contextmanager
def reconstruction_outputs(out: str | Path, frames: np.ndarray, arrays: dict[str, np.ndarray],
                           options: ReconstructOptions, with_jaw: bool, constrained: Path | None = None
                           ) -> Iterator[ReconstructionWriter]:
    """A :class:`ReconstructionWriter` staging a reconstruction of ``frames`` for ``out``, through
    :func:`lgi.io.atomic.job_outputs`: the outputs replace an earlier run's only once it is closed, and an
    error or interrupt leaves ``out`` as it was (an earlier run's outputs not written now are removed)."""
    from lgi.io.atomic import job_outputs

    with job_outputs(out, OUTPUTS, OUTPUT_CONTENTS) as stage:
        writer = ReconstructionWriter(stage, frames, arrays, options, with_jaw, constrained)
        try:
            yield writer
        except BaseException:
            writer.abandon()
            raise
        if not writer.closed:
            writer.abandon()
            raise RuntimeError("the reconstruction's writer was not closed")


class ReconstructionWriter:
    """The one writer of a reconstruction, block of frames by block, into a staging folder: ``meshes.npz``
    (vertices (F, V, 3) float32 cm, frames, jaw (F, 4) with a rig), ``diagnostics.csv``, ``per_frame.csv``,
    ``run.json`` (:func:`run_record`) and, as asked, ``obj/``, ``shot.usdc``, ``per_frame.png`` and
    ``bundles_constrained.parquet`` (the bundles with the rays' points: ``constrained``).

    Each block's surfaces go to disk as they come (:class:`lgi.io.npz.NpzWriter`; the same bytes as the whole
    shot written at once), its diagnostics rows are appended, and only per-frame rows stay in memory, so a long
    take is written in memory bounded by a block. Use :func:`reconstruction_outputs`.

    Parameters
    ----------
    stage : Path
        The staging folder (:func:`lgi.io.atomic.job_outputs`).
    frames : (F,) int
        The shot's frame numbers; blocks come in this order.
    arrays : dict
        The index's arrays (faces and UVs for OBJ and USD).
    options : ReconstructOptions
    with_jaw : bool
        Whether the blocks carry jaw parameters (an index with a rig).
    """

    def __init__(self, stage: Path, frames: np.ndarray, arrays: dict[str, np.ndarray],
                 options: ReconstructOptions, with_jaw: bool, constrained: Path | None = None) -> None:
        from lgi.io.csvio import CsvAppender
        from lgi.io.npz import NpzWriter

        self.stage, self.frames, self.arrays, self.options = stage, np.asarray(frames), arrays, options
        self.constrained = constrained
        self.done = 0
        self.closed = False
        self._npz = NpzWriter(stage / "meshes.npz")
        self._npz.begin("vertices", (len(self.frames), len(arrays["neutral"]), 3), np.float32)
        self._jaw: list[np.ndarray] | None = [] if with_jaw else None
        self._csv = CsvAppender(stage / "diagnostics.csv")
        self._per_frame: list[pd.DataFrame] = []
        if options.obj:
            (stage / "obj").mkdir()

    def append(self, res) -> None:
        """Write the next block of frames (a :class:`~lgi.solve.results.SequenceResult` of frames following the
        last block's)."""
        from lgi._stages import stage as debug_stage

        n = len(res.frames)
        if not np.array_equal(res.frames, self.frames[self.done:self.done + n]):
            raise RuntimeError(f"block of frames {res.frames[:1]}... does not follow frame {self.done} of the shot")
        if self.done == 0:
            debug_stage("write")
        self._npz.write(np.asarray(res.vertices, np.float32))
        if self._jaw is not None:
            self._jaw.append(np.asarray(res.jaw, np.float32))
        self._csv.append(res.diagnostics)
        self._per_frame.append(per_frame_table(res.diagnostics))
        if self.options.obj:
            from lgi.io.obj import write_obj

            a = self.arrays
            for f, frame in enumerate(res.frames):
                write_obj(self.stage / "obj" / f"frame_{int(frame):05d}.obj", res.vertices[f], a["face_vertices"],
                          a["face_offsets"], a.get("uvs"), a.get("face_uvs"))
        self.done += n

    def close(self, noise_mm: float | None, noise_estimate=None) -> None:
        """Finish the files once every frame is written: the meshes' frames and jaw, the per-frame table (and
        plot), ``run.json``, and the asked USD and constrained bundles."""
        if self.done != len(self.frames):
            raise RuntimeError(f"{self.done} of the shot's {len(self.frames)} frames written")
        self._npz.end()
        self._npz.add("frames", self.frames)
        if self._jaw is not None:
            self._npz.add("jaw", np.concatenate(self._jaw))
        self._npz.close()
        self._csv.close()
        per_frame = pd.concat(self._per_frame, ignore_index=True)
        per_frame.to_csv(self.stage / "per_frame.csv", index=False, float_format="%.6g")
        record = run_record(self.options, noise_mm, noise_estimate)
        (self.stage / "run.json").write_text(json.dumps(record, indent=1, sort_keys=True, allow_nan=False) + "\n")
        if self.options.plot:
            plot_per_frame(per_frame, self.stage / "per_frame.png")
        if self.constrained is not None:
            shutil.copyfile(self.constrained, self.stage / CONSTRAINED)
        if self.options.usd:
            from lgi.export.formats import write_usd
            from lgi.io.npz import npz_member

            a = self.arrays
            write_usd(self.stage / "shot.usdc", npz_member(self.stage / "meshes.npz", "vertices"),
                      a["face_vertices"], a["face_offsets"], a.get("uvs"), a.get("face_uvs"), self.frames,
                      fps=self.options.fps)
        self.closed = True

    def abandon(self) -> None:
        """Close the files of a run that stopped (the staging folder is then removed)."""
        import contextlib

        with contextlib.suppress(Exception):
            self._npz.abort()
        with contextlib.suppress(Exception):
            self._csv.close()
