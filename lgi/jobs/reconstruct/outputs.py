"""What a reconstruction writes (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv``, ``run.json`` and the
asked extras): the one writer, its per-frame table, and the output folder's check before any work."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi import __version__
from lgi._debug_stages import stage as debug_stage
from lgi.export.clips import USD_CLIP_CONTENTS
from lgi.io.atomic import RESUME_FILE, check_job_folder, job_outputs, staged_key
from lgi.io.csvio import CsvAppender
from lgi.io.npz import NpzWriter, load_npz, save_npz
from lgi.io.stored import StoredArray
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.rays import CONSTRAINED

#: Every entry a reconstruction writes into its output directory (see :func:`lgi.io.atomic.job_outputs`).
log = logging.getLogger(__name__)

OUTPUTS = ("meshes.npz", "diagnostics.csv", "per_frame.csv", "run.json", "per_frame.png", "shot.usdc", "shot.clips",
           "obj", "bundles_constrained.parquet", "shot.blender.py")
#: What the output folders hold (anything else there is someone else's: the run refuses to replace it).
OUTPUT_CONTENTS = {"obj": ("frame_*.obj", "*.mtl"), "shot.clips": USD_CLIP_CONTENTS}


def check_outputs(out: str | Path, inputs: tuple[Any, ...] = ()) -> None:
    """Refuse, before any work, an output path that cannot become the job's directory, or whose outputs would
    replace one of the run's ``inputs`` (index, bundles, jaw file)."""
    check_job_folder(out, OUTPUTS, OUTPUT_CONTENTS, inputs)


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


