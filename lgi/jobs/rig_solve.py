"""``lgi rig-solve``: a reconstructed shot as animation curves of the actor's rig.

The algorithm is :mod:`lgi.retarget.solve`; this job reads the reconstruction (``meshes.npz``) and the rig
(``lgi rig-generate``'s dataset, optionally its USD), checks the inputs and outputs before the work, and writes,
all at once or nothing:

``OUT_DIR/curves.csv`` (``curves.parquet`` with ``--format parquet``)
    frame, control, value: each control's weight in [0, 1] per frame (correctives are driven, not listed) and,
    for a rig with a jaw joint, its parameters as the controls :data:`JAW_CURVES` (degrees and cm).
``OUT_DIR/residuals.csv``
    frame, rms_mm, max_mm: the rig's playback against the reconstruction over the face region.
``OUT_DIR/vertex_error.npz``
    ``rms_mm`` (V,), ``max_mm`` (V,) float32: per vertex over the shot, where the rig falls short;
    ``region`` (V,) bool, the face region (the vertices the rig moves).
``OUT_DIR/vertex_error.png``
    the two maps painted on the neutral.
``OUT_DIR/solve.json``
    the options, the counts and the summary figures.
``--usd ANIM.usda`` (with ``--rig-usd``)
    a UsdSkel animation layer over the rig's USD (:mod:`lgi.export.rig_anim`).
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.io.atomic import reads
from lgi.options import declared, option

log = logging.getLogger(__name__)

OUTPUTS = ("curves.csv", "curves.parquet", "residuals.csv", "vertex_error.npz", "vertex_error.png", "solve.json")
JAW_MODES = ("fit", "fixed")
FORMATS = ("csv", "parquet")


@declared
@dataclass(frozen=True)
class RigSolveOptions:
    """Options of ``lgi rig-solve`` (:mod:`lgi.options`)."""

    smooth: float = option(
        4.0, "temporal regularisation: the period in frames whose wiggles the curves' penalty halves (zero-phase, "
        "so no lag; default %(default)s; 0: each frame fitted on its own)", group="method", metavar="FRAMES",
        units="frames")
    vertices: int = option(
        4000, "face vertices fitted per frame, an even subsample (default %(default)s; 0: every vertex the rig "
        "moves)", group="method", metavar="N")
    robust: float = option(
        3.0, "Huber threshold in multiples of each frame's median vertex residual (default %(default)s; 0: plain "
        "least squares)", group="method", metavar="TIMES")
    fps: float = option(30.0, "time codes per second of the USD animation (default %(default)s)", group="outputs",
                        metavar="F")
    jaw: str = option(
        "fit", "for a rig with a jaw joint: fit the jaw's rotation and slide (degrees, cm) per frame with the "
        "weights, started from the reconstruction's jaw, or hold them at the reconstruction's (default "
        "%(default)s)", group="method", choices=JAW_MODES)
    format: str = option(
        "csv", "the curves' file: curves.csv or curves.parquet, columns frame, control, value (weights in [0, 1]; "
        "the jaw joint's jaw_open_deg, jaw_yaw_deg, jaw_roll_deg in degrees and jaw_forward_cm in cm; default "
        "%(default)s)", group="outputs", choices=FORMATS)

    def __post_init__(self) -> None:
        if not isinstance(self.smooth, (int, float)) or not math.isfinite(self.smooth) or \
                not (self.smooth == 0 or self.smooth >= 2):
            raise InputError(f"--smooth must be 0 (none) or a period of at least 2 frames, not {self.smooth!r}")
        if isinstance(self.vertices, bool) or not isinstance(self.vertices, int) or self.vertices < 0:
            raise InputError(f"--vertices must be a whole number >= 0 (0: every face vertex), not {self.vertices!r}")
        if not isinstance(self.robust, (int, float)) or not math.isfinite(self.robust) or \
                not (self.robust == 0 or self.robust >= 1):
            raise InputError(f"--robust must be 0 (plain least squares) or at least 1, not {self.robust!r}")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise InputError(f"--fps must be a positive number, not {self.fps!r}")
        if self.jaw not in JAW_MODES:
            raise InputError(f"--jaw must be one of {', '.join(JAW_MODES)}, not {self.jaw!r}")
        if self.format not in FORMATS:
            raise InputError(f"--format must be one of {', '.join(FORMATS)}, not {self.format!r}")


def read_curves(out: str | Path, controls: list[str]) -> np.ndarray:
    """(F, len(controls)) float64: the curves ``lgi rig-solve`` wrote in ``out`` (csv or parquet), frames in
    order, the columns in the order of ``controls`` (control names, or :data:`JAW_CURVES`)."""
    import pandas as pd

    out = Path(out)
    t = pd.read_parquet(out / "curves.parquet") if (out / "curves.parquet").is_file() else \
        pd.read_csv(out / "curves.csv")
    return t.pivot(index="frame", columns="control", values="value")[list(controls)].to_numpy(np.float64)


@reads("recon_dir")
def rig_solve(recon_dir: str | Path, rig_dir: str | Path, out: str | Path, options: RigSolveOptions | None = None,
              usd: str | Path | None = None, rig_usd: str | Path | None = None,
              show_progress: bool = False) -> dict[str, Any]:
    """Solve the shot in ``recon_dir/meshes.npz`` onto the rig in ``rig_dir``; returns a summary
    (:func:`rig_solve_report`)."""
    import pandas as pd

    from lgi.dataset.shapes import ENTRIES as DATASET_ENTRIES
    from lgi.export.blender import for_blender, script_path, usd_correctives, write_blender_script
    from lgi.export.formats import usd_convention
    from lgi.io.arrays import nonfinite_frames
    from lgi.io.atomic import check_contents, check_distinct, check_not_in_store, check_output, files_in, job_outputs
    from lgi.io.npz import load_meshes
    from lgi.progress import progress
    from lgi.retarget.solve import JAW_CURVES, RigSolver, load_rig, solve_shot

    o = options or RigSolveOptions()
    src = Path(recon_dir) / "meshes.npz"
    inputs = [recon_dir, src, rig_dir, *files_in(rig_dir, DATASET_ENTRIES), rig_usd]
    if usd is not None:
        if Path(usd).suffix.lower() not in (".usd", ".usda", ".usdc"):
            raise InputError("--usd takes a .usd, .usda or .usdc file name", path=usd)
        if rig_usd is None:
            raise InputError("--usd needs --rig-usd (the rig's USD from lgi rig-generate --usd): the animation is "
                             "bound to it", path=usd)
        check_output(usd, "file", inputs=inputs)
        check_output(script_path(usd), "file", inputs=inputs)  # written when the rig is in Blender's convention
        check_not_in_store(usd, "--usd")
        check_distinct({"--out": out, "--usd": usd, "the Blender script": script_path(usd)})
    check_output(out, "dir", inputs=inputs)
    check_not_in_store(out)
    check_contents(out, None, OUTPUTS)
    if not src.is_file():
        raise InputError("no meshes.npz (run lgi reconstruct first)", path=recon_dir)
    t0 = time.perf_counter()
    rig, ds = load_rig(rig_dir)
    z = load_meshes(src, required=("vertices",))
    meshes = z["vertices"]
    frames = np.asarray(z.get("frames", np.arange(len(meshes))))
    if meshes.ndim != 3 or meshes.shape[2] != 3 or len(meshes) == 0:
        raise InputError(f"vertices has shape {meshes.shape}, not (F, V, 3) with F >= 1", path=src)
    if meshes.shape[1] != len(rig.neutral):
        raise InputError(f"the reconstruction has {meshes.shape[1]} vertices and the rig {len(rig.neutral)}: the "
                         "rig is on another mesh topology (generate it with this actor's index)", path=src)
    bad = nonfinite_frames(meshes)
    if len(bad):
        raise InputError(f"{len(bad)} frames hold non-finite vertices (first: frame {int(frames[bad[0]])})", path=src)
    jaw_in = _recon_jaw(z, len(meshes), src)
    if rig.jaw is None:
        if o.jaw == "fixed":
            raise InputError("--jaw fixed holds the rig's jaw joint at the reconstruction's jaw, but this rig has no "
                             "jaw joint (generate it with lgi rig-generate from a jaw-rigged index)",
                             path=Path(rig_dir) / "mesh.npz")
        if jaw_in is not None:
            log.warning("the rig has no jaw joint (made from an index without a jaw rig, or by an earlier lgi "
                        "rig-generate that baked the jaw into its shapes): the reconstruction's jaw is solved as the "
                        "jaw controls' blend-shape weights; regenerate the rig with lgi rig-generate for a jaw joint")
    elif jaw_in is None:
        if o.jaw == "fixed":
            raise InputError("--jaw fixed needs the reconstruction's jaw (meshes.npz 'jaw', written by lgi "
                             "reconstruct with a jaw-rigged index); this one has none: use --jaw fit", path=src)
        log.info("the reconstruction has no jaw parameters: the rig's jaw joint is fitted from the closed jaw")
    clash = sorted(set(rig.controls) & set(JAW_CURVES)) if rig.jaw is not None else []
    if clash:
        raise InputError(f"rig controls {', '.join(clash)} have the names of the jaw joint's curves",
                         path=Path(rig_dir) / "manifest.json")
    if rig_usd is not None:
        from lgi.export.rig_anim import check_rig_usd

        check_rig_usd(rig_usd, rig.names, rig.neutral, rig.deltas, jaw=rig.jaw)

    region = rig.face_region()
    idx = np.flatnonzero(region)
    if idx.size == 0:
        raise InputError("no rig shape moves any vertex: an empty rig", path=rig_dir)
    sample = idx
    if o.vertices and idx.size > o.vertices:
        # A fixed seed: the same inputs give the same curves.
        sample = np.sort(np.random.default_rng(0).choice(idx, o.vertices, replace=False))
    solver = RigSolver(rig, sample, robust=o.robust)
    t1 = time.perf_counter()
    # The reconstruction's jaw starts (or holds) the rig's jaw joint; a rig without one solves the weights only.
    jaw_start = jaw_in if rig.jaw is not None else None
    curves, fits = solve_shot(solver, meshes, o.smooth,
                                   progress=lambda it: progress(it, "solving", disable=not show_progress),
                                   jaw=jaw_start, fix_jaw=o.jaw == "fixed")
    solve_s = time.perf_counter() - t1
    names = [*rig.controls, *(JAW_CURVES if rig.jaw is not None else ())]

    rms, mx, v_rms, v_max, p95 = _residuals(rig, curves, meshes, idx, len(region))
    resid_df = pd.DataFrame({"frame": frames, "rms_mm": rms.round(5), "max_mm": mx.round(5)})
    summary = {"out": str(Path(out).resolve()), "usd": None if usd is None else str(Path(usd).resolve()),
               "rig": str(Path(rig_dir).resolve()), "recon": str(Path(recon_dir).resolve()),
               "frames": len(frames), "controls": rig.n_controls, "correctives": len(rig.combinations),
               "region_vertices": int(idx.size), "fitted_vertices": int(sample.size),
               "rms_mm": float(np.sqrt(np.mean(rms**2))), "p95_mm": p95,
               "max_mm": float(mx.max()), "worst_frame": int(frames[int(np.argmax(mx))]),
               "iterations_mean": float(np.mean(fits.iterations)),
               "ms_per_frame": 1000.0 * solve_s / len(frames), "options": asdict(o),
               "jaw": _jaw_summary(rig, curves, jaw_in, o.jaw), "curves": f"curves.{o.format}",
               "seconds": 0.0}
    from lgi.evaluation.render import heatmap_row
    from lgi.io.csvio import write_csv
    from lgi.io.npz import save_npz

    with job_outputs(out, OUTPUTS) as stage:
        _write_curves(stage / f"curves.{o.format}", frames, names, curves)
        write_csv(resid_df, stage / "residuals.csv")
        save_npz(stage / "vertex_error.npz", rms_mm=v_rms, max_mm=v_max, region=region)
        heatmap_row(stage / "vertex_error.png", rig.neutral, ds.triangles,
                    {"RMS over the shot": v_rms, "max over the shot": v_max}, mask=region,
                    label="rig playback - reconstruction (mm)",
                    title=f"where the rig falls short ({len(frames)} frames)")
        summary["seconds"] = time.perf_counter() - t0
        (stage / "solve.json").write_text(json.dumps(summary, indent=1))
        if usd is not None:
            from lgi.export.rig_anim import write_rig_animation

            # Last, so that nothing after it can fail and leave a new animation beside the old outputs.
            k = rig.n_controls
            write_rig_animation(usd, rig_usd, rig.all_weights(curves[:, :k]), frames, o.fps,
                                jaw=None if rig.jaw is None else curves[:, k:], pivot=None if rig.jaw is None else
                                rig.jaw.pivot)
            if for_blender(usd_convention(rig_usd)):
                summary["blender_script"] = str(write_blender_script(
                    usd, o.fps, int(frames[0]), int(frames[-1]), usd_correctives(rig)).resolve())
    return summary


def _write_curves(path: Path, frames: np.ndarray, names: list[str], curves: np.ndarray) -> None:
    """``curves.csv`` or ``curves.parquet`` (by ``path``'s suffix): one row per frame (F,) and control (names,
    N) of ``curves`` (F, N), values rounded to 1e-7, written a block of frames at a time (a 36,000-frame take
    of 61 curves is 2.2 million rows). The bytes are those of the whole table written at once: the CSV's rows
    joined, the Parquet's row groups of pyarrow's default size."""
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    from lgi.io.csvio import CsvAppender
    from lgi.solve.streamed import frame_blocks

    group = 1 << 20  # pyarrow's default rows per row group
    block = max(1, (64 << 10) // max(len(names), 1))
    csv = CsvAppender(path) if path.suffix == ".csv" else None
    parquet, pending = None, []

    def put_parquet(tables: list[pa.Table]) -> None:
        nonlocal parquet
        table = pa.concat_tables(tables).combine_chunks()
        if parquet is None:
            parquet = pq.ParquetWriter(path, table.schema, compression="snappy")
        parquet.write_table(table)

    try:
        for lo, hi in frame_blocks(len(frames), block):
            df = pd.DataFrame({"frame": np.repeat(frames[lo:hi], len(names)),
                               "control": np.tile(np.asarray(names, object), hi - lo),
                               "value": curves[lo:hi].reshape(-1).round(7)})
            if csv is not None:
                csv.append(df)
                continue
            pending.append(pa.Table.from_pandas(df, preserve_index=False))
            if sum(len(t) for t in pending) >= group:
                whole = pa.concat_tables(pending)
                put_parquet([whole.slice(0, group)])
                pending = [whole.slice(group)]
        if csv is None and (pending and sum(len(t) for t in pending) or parquet is None):
            put_parquet(pending)
    finally:
        if csv is not None:
            csv.close()
        if parquet is not None:
            parquet.close()


def _residuals(rig, curves: np.ndarray, meshes, idx: np.ndarray, n_vertices: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """The rig's playback of ``curves`` (F, N) against the reconstruction ``meshes`` (F, V, 3) cm (an array or a
    :class:`~lgi.io.stored.StoredArray`) over the face region ``idx`` (R,), not only the fitted subsample, a block
    of frames at a time.

    Returns
    -------
    rms, max : (F,) float32, mm: each frame's RMS and largest vertex distance
    v_rms, v_max : (V,) float32, mm: each vertex's over the shot (0 outside the region)
    p95 : float, mm: the 95th percentile of every frame's and vertex's distance
    """
    from lgi.retarget.solve import playback
    from lgi.solve.streamed import frame_blocks, streamed_percentile

    n_f = len(curves)
    # playback's chunk: the frames meet BLAS in the same groups as when the shot was played whole (1.3 MB a frame).
    block = 64

    def errors():
        for lo, hi in frame_blocks(n_f, block):
            play = playback(rig, curves[lo:hi], idx)
            yield np.linalg.norm(play - meshes[lo:hi][:, idx].astype(np.float32), axis=2) * 10.0  # (B, R) mm

    rms = np.zeros(n_f, np.float32)
    mx = np.zeros(n_f, np.float32)
    sq = np.zeros(idx.size, np.float32)
    top = np.zeros(idx.size, np.float32)
    for (lo, hi), err in zip(frame_blocks(n_f, block), errors(), strict=True):
        rms[lo:hi] = np.sqrt(np.mean(err**2, axis=1))
        mx[lo:hi] = err.max(axis=1)
        # Row after row onto the running sums, as numpy sums the whole (F, R) array down its frames.
        sq = np.add.reduce(np.concatenate([sq[None], err**2]), axis=0)
        top = np.maximum(top, err.max(axis=0))
    v_rms = np.zeros(n_vertices, np.float32)
    v_max = np.zeros(n_vertices, np.float32)
    v_rms[idx] = np.sqrt(sq / n_f)
    v_max[idx] = top
    return rms, mx, v_rms, v_max, streamed_percentile(errors, 95, np.float32)


def _recon_jaw(z, n_frames: int, path: Path) -> np.ndarray | None:
    """(F, 4) float64: the reconstruction's jaw parameters (``meshes.npz`` ``jaw``), or None when it has none."""
    if "jaw" not in z:
        return None
    jaw = np.asarray(z["jaw"], np.float64)
    if jaw.shape != (n_frames, 4):
        raise InputError(f"jaw has shape {jaw.shape}, not ({n_frames}, 4) (open, yaw, roll deg, forward cm per "
                         "frame)", path=path)
    if not np.all(np.isfinite(jaw)):
        row = int(np.flatnonzero(~np.all(np.isfinite(jaw), axis=1))[0])
        raise InputError(f"jaw holds non-finite values (first in row {row})", path=path)
    return jaw


