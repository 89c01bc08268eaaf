"""The reconstruct-shot flow's stages over chunks of frames: choose, finish, assemble; the prepared shot kept once
per process, and the chunk files (choices, finished parts) they hand on."""

from __future__ import annotations

import json
import os
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.errors import InputError, collected_warnings
from lgi.io.atomic import atomic_file
from lgi.io.npz import load_npz, save_npz
from lgi.jobs.reconstruct.options import ReconstructOptions
from lgi.jobs.reconstruct.outputs import reconstruction_outputs
from lgi.jobs.reconstruct.shot import Shot
from lgi.jobs.reconstruct.summary import ShotSummary


def replace_outputs(options: ReconstructOptions) -> ReconstructOptions:
    """``options`` for a first pass whose files are not the job's outputs: no OBJ, USD or plot."""
    return replace(options, obj=False, usd=False, plot=False)


def save_choices(path: str | Path, sels: list, durable: bool = True) -> None:
    """Write frames' choices to an npz, exactly (every field a later frame or the finish reads); ``durable``:
    flushed to disk before it appears (see :func:`lgi.io.atomic.atomic_file`)."""
    from lgi.solve.surface import _stack_slots

    a: dict[str, np.ndarray] = {}
    a["width"] = np.array([r.shapes.shape[1] for r in sels], np.int64)
    a["shapes"], a["weights"] = _stack_slots([r.shapes for r in sels], [r.weights for r in sels])
    for k in ("n_containing", "status", "projection", "score", "residual", "bundles", "simplex_shapes",
              "simplex_weights"):
        a[k] = np.stack([getattr(r, k) for r in sels])
    a["source"] = np.stack([np.asarray(r.source, object).astype(str) for r in sels])
    a["fallback"] = np.array(json.dumps([r.fallback for r in sels]))
    if sels[0].jaw is not None:
        a["jaw"] = np.stack([r.jaw for r in sels])
    if sels[0].far_share is not None:
        a["far_share"] = np.stack([r.far_share for r in sels])
    a["fit_weights"] = np.stack([r.fit.weights for r in sels])
    a["fit_residual"] = np.stack([r.fit.residual for r in sels])
    a["fit_rms"] = np.array([r.fit.rms for r in sels], np.float64)
    a["fit_jaw_source"] = np.array([r.fit.jaw_source for r in sels])
    if sels[0].fit.jaw is not None:
        a["fit_jaw"] = np.stack([r.fit.jaw for r in sels])
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, suffix=".npz", durable=durable) as tmp:
        save_npz(tmp, **a)


def load_choices(path: str | Path) -> list:
    """The choices :func:`save_choices` wrote."""
    from lgi.solve.globalfit import GlobalFitResult
    from lgi.solve.results import FrameResult

    a = load_npz(path)
    notes = json.loads(str(a["fallback"]))
    out = []
    for f, k in enumerate(a["width"]):
        fit = GlobalFitResult(a["fit_weights"][f], a["fit_jaw"][f] if "fit_jaw" in a else None,
                              a["fit_residual"][f], float(a["fit_rms"][f]), str(a["fit_jaw_source"][f]))
        out.append(FrameResult(
            vertices=np.zeros((0, 3), np.float32), shapes=a["shapes"][f, :, :k], weights=a["weights"][f, :, :k],
            n_containing=a["n_containing"][f], status=a["status"][f], projection=a["projection"][f],
            score=a["score"][f], residual=a["residual"][f], fallback=notes[f],
            jaw=a["jaw"][f] if "jaw" in a else None, bundles=a["bundles"][f], source=a["source"][f].astype(object),
            fit=fit, simplex_shapes=a["simplex_shapes"][f], simplex_weights=a["simplex_weights"][f],
            far_share=a["far_share"][f] if "far_share" in a else None))
    return out


_SHOTS: dict[str, Shot] = {}
_SHOTS_LOCK = threading.Lock()


