"""The review job: a reconstruction as a self-contained page to scrub through in 3D (``lgi review``).

:func:`review` reads a reconstruction's outputs (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv``) and the
index it was made with, and writes ``REVIEW_DIR``: ``index.html``, ``viewer.js`` (the WebGL viewer, lgi's own) and
the data scripts ``review_meta.js`` (topology, markers, curves, summary, diagnostics) and ``review_frames.js``
(the quantised frames and colour maps). The page opens from the file system with no server and no network.

The command line, ``lgi demo``, ``lgi reconstruct --review`` and the flows all call :func:`review`.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import shutil
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.errors import InputError
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: What a review folder holds (anything else in an existing one makes the job refuse to replace it).
REVIEW_ENTRIES = ("index.html", "viewer.js", "review_meta.js", "review_frames.js")
#: Frames per separately compressed block of the page's data: the page shows the first block while it inflates
#: the others (a 1000-frame ICT shot takes seconds to inflate whole).
BLOCK = 50
#: The status of a marker in a frame, in the order of the page's codes (the diagnostics' ``status`` values, and
#: ``ray`` where the ``constraint`` column says a viewing ray held the marker).
STATUSES = ("contained", "projected", "neighbour", "fitted", "missing", "bridged", "ray", "other")


@dataclass(frozen=True)
class ReviewOptions:
    """Options of the review job (the ``lgi review`` flags).

    Attributes
    ----------
    truth : str or None
        An npz with ``vertices`` (F, V, 3) cm, the true surfaces (``lgi synth``'s ``truth.npz``): adds the
        distance-to-truth colour map and the error curve.
    compare : str or None
        Another reconstruction of the same shot on the same mesh (e.g. ``--method blendshape``): adds the
        distance-between-them colour map.
    scans : str or None
        The folder ``lgi compare --out`` wrote for this reconstruction: adds the distance-to-the-scan colour map
        (mm) on the frames compared with a scan, and its RMS as points on the curves.
    rig_solve : str or None
        The folder ``lgi rig-solve`` wrote for this reconstruction: adds the distance from the rig's playback of
        its curves to the reconstruction (mm) as a colour map, and its RMS per frame as a curve.
    rig : str or None
        With ``rig_solve``: the rig dataset (default: the one its ``solve.json`` names).
    fps : float
        The shot's frame rate, frames per second: the page's playback rate at speed 1.
    step_um : float, um
        Quantisation step of the positions the page shows (within half of it; coarser only when the shot moves
        more than 32767 steps). The colour maps are computed from the exact meshes.
    """

    truth: str | None = None
    compare: str | None = None
    fps: float = 30.0
    scans: str | None = None
    step_um: float = 10.0
    rig_solve: str | None = None
    rig: str | None = None

    def __post_init__(self) -> None:
        if self.rig and not self.rig_solve:
            raise InputError("--rig goes with --rig-solve (the rig its curves drive)")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise InputError(f"--fps must be a positive number of frames per second, not {self.fps!r}")
        if not isinstance(self.step_um, (int, float)) or not 0 <= self.step_um <= 1000:
            raise InputError(f"--step must be a number of um in [0, 1000], not {self.step_um!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _read_meshes(recon_dir: Path, what: str) -> dict[str, np.ndarray]:
    from lgi.io.arrays import nonfinite_frames
    from lgi.io.npz import load_meshes

    path = recon_dir / "meshes.npz"
    if not recon_dir.is_dir():
        raise InputError(f"{what} is not a folder", path=recon_dir)
    if not path.is_file():
        raise InputError(f"no meshes.npz: {what} is not a reconstruction (lgi reconstruct writes meshes.npz, "
                         "diagnostics.csv and per_frame.csv)", path=path)
    m = load_meshes(path, required=("vertices", "frames"))
    v = m["vertices"]
    if v.ndim != 3 or v.shape[2] != 3 or v.dtype.kind != "f" or len(m["frames"]) != len(v):
        raise InputError(f"vertices {v.shape} / frames {m['frames'].shape} are not a shot's (F, V, 3) and (F,)",
                         path=path)
    if len(nonfinite_frames(v)):
        raise InputError("vertices hold non-finite values", path=path)
    return m


def _read_diagnostics(recon_dir: Path) -> pd.DataFrame:
    path = recon_dir / "diagnostics.csv"
    if not path.is_file():
        raise InputError("no diagnostics.csv: not a reconstruction's folder (lgi reconstruct writes it)", path=path)
    try:
        d = pd.read_csv(path, keep_default_na=False, na_values=[""])
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
        raise InputError(f"not a readable CSV ({exc})", path=path) from None
    missing = [c for c in ("frame", "marker", "status") if c not in d.columns]
    if missing:
        raise InputError(f"lacks the columns {missing}", path=path)
    return d


def correction_size(diagnostics: pd.DataFrame, arrays: dict[str, np.ndarray], frames: np.ndarray,
                    markers: list[str]) -> np.ndarray:
    """(F, V) float32 mm: an upper bound of the size of the correction that took each vertex through the bundles.

    The reconstruction stores, per frame and bundle, the distance to the bundle before and after the correction,
    not the correction's vectors; the correction is the index's field of each bundle (1 at it, 0 at the others)
    times the bundle's residual vector. By the triangle inequality its size at a vertex is at most
    sum over bundles of |field(v)| x (before - after), which is what this returns (exact where one bundle
    dominates, as near each bundle)."""
    import scipy.sparse as sp

    n_v = arrays["neutral"].shape[0]
    if "corr_indptr" not in arrays:
        return np.zeros((len(frames), n_v), np.float32)
    c = sp.csr_matrix((np.abs(arrays["corr_data"]), arrays["corr_indices"], arrays["corr_indptr"]),
                      shape=(len(markers), n_v))
    r = _grid(diagnostics, frames, markers, "residual_before_mm") - _grid(diagnostics, frames, markers, "residual_mm")
    r = np.clip(np.nan_to_num(r), 0.0, None)
    return np.asarray((c.T @ r.T).T, np.float32)


def _grid(d: pd.DataFrame, frames: np.ndarray, markers: list[str], col: str) -> np.ndarray:
    """(F, M) float of a diagnostics column (NaN where absent)."""
    out = np.full((len(frames), len(markers)), np.nan)
    if col not in d:
        return out
    fi, mi = _rows(d, frames, markers)
    ok = (fi >= 0) & (mi >= 0)
    out[fi[ok], mi[ok]] = pd.to_numeric(d[col], errors="coerce").to_numpy(np.float64)[ok]
    return out


def _rows(d: pd.DataFrame, frames: np.ndarray, markers: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Per diagnostics row, its frame's and marker's positions (-1 where unknown)."""
    fpos = pd.Series(np.arange(len(frames)), index=np.asarray(frames, np.int64))
    mpos = pd.Series(np.arange(len(markers)), index=markers)
    fi = pd.to_numeric(d["frame"], errors="coerce").map(fpos).fillna(-1).to_numpy(np.int64)
    mi = d["marker"].astype(str).map(mpos).fillna(-1).to_numpy(np.int64)
    return fi, mi


def _aligned(other: np.ndarray, other_frames: np.ndarray | None, frames: np.ndarray, path: Path,
             n_v: int, what: str) -> np.ndarray:
    """``other`` (F', V, 3) on the shot's frames, by frame number when it has them, else by position."""
    if other.ndim != 3 or other.shape[1:] != (n_v, 3):
        raise InputError(f"{what} has vertices of shape {other.shape}; the reconstruction has (F, {n_v}, 3) "
                         "(another mesh topology?)", path=path)
    if other_frames is None:
        if len(other) < len(frames):
            raise InputError(f"{what} has {len(other)} frames, the reconstruction {len(frames)}", path=path)
        return other[: len(frames)]
    if len(other_frames) == len(frames) and np.array_equal(other_frames, frames):
        return other  # the same frames in the same order: no copy of a large shot
    pos = {int(f): i for i, f in enumerate(other_frames)}
    absent = [int(f) for f in frames if int(f) not in pos]
    if absent:
        raise InputError(f"{what} lacks {len(absent)} of the reconstruction's frames", path=path, frame=absent[0])
    return other[[pos[int(f)] for f in frames]]


def _map(values: np.ndarray, label: str, note: str) -> dict[str, Any]:
    from lgi.review.pack import blob, colour_top, quantise_map

    finite = values[np.isfinite(values)]
    vmax = colour_top(finite)
    return {"label": label, "note": note, "vmax_mm": vmax, "max_mm": float(finite.max()) if finite.size else 0.0,
            "blocks": [blob(quantise_map(values[lo:lo + BLOCK], vmax)) for lo in range(0, len(values), BLOCK)]}


def _diag_columns(d: pd.DataFrame, order: np.ndarray) -> list[dict[str, Any]]:
    """The diagnostics' columns in (frame, marker) order as page blobs: numbers as float32, text as codes into
    its distinct values."""
    from lgi.review.pack import blob

    cols = []
    for name in d.columns:
        if name in ("frame", "marker"):
            continue
        s = d[name].iloc[order] if len(order) else d[name]
        if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
            cols.append({"name": name, "kind": "number", "data": blob(s.to_numpy(np.float32))})
        else:
            cats, codes = np.unique(s.fillna("").astype(str).to_numpy(), return_inverse=True)
            kind = np.uint8 if len(cats) <= 255 else np.uint16 if len(cats) <= 65535 else np.int32
            cols.append({"name": name, "kind": "text", "values": cats.tolist(),
                         "data": blob(codes.astype(kind))})
    return cols


def review(recon_dir: str | Path, index_dir: str | Path, out: str | Path, options: ReviewOptions | None = None,
           summary: dict[str, Any] | None = None, warnings: list[str] | None = None) -> dict[str, Any]:
    """Write the review page of a reconstruction into ``out``; returns what it wrote (paths, sizes, maps).

    Parameters
    ----------
    recon_dir : path
        A reconstruction (``meshes.npz`` with ``vertices`` (F, V, 3) float32 cm and ``frames`` (F,);
        ``diagnostics.csv``; ``per_frame.csv``, recomputed from the diagnostics when absent).
    index_dir : path
        The index it was reconstructed with (mesh topology, marker layout, neutral, correction fields).
    out : path
        The review folder (replaced as a whole; refused if it holds files lgi does not write there).
    options : ReviewOptions
    summary : dict, optional
        The reconstruct job's summary (:func:`lgi.jobs.reconstruct.summarise`), shown on the page; without it
        the page shows what the diagnostics say.
    warnings : list of str, optional
        Warnings of the run to show.

    Bad input raises :class:`~lgi.errors.InputError` naming the file, before anything is written.
    """
    from lgi.index.build import LGIIndex
    from lgi.io.atomic import atomic_dir, check_output
    from lgi.review.pack import blob, encode_codes, quantise_frames, write_script

    o = options or ReviewOptions()
    t0 = time.perf_counter()
    recon, out = Path(recon_dir), Path(out)
    inputs = [recon, index_dir] + [p for p in (o.truth, o.compare, o.scans, o.rig_solve, o.rig) if p]
    check_output(out, "dir", owned=REVIEW_ENTRIES, what="lgi review folder", inputs=inputs)
    meshes = _read_meshes(recon, "RECON_DIR")
    diag = _read_diagnostics(recon)
    if summary is None:
        summary = _run_record(recon)
    index = LGIIndex.load(index_dir)
    a = index.arrays
    verts, frames = meshes["vertices"], np.asarray(meshes["frames"], np.int64)
    n_f, n_v = verts.shape[:2]
    if n_v != index.n_vertices:
        raise InputError(f"meshes.npz has {n_v} vertices, the index {index.n_vertices}: not reconstructed with "
                         f"this index ({index_dir})", path=recon / "meshes.npz")
    markers = index.marker_names
    unknown = sorted(set(diag["marker"].astype(str)) - set(markers))
    if unknown:
        raise InputError(f"names markers the index does not have ({unknown[:3]})", path=recon / "diagnostics.csv")
    per_frame_path = recon / "per_frame.csv"
    if per_frame_path.is_file():
        try:
            per_frame = pd.read_csv(per_frame_path)
        except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
            raise InputError(f"not a readable CSV ({exc})", path=per_frame_path) from None
    else:
        from lgi.jobs.reconstruct import per_frame_table

        per_frame = per_frame_table(diag)
    truth = compare = None
    if o.truth:
        t = Path(o.truth)
        from lgi.io.npz import load_npz

        tz = load_npz(t, required=("vertices",))
        truth = _aligned(tz["vertices"], tz.get("frames"), frames, t, n_v, "the truth")
    if o.compare:
        c = Path(o.compare)
        cm = _read_meshes(c, "--compare")
        compare = _aligned(cm["vertices"], cm["frames"], frames, c / "meshes.npz", n_v, "--compare's reconstruction")
    scans = None
    if o.scans:
        from lgi.review.scans import read_scan_map

        scans = read_scan_map(o.scans, frames, verts)
    rigmap = None
    if o.rig_solve:
        from lgi.review.rigmap import read_rig_map

        rigmap = read_rig_map(o.rig_solve, o.rig, frames, verts)

    # ---- the frames, quantised
    from lgi.dataset.mesh import triangulate

    tris = triangulate(a["face_vertices"], a["face_offsets"])[0].astype(np.int32)
    q = quantise_frames(verts, a["neutral"], o.step_um * 1e-4)
    # ---- colour maps, mm per vertex and frame
    maps = []
    if truth is not None:
        dist = np.linalg.norm(verts.astype(np.float32) - truth.astype(np.float32), axis=2) * MM_PER_CM
        maps.append({"key": "truth", **_map(dist, "distance to the truth", f"against {Path(o.truth).name}")})
    corr = correction_size(diag, a, frames, markers)
    maps.append({"key": "correction", **_map(corr, "correction size (bound)",
                                             "sum over bundles of |correction field| x (residual before - after)")})
    if compare is not None:
        dist = np.linalg.norm(verts.astype(np.float32) - compare.astype(np.float32), axis=2) * MM_PER_CM
        maps.append({"key": "compare", **_map(dist, "distance from --compare", str(Path(o.compare)))})
    if scans is not None:
        from lgi.review.scans import page_map

        maps.append(page_map(scans, o.scans, BLOCK))
    if rigmap is not None:
        from lgi.review import rigmap as rm

        maps.append(rm.page_map(rigmap, o.rig_solve, BLOCK))

    # ---- markers: status codes per frame, diagnostics in (frame, marker) order
    fi, mi = _rows(diag, frames, markers)
    keep = (fi >= 0) & (mi >= 0)
    st = diag["status"].astype(str).to_numpy()
    if "constraint" in diag:
        st = np.where(diag["constraint"].astype(str).to_numpy() == "ray", "ray", st)
    code = np.array([STATUSES.index(s) if s in STATUSES else len(STATUSES) - 1 for s in st], np.uint8)
    status = np.full((n_f, len(markers)), STATUSES.index("missing"), np.uint8)
    status[fi[keep], mi[keep]] = code[keep]
    slot = np.full((n_f, len(markers)), -1, np.int32)
    slot[fi[keep], mi[keep]] = np.flatnonzero(keep)
    order = slot.ravel()
    present = order >= 0
    dcols = _diag_columns(diag, np.where(present, order, 0))

    # ---- per-frame curves
    curves = []
    pf = per_frame.set_index("frame").reindex(frames) if "frame" in per_frame else per_frame
    jaw = meshes.get("jaw")
    if jaw is not None and jaw.ndim == 2 and len(jaw) == n_f:
        curves.append({"key": "jaw", "label": "jaw opening", "unit": "deg", "values": jaw[:, 0].astype(float).tolist()})
    elif "jaw_open_deg" in diag:
        g = np.nanmax(_grid(diag, frames, markers, "jaw_open_deg"), axis=1)
        curves.append({"key": "jaw", "label": "jaw opening", "unit": "deg", "values": g.tolist()})
    for col, label in (("residual_before_mm", "largest bundle residual before correction"),
                       ("residual_mm", "largest bundle residual after correction")):
        if col in pf:
            curves.append({"key": col, "label": label, "unit": "mm", "values": pf[col].astype(float).tolist()})
    m = max(len(markers), 1)
    if "projected" in pf and "missing" in pf:
        share = (pf["projected"].astype(float) + pf["missing"].astype(float)) / m * 100
        curves.append({"key": "unsure", "label": "bundles missing or projected", "unit": "%",
                       "values": share.tolist()})
    if truth is not None:
        e = np.linalg.norm(verts.astype(np.float32) - truth.astype(np.float32), axis=2) * MM_PER_CM
        curves.append({"key": "error_rms", "label": "error against the truth, RMS", "unit": "mm",
                       "values": np.sqrt(np.mean(e**2, axis=1)).tolist()})
        curves.append({"key": "error_max", "label": "error against the truth, max", "unit": "mm",
                       "values": e.max(axis=1).tolist()})
    if scans is not None:
        # Points, not a line: the frames with a scan are usually a few, far apart.
        curves.append({"key": "scan_rms", "label": "distance to the scan, RMS of the covered vertices", "unit": "mm",
                       "values": scans.rms_mm.tolist(), "points": True, "missing": "no scan at this frame"})
    if rigmap is not None:
        curves.append({"key": "rig_rms", "label": "rig playback - reconstruction, RMS over the face region",
                       "unit": "mm", "values": rigmap.rms_mm.tolist()})

    # ---- summary and warnings
    info = _summary(recon, index_dir, index, diag, per_frame, summary, o, n_f, n_v)
    warn = list(warnings or []) + _warnings(diag, per_frame, len(markers), summary)
    if scans is not None:
        from lgi.review.scans import summary_rows

        info += summary_rows(scans, o.scans)
        warn += scans.warnings
    if rigmap is not None:
        from lgi.review import rigmap as rm

        info += rm.summary_rows(rigmap, o.rig_solve)

    meta = {
        "format": "lgi-review", "version": 1, "fps": o.fps,
        "title": f"{recon.resolve().name}: {n_f} frames x {n_v} vertices",
        "frames": frames.tolist(), "n_vertices": n_v, "markers": markers, "statuses": list(STATUSES),
        "triangles": blob(tris.ravel()), "marker_vertices": blob(a["marker_vertices"].astype(np.int32).ravel()),
        "marker_weights": blob(a["marker_weights"].astype(np.float32).ravel()),
        "status": blob(status.ravel()), "diag_present": blob(present.astype(np.uint8)), "diagnostics": dcols,
        "curves": curves, "summary": info, "warnings": warn,
        # Frames marked on the curves (positions in the shot): those compared with a scan.
        "marks": [{"label": "scan", "frames": np.flatnonzero(scans.slots >= 0).tolist()}] if scans is not None
        else [],
        "quantisation": {"scale_cm": q.scale, "error_bound_mm": q.error_bound_cm * MM_PER_CM,
                         "moving_vertices": int(len(q.moving))},
    }
    frames_payload = {"rest": blob(q.rest.ravel()), "moving": blob(q.moving), "block": BLOCK,
                      "blocks": [blob(encode_codes(q.codes[lo:lo + BLOCK])) for lo in range(0, n_f, BLOCK)],
                      "scale": q.scale, "n_frames": n_f, "maps": maps}
    static = resources.files("lgi.review") / "static"
    with atomic_dir(out, REVIEW_ENTRIES, "lgi review folder") as tmp:
        for name in ("index.html", "viewer.js"):
            (tmp / name).write_bytes((static / name).read_bytes())
        sizes = {"review_meta.js": write_script(tmp / "review_meta.js", "LGI_REVIEW_META", meta),
                 "review_frames.js": write_script(tmp / "review_frames.js", "LGI_REVIEW_FRAMES", frames_payload)}
    sizes.update({n: (out / n).stat().st_size for n in ("index.html", "viewer.js")})
    return {"page": str((out / "index.html").resolve()), "bytes": int(sum(sizes.values())), "files": sizes,
            "frames": n_f, "vertices": n_v, "maps": [mp["key"] for mp in maps], "seconds": time.perf_counter() - t0,
            "quantisation_error_mm": q.error_bound_cm * MM_PER_CM, "moving_vertices": int(len(q.moving))}


def _run_record(recon: Path) -> dict[str, Any] | None:
    """The reconstruction's ``run.json`` (its method, options and noise), or None when it has none or it cannot
    be read (the page then says so; a review does not fail on it)."""
    path = recon / "run.json"
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: not read (%s); the page shows no options or noise estimate", path, exc)
        return None
    return record if isinstance(record, dict) else None


def _summary(recon: Path, index_dir: str | Path, index, diag: pd.DataFrame, per_frame: pd.DataFrame,
             summary: dict[str, Any] | None, o: ReviewOptions, n_f: int, n_v: int) -> list[list[str]]:
    """(label, text) rows of the run's summary for the page."""
    st = diag["status"].astype(str).to_numpy()
    rows = [["reconstruction", str(recon.resolve())], ["index", str(Path(index_dir).resolve())],
            ["dataset", str(index.manifest.get("dataset_info", {}).get("name", "?"))],
            ["shot", f"{n_f} frames x {n_v} vertices, {index.n_markers} markers"],
            ["bundle statuses", ", ".join(f"{s} {100 * np.mean(st == s):.1f} %" for s in np.unique(st))]]
    if summary:
        from lgi.jobs.reconstruct import report_lines

        if summary.get("noise_estimate_mm") is not None:
            axes = summary.get("noise_estimate_axes_mm")
            per_axis = "" if not axes or None in axes else " (x {:.4f}, y {:.4f}, z {:.4f})".format(*axes)
            rows.append(["noise estimate", f"{summary['noise_estimate_mm']:.4f} mm{per_axis} (coherence "
                                           f"{summary.get('noise_coherence', float('nan')):.2f})"])
        if summary.get("noise_mm") is not None:
            rows.append(["noise used", f"{summary['noise_mm']:.4f} mm"])
        if summary.get("method"):
            rows.append(["method", str(summary["method"])])
        if summary.get("options"):
            rows.append(["options", ", ".join(f"{k}={v}" for k, v in summary["options"].items())])
        try:
            rows += [["report", line] for line in report_lines(summary)]
        except (KeyError, TypeError, ValueError):
            pass  # a summary from another version: its figures above are enough
    else:
        rows.append(["noise estimate", "not stored with the reconstruction (no run.json: written by an older lgi)"])
    counts = index.manifest.get("counts", {})
    if counts:
        rows.append(["index counts", ", ".join(f"{k} {v}" for k, v in counts.items())])
    if o.truth:
        rows.append(["truth", str(Path(o.truth).resolve())])
    if o.compare:
        rows.append(["compare", str(Path(o.compare).resolve())])
    return rows


def _warnings(diag: pd.DataFrame, per_frame: pd.DataFrame, n_markers: int,
              summary: dict[str, Any] | None) -> list[str]:
    """What a supervisor should look at first, from the diagnostics."""
    out = []
    if "missing" in per_frame and len(per_frame):
        share = per_frame["missing"].to_numpy(float) / max(n_markers, 1)
        bad = np.flatnonzero(share > 0.2)
        if bad.size:
            out.append(f"{bad.size} frames miss over 20 % of their bundles (first: frame "
                       f"{int(per_frame['frame'].iloc[bad[0]])})")
    if "residual_mm" in per_frame and len(per_frame):
        r = per_frame["residual_mm"].to_numpy(float)
        if np.isfinite(r).any() and np.nanmax(r) > 0.01:
            f = int(per_frame["frame"].iloc[int(np.nanargmax(r))])
            out.append(f"largest bundle residual after correction {np.nanmax(r):.3f} mm (frame {f})")
    if "fallback" in diag:
        fb = diag["fallback"].astype(object).where(diag["fallback"].notna(), "").astype(str)
        if (fb != "").any():
            out.append(f"{int((fb != '').sum())} bundle-frames fell back ({fb[fb != ''].iloc[0]})")
    if summary and summary.get("noise_estimated") and not math.isfinite(summary.get("noise_estimate_mm") or 0.0):
        out.append("noise not estimated: no marker is seen for 7 frames in a row")
    return out


def review_report(r: dict[str, Any]) -> list[str]:
    """The lines ``lgi review`` prints."""
    per_1000 = r["bytes"] / max(r["frames"], 1) * 1000 / 1e6
    return [f"review page of {r['frames']} frames x {r['vertices']} vertices: {r['page']}",
            f"  {r['bytes'] / 1e6:.1f} MB ({per_1000:.1f} MB per 1000 frames; {r['moving_vertices']} vertices move; "
            f"positions within {r['quantisation_error_mm'] * 1000:.2f} um), colour maps: {', '.join(r['maps'])}; "
            "open it in a browser (no server needed)"]


def review_beside(out: str | Path, index_dir: str | Path, summary: dict[str, Any] | None = None,
                  options: ReviewOptions | None = None, warnings: list[str] | None = None) -> dict[str, Any]:
    """The review page of the reconstruction in ``out``, written to ``out/review`` (``--review``, the demo and the
    flows)."""
    return review(out, index_dir, Path(out) / "review", options, summary, warnings)


@contextlib.contextmanager
def collected_warnings() -> Iterator[list[str]]:
    """The warnings lgi logs inside the block (what a run could not do as asked), for the page."""
    seen: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            seen.append(record.getMessage())

    handler = Collect(logging.WARNING)
    logging.getLogger("lgi").addHandler(handler)
    try:
        yield seen
    finally:
        logging.getLogger("lgi").removeHandler(handler)


def remove_review(out: str | Path) -> None:
    """Remove ``out/review`` if it is a review folder (a re-run without ``--review``: the old page would show
    another run)."""
    p = Path(out) / "review"
    if p.is_dir() and all(e.name in REVIEW_ENTRIES for e in p.iterdir()):
        shutil.rmtree(p)