def _jaw_summary(rig, curves: np.ndarray, jaw_in: np.ndarray | None, mode: str) -> dict[str, Any] | None:
    """The jaw joint's part of solve.json: how it was solved and how far from the reconstruction's jaw."""
    from lgi.retarget.solve import JAW_CURVES

    if rig.jaw is None:
        return None
    k = rig.n_controls
    out: dict[str, Any] = {"mode": mode if jaw_in is not None else "fit from closed",
                           "driven_controls": [rig.controls[i] for i in rig.jaw_controls],
                           "range": {n: [float(curves[:, k + i].min()), float(curves[:, k + i].max())]
                                     for i, n in enumerate(JAW_CURVES)}}
    if jaw_in is not None:
        d = curves[:, k:] - jaw_in
        out["from_reconstruction_rms"] = {n: float(np.sqrt(np.mean(d[:, i] ** 2))) for i, n in enumerate(JAW_CURVES)}
    return out


def rig_solve_report(s: dict[str, Any]) -> list[str]:
    o = s["options"]
    smooth = "off" if not o["smooth"] else format(o["smooth"], "g") + " frames"
    return [f"solved {s['frames']} frames onto {s['controls']} controls ({s['correctives']} correctives driven), "
            f"{s['fitted_vertices']} of {s['region_vertices']} face vertices fitted, smoothing "
            f"{smooth}: {s['ms_per_frame']:.1f} ms per frame",
            f"rig playback - reconstruction over the face: RMS {s['rms_mm']:.3f} mm, 95th pct {s['p95_mm']:.3f} mm, "
            f"max {s['max_mm']:.3f} mm (frame {s['worst_frame']})",
            *([] if not s.get("jaw") else [
                f"jaw joint ({s['jaw']['mode']}): open {s['jaw']['range']['jaw_open_deg'][0]:.1f} to "
                f"{s['jaw']['range']['jaw_open_deg'][1]:.1f} deg"
                + ("" if "from_reconstruction_rms" not in s["jaw"] else
                   f", {s['jaw']['from_reconstruction_rms']['jaw_open_deg']:.3f} deg RMS from the reconstruction's")]),
            f"outputs: {s['out']}" + (f"  usd: {s['usd']}" if s["usd"] else "")
            + (f"  Blender: run {s['blender_script']}" if s.get("blender_script") else "")]


#: The rig's names this job gives its callers, loaded on first use (the command line imports this module for its
#: options, and lgi.retarget.solve would add a quarter of a second to every lgi --help).
_RIG_NAMES = ("JAW_CURVES", "load_rig", "playback")


def __getattr__(name: str) -> Any:
    if name not in _RIG_NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import lgi.retarget.solve

    return getattr(lgi.retarget.solve, name)