def _fingerprint(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> str:
    """What a prepared shot depends on: the index's and the bundles' (and a jaw file's) paths, sizes and
    modification times, and the options. A file that is not there counts as such: preparing the shot then says
    what is wrong with the input (an index folder without its manifest is not an LGI index)."""
    files = [Path(index_dir) / n for n in ("manifest.json", "index.npz", "deltas.npy")] + [Path(bundles)]
    if options.jaw not in ("auto", "none"):
        files.append(Path(options.jaw))
    stats = []
    for f in files:
        try:
            st = f.stat()
        except OSError:
            stats.append([str(f.absolute()), None, None])
            continue
        stats.append([str(f.resolve()), st.st_size, st.st_mtime_ns])
    return json.dumps([stats, options.to_json()], sort_keys=True)


def prepared_shot(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> Shot:
    """The shot prepared once per process and reused by every chunk task that runs there (the index loaded,
    the bundles read, bridged and denoised, the noise estimated): a flow's tasks on Prefect's threads share one,
    each Dask worker process prepares its own. A changed input file makes a new one. The solver is only read
    while chunks are chosen and finished, so the tasks may share it."""
    key = _fingerprint(index_dir, bundles, options)
    with _SHOTS_LOCK:
        shot = _SHOTS.get(key)
        if shot is None:
            _SHOTS.clear()  # one shot at a time per process: a worker moves from shot to shot
            shot = _SHOTS[key] = Shot(index_dir, bundles, options)
    return shot


def preflight(index_dir: str | Path, bundles: str | Path, options: ReconstructOptions) -> int:
    """Check the inputs of a reconstruction before any work is scheduled (the index loads, the bundles name its
    markers, the jaw option suits the index, a jaw file covers every frame); returns the number of frames.

    The checks are those of preparing the shot, which is kept (:func:`prepared_shot`): the flow's chunk tasks in
    this process then start from it instead of preparing it again."""
    shot = prepared_shot(index_dir, bundles, options)
    if shot.index.jaw_rig() is not None and options.jaw == "none":
        raise InputError("the index was built with a jaw rig (its shapes are unskinned): use --jaw auto or a jaw "
                         "file, or rebuild the index without a rig", path=index_dir)
    if options.observations:
        from lgi.capture.observations import read_rays

        read_rays(options.observations, shot.index.marker_names, shot.frames,
                  shot.seen, options.calib)
    return shot.n_frames  # contours: read and checked when the shot is prepared


def forget_shots() -> None:
    """Drop this process's prepared shot and remembered chunk files (the next task prepares the shot again)."""
    with _SHOTS_LOCK:
        _SHOTS.clear()
        _MEMO.clear()
        _PARTS.clear()
        _PARTS_BYTES[0] = 0


def choose_chunk(index_dir: str, bundles: str, options: ReconstructOptions, lo: int, hi: int, out: str,
                 previous: str | None = None) -> str:
    """Choose frames lo:hi (continuing from the last choice in the ``previous`` chunk's file); write them to
    ``out`` (npz). Chained over a shot's chunks, the choices are those a single pass makes."""
    shot = prepared_shot(index_dir, bundles, options)
    prev = _recall(previous, load_choices)[-1] if previous else None
    sels = shot.choose(lo, hi, prev)
    save_choices(out, sels, durable=False)
    _remember(out, sels)
    return out


# The chunk files a process wrote, kept in memory for its own tasks that read them next (the flow's tasks on
# Prefect's threads): the files hold the same values exactly, so a task in another process (Dask) reads the
# same. Keyed by path, size and modification time, so a file written again is read again.
_MEMO: OrderedDict[str, tuple[tuple[int, int], Any]] = OrderedDict()
# The flow hands chunks out a few ahead of need (lgi.orchestration.reconstruct.CHOOSING, FINISHING), so its tasks
# read the last few choice files written; kept beyond that, the choices grew a 9,000-frame ICT take's peak (64
# kept: 1.23x that of 1,000 frames).
_MEMO_KEPT = 16


def _file_key(path: str | Path) -> tuple[int, int]:
    st = Path(path).stat()
    return st.st_size, st.st_mtime_ns


def _remember(path: str | Path, value: Any) -> None:
    with _SHOTS_LOCK:
        _MEMO[str(path)] = (_file_key(path), value)
        while len(_MEMO) > _MEMO_KEPT:
            _MEMO.popitem(last=False)


def _recall(path: str | Path, load: Callable[[str | Path], Any]) -> Any:
    """What ``path`` holds: from memory when this process wrote that very file, else ``load(path)``."""
    with _SHOTS_LOCK:
        hit = _MEMO.get(str(path))
    if hit is not None and hit[0] == _file_key(path):
        return hit[1]
    return load(path)


def finish_chunk(index_dir: str, bundles: str, options: ReconstructOptions, choices: list[str], lo: int, hi: int,
                 out: str, first: int = 0, keep: bool = False) -> str:
    """Blend, skin and correct frames lo:hi from the choice files ``choices`` (consecutive chunks from frame
    ``first``, covering :meth:`Shot.needs`; by default the whole shot's); write the part to ``out``
    (:func:`save_part`), or with ``keep`` hold it in this process's memory under that name for
    :func:`assemble` in the same process (a flow on threads: the same values, without the disk), while the parts
    held stay within :data:`PARTS_KEPT_BYTES`. The warnings logged while finishing go with the part: a chunk
    finished in another process logs them there."""
    shot = prepared_shot(index_dir, bundles, options)
    sels = [s for path in choices for s in _recall(path, load_choices)]
    with collected_warnings(this_thread=True) as warned:
        res = shot.finish(sels, lo, hi, first=first)
    part = (res.vertices, res.jaw, res.diagnostics, warned)
    size = res.vertices.nbytes + int(res.diagnostics.memory_usage(deep=False).sum())
    with _SHOTS_LOCK:
        # Held in memory up to a budget, on disk beyond: a long take's finished chunks wait for the writer there.
        keep = keep and _PARTS_BYTES[0] + size <= PARTS_KEPT_BYTES
        if keep:
            _PARTS[str(out)] = (part, size)
            _PARTS_BYTES[0] += size
    if not keep:
        save_part(out, *part)
    return out


#: Finished chunks of a flow on threads are handed to the writer in memory up to this many bytes, through files
#: beyond: memory stays bounded however long the take. The writer runs once every chunk is finished, so the
#: chunks kept wait for the whole run: at 256 MiB a 1,000-frame ICT take (320 MiB of meshes) had barely filled
#: them, and longer takes peaked 1.10x higher. A few chunks' worth keeps the peak flat from short takes on.
PARTS_KEPT_BYTES = 64 * 2**20
# Finished chunks kept in memory (finish_chunk's ``keep``) until assemble takes them, or forget_parts; and their
# total size.
_PARTS: dict[str, tuple[tuple[np.ndarray, np.ndarray | None, pd.DataFrame, list[str]], int]] = {}
_PARTS_BYTES = [0]


def forget_parts(folder: str | Path) -> None:
    """Drop the finished chunks kept in memory under ``folder`` (a failed or interrupted run's)."""
    prefix = str(Path(folder)) + os.sep
    with _SHOTS_LOCK:
        for k in [k for k in _PARTS if k.startswith(prefix)]:
            _PARTS_BYTES[0] -= _PARTS.pop(k)[1]


def save_part(path: str | Path, vertices: np.ndarray, jaw: np.ndarray | None, diagnostics: pd.DataFrame,
              warnings: list[str] = ()) -> None:
    """Write a finished chunk: its vertices ((F, V, 3) float32, cm), the jaw used ((F, 6), if any) and the
    warnings logged while finishing it to ``path`` (npz), its rows of ``diagnostics.csv`` beside it (the same
    name, .parquet)."""
    with atomic_file(Path(path).with_suffix(".parquet"), durable=False) as tmp:
        diagnostics.to_parquet(tmp, index=False)
    with atomic_file(path, suffix=".npz", durable=False) as tmp:
        save_npz(tmp, vertices=vertices, warnings=np.array(list(warnings), dtype=str),
                 **({} if jaw is None else {"jaw": jaw}))


def load_part(path: str | Path) -> tuple[np.ndarray, np.ndarray | None, pd.DataFrame, list[str]]:
    """The finished chunk :func:`save_part` wrote: vertices, jaw (or None), diagnostics and warnings."""
    a = load_npz(path)
    return (a["vertices"], a.get("jaw"), pd.read_parquet(Path(path).with_suffix(".parquet")),
            [str(w) for w in a.get("warnings", ())])


def assemble(index_dir: str, bundles: str, options: ReconstructOptions, parts: list[str],
             out: str) -> dict[str, Any]:
    """Write the finished chunks (in frame order) as the shot's outputs, one after another
    (:func:`reconstruction_outputs`: a chunk at a time in memory); returns the summary, with the warnings
    logged while finishing the chunks as ``chunk_warnings``."""
    from lgi.solve.results import SequenceResult

    t0 = time.perf_counter()
    shot = prepared_shot(index_dir, bundles, options)
    tally = ShotSummary(shot.index.n_markers)
    done = 0
    warned: list[str] = []
    with reconstruction_outputs(out, shot.frames, shot.index.arrays, options, shot.index.jaw_rig() is not None,
                                shot.constrained_file) as writer:
        for path in parts:
            with _SHOTS_LOCK:
                kept = _PARTS.pop(str(path), None)
                if kept is not None:
                    _PARTS_BYTES[0] -= kept[1]
            vertices, jaw, diag, said = load_part(path) if kept is None else kept[0]
            warned += said
            res = SequenceResult(np.asarray(shot.frames[done:done + len(vertices)]), vertices, diag, jaw,
                                 shot.solver.noise, options.smooth)
            writer.append(res)
            tally.add(res)
            done += len(vertices)
        writer.close(shot.solver.noise, shot.noise.estimate)
    return {**tally.result(shot, out, {"finish": time.perf_counter() - t0}), "chunk_warnings": warned}