def _durable(path: Path, write) -> None:
    """``write(tmp)`` then ``tmp`` synced and renamed to ``path``: the file is whole or the old one."""
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def resume_key(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> str:
    """What a run's outputs depend on, as a key a stopped run's checkpoint is matched by: lgi's version, the
    options (not the scheduling), the bundles' and the given files' content, the index's files by size and time."""

    h = hashlib.sha256(json.dumps([__version__, {k: v for k, v in options.to_json().items() if k != "chunk_size"}],
                                  sort_keys=True, default=str).encode())
    given = [bundles, *(p for p in (options.jaw, options.observations, options.calib, options.contours)
                        if p not in (None, "auto", "none"))]
    for p in given:
        path = Path(p)
        if path.is_file():
            with open(path, "rb") as fh:
                for chunk in iter(lambda fh=fh: fh.read(1 << 20), b""):
                    h.update(chunk)
        h.update(str(path.resolve()).encode())
    for f in sorted(Path(index_dir).iterdir()):
        if f.is_file():
            st = f.stat()
            h.update(f"{f.name}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()


@contextlib.contextmanager
def reconstruction_outputs(out: str | Path, frames: np.ndarray, arrays: dict[str, np.ndarray],
                           options: ReconstructOptions, with_jaw: bool, constrained: Path | None = None,
                           resume: str | None = None) -> Iterator[ReconstructionWriter]:
    """A :class:`ReconstructionWriter` staging a reconstruction of ``frames`` for ``out``, through
    :func:`lgi.io.atomic.job_outputs`: the outputs replace an earlier run's only once it is closed, and an
    error or interrupt leaves ``out`` as it was (an earlier run's outputs not written now are removed).

    ``resume``: the job's key (:func:`resume_key`). A run of the same job stopped after a checkpoint
    (:meth:`ReconstructionWriter.checkpoint`) is taken over: the writer starts where it stopped
    (:attr:`ReconstructionWriter.resumed`)."""
    with job_outputs(out, OUTPUTS, OUTPUT_CONTENTS, resume) as stage:
        writer = ReconstructionWriter(stage, frames, arrays, options, with_jaw, constrained, resume)
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
                 options: ReconstructOptions, with_jaw: bool, constrained: Path | None = None,
                 resume: str | None = None) -> None:
        self.stage, self.frames, self.arrays, self.options = stage, np.asarray(frames), arrays, options
        self.constrained = constrained
        self.done = 0
        self.closed = False
        self._key = resume
        #: A stopped run's state this writer goes on from (None: a new run): ``done`` frames written, the
        #: ``summary`` counts (:meth:`ShotSummary.state`) and the ``carried`` choices the next block reads.
        self.resumed: dict[str, Any] | None = None
        saved = self._saved_state() if resume else None
        partial = stage / ".meshes.partial"
        if saved is not None:
            os.replace(stage / "meshes.npz", partial)
        self._npz = NpzWriter(stage / "meshes.npz")
        self._npz.begin("vertices", (len(self.frames), len(arrays["neutral"]), 3), np.float32)
        self._jaw: list[np.ndarray] | None = [] if with_jaw else None
        self._per_frame: list[pd.DataFrame] = []
        if saved is None:
            self._csv = CsvAppender(stage / "diagnostics.csv")
            if options.obj:
                (stage / "obj").mkdir()
            return
        info, a = saved
        done = int(info["done"])
        # The frames written before the stop, copied from where they are into a new archive (its entry's size
        # is in its header, and the rows follow on).

        old = StoredArray(partial, int(info["rows_offset"]), (done, len(arrays["neutral"]), 3), np.float32)
        for lo in range(0, done, 64):
            self._npz.write(old[lo:lo + 64])
        partial.unlink()
        self._csv = CsvAppender(stage / "diagnostics.csv", (int(info["csv_bytes"]), a["csv_schema"].tobytes()))
        self._per_frame = [pd.DataFrame({c: a[f"per_frame_{c}"] for c in info["per_frame_columns"]})]
        if self._jaw is not None:
            self._jaw = [a["jaw"]]
        from lgi.jobs.reconstruct.chunks import load_choices

        self.done = done
        summary = {k[len("summary_"):]: a[k] for k in a if k.startswith("summary_")}
        self.resumed = {"done": done, "summary": (info["summary"], summary),
                        "carried": (int(info["carried_first"]), load_choices(stage / info["choices"]))}
        log.info("resuming %s from frame %d of %d (a stopped run's)", stage.parent, done, len(self.frames))

    def _saved_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]] | None:
        """The checkpoint a stopped run of this job left in the staging folder, or None."""
        if staged_key(self.stage) != self._key:
            return None
        info = json.loads((self.stage / RESUME_FILE).read_text())
        if int(info.get("frames", -1)) != len(self.frames) or not (self.stage / "meshes.npz").is_file():
            return None
        return info, load_npz(self.stage / info["state"])

    def checkpoint(self, summary: tuple[dict[str, Any], dict[str, np.ndarray]], carried: tuple[int, list]) -> None:
        """Make the frames written so far durable and note how to go on from them, so that a run stopped after
        this (killed, or interrupted) is resumed by the same command (``resume`` key): the meshes' rows and the
        diagnostics flushed and synced, and beside them the per-frame rows, jaw, ``summary``
        (:meth:`ShotSummary.state`) and the ``carried`` choices (``(first, choices)``, what the next block reads).
        The note (:data:`~lgi.io.atomic.RESUME_FILE`) is written last and replaced whole: a stop at any moment
        leaves the last complete checkpoint."""
        from lgi.jobs.reconstruct.chunks import save_choices

        if self._key is None or not self.done:
            return
        rows = self._npz.flush()
        csv_bytes, schema = self._csv.flush()
        per_frame = pd.concat(self._per_frame, ignore_index=True)
        self._per_frame = [per_frame]
        tag = f".resume-{self.done:09d}"
        arrays = {f"per_frame_{c}": per_frame[c].to_numpy() for c in per_frame.columns}
        arrays["csv_schema"] = np.frombuffer(schema, np.uint8)
        if self._jaw is not None:
            self._jaw = [np.concatenate(self._jaw)]
            arrays["jaw"] = self._jaw[0]
        arrays.update({f"summary_{k}": v for k, v in summary[1].items()})
        _durable(self.stage / f"{tag}.npz", lambda p: save_npz(p, **arrays))
        _durable(self.stage / f"{tag}-choices.npz", lambda p: save_choices(p, carried[1], durable=False))
        info = {"key": self._key, "frames": len(self.frames), "done": self.done, "rows_offset": self._npz.rows_offset,
                "rows": rows, "csv_bytes": csv_bytes, "per_frame_columns": list(per_frame.columns),
                "summary": summary[0], "carried_first": int(carried[0]), "state": f"{tag}.npz",
                "choices": f"{tag}-choices.npz"}
        _durable(self.stage / RESUME_FILE, lambda p: p.write_text(json.dumps(info)))
        for old in self.stage.glob(".resume-*"):
            if not old.name.startswith(tag):
                old.unlink(missing_ok=True)

    def append(self, res) -> None:
        """Write the next block of frames (a :class:`~lgi.solve.results.SequenceResult` of frames following the
        last block's)."""
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
        for note in self.stage.glob(".resume*"):  # every frame is written: nothing to go on from
            note.unlink()
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
                      fps=self.options.fps, convention=self.options.convention)
            from lgi.export.blender import for_blender, write_blender_script

            if for_blender(self.options.convention):
                # Named by its place after the commit (the staging folder's parent is the output folder).
                write_blender_script(self.stage.parent / "shot.usdc", self.options.fps, int(self.frames[0]),
                                     int(self.frames[-1]), path=self.stage / "shot.blender.py")
        self.closed = True

    def abandon(self) -> None:
        """Close the files of a run that stopped (the staging folder is then removed)."""
        with contextlib.suppress(Exception):
            self._npz.abort()
        with contextlib.suppress(Exception):
            self._csv.close()
