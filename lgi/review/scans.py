"""The review page's scan map: what ``lgi compare --out`` measured, as per-vertex colours on the frames it measured.

A scan exists for a few frames of a shot, and covers part of the face: the map is sparse in both. It stores
codes only for the frames with a scan (a slot per such frame), and codes above the colour ramp for the vertices
without a distance, so that neither a frame without a scan nor a hole of the scan shows as 0 mm:

* :data:`~lgi.review.pack.NOT_COVERED`: in the compared region, but the closest scan point lies on the scan's
  border or beyond the gate (a hole, the scan's outline; ``covered`` false in ``vertex_distances.parquet``);
* :data:`~lgi.review.pack.NOT_MEASURED`: outside the compared region (``lgi compare --region``): no row.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.errors import InputError
from lgi.evaluation.compare import frame_fingerprint
from lgi.review.pack import NOT_COVERED, NOT_MEASURED, TOP_WITH_GAPS, blob, colour_top, quantise_gaps

#: The columns of ``vertex_distances.parquet`` the map reads.
VERTEX_COLUMNS = ("frame", "scan", "vertex", "distance_mm", "covered")
#: Pairs listed on the page's summary, at most (a session may scan many frames).
LISTED = 12


@dataclass
class ScanMap:
    """The scan map of a shot, ready for the page.

    Attributes
    ----------
    slots : (F,) int64
        Per frame of the shot (in its order), the frame's row in ``codes``, or -1 where it has no scan.
    codes : (K, V) uint8
        Per frame with a scan, in frame order: distance codes over [0, ``vmax_mm``] (0..253), 254 not covered,
        255 not measured (:func:`lgi.review.pack.quantise_gaps`).
    vmax_mm : float, mm
        Top of the colour bar (the 99.9th percentile of the covered distances).
    max_mm : float, mm
        Largest covered distance.
    pairs : list of dict
        Per slot: ``frame``, ``scan`` (file name), ``covered_share``, ``rms_mm``, ``p95_mm``, ``max_mm``, ``align``.
    rms_mm : (F,) float64, mm
        Per frame, the RMS of the covered distances (NaN without a scan): the summary's ``rms_mm``.
    warnings : list of str
        What the page should say (several scans of one frame).
    """

    slots: np.ndarray
    codes: np.ndarray
    vmax_mm: float
    max_mm: float
    pairs: list[dict[str, Any]]
    rms_mm: np.ndarray
    warnings: list[str] = field(default_factory=list)


def _read_rows(folder: Path) -> list[dict[str, Any]]:
    path = folder / "summary.json"
    try:
        rows = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable summary of lgi compare ({exc})", path=path) from None
    if not isinstance(rows, list) or not rows or not all(
            isinstance(r, dict) and {"frame", "scan"} <= r.keys() for r in rows):
        raise InputError("not lgi compare's summary (a list of rows with frame and scan)", path=path)
    return rows


def _read_vertices(folder: Path) -> pd.DataFrame:
    path = folder / "vertex_distances.parquet"
    try:
        d = pd.read_parquet(path, columns=list(VERTEX_COLUMNS))
    except (OSError, ValueError, KeyError) as exc:  # pyarrow's errors derive from these
        raise InputError(f"not lgi compare's per-vertex table with columns {', '.join(VERTEX_COLUMNS)} ({exc})",
                         path=path) from None
    return d


def read_scan_map(folder: str | Path, frames: np.ndarray, vertices: np.ndarray) -> ScanMap:
    """The scan map of the reconstruction (``frames`` (F,) int, ``vertices`` (F, V, 3) float32 cm, as its
    ``meshes.npz`` holds them) from the folder ``lgi compare --out`` wrote for it.

    Refused (:class:`~lgi.errors.InputError`, naming the file): a folder that is not lgi compare's output, a
    frame the reconstruction does not have, a vertex index beyond its mesh, and distances measured on other
    vertices than the reconstruction's (summary.json's ``vertices_sha256``: another reconstruction, or a re-run
    since).
    """
    d = Path(folder)
    if not d.is_dir() or not (d / "summary.json").is_file() or not (d / "vertex_distances.parquet").is_file():
        raise InputError("--scans: not a folder written by lgi compare --out (it holds summary.json and "
                         "vertex_distances.parquet)", path=d)
    rows = _read_rows(d)
    table = _read_vertices(d)
    n_f, n_v = vertices.shape[:2]
    position = {int(f): i for i, f in enumerate(frames)}
    chosen: dict[int, dict[str, Any]] = {}
    warnings = []
    for r in rows:
        f = int(r["frame"])
        if f not in position:
            raise InputError(f"frame {f} was compared with {r['scan']}, but the reconstruction has no frame {f}: "
                             "these distances are of another shot", path=d / "summary.json")
        if f in chosen:
            warnings.append(f"frame {f} has more than one scan in {d}: the scan map shows "
                            f"{Path(chosen[f]['scan']).name} (the first), not {Path(r['scan']).name}")
            continue
        want = r.get("vertices_sha256")
        # Older compare outputs lack the fingerprint: nothing to check them against.
        if want is not None and want != frame_fingerprint(vertices[position[f]]):
            raise InputError(f"frame {f}'s distances were measured on other vertices than this reconstruction's "
                             "frame (another reconstruction, or one re-run since): run lgi compare on it again",
                             path=d / "summary.json")
        chosen[f] = r
    order = sorted(chosen, key=position.__getitem__)
    slots = np.full(n_f, -1, np.int64)
    slots[[position[f] for f in order]] = np.arange(len(order))
    values = np.zeros((len(order), n_v), np.float32)
    covered = np.zeros((len(order), n_v), bool)
    measured = np.zeros((len(order), n_v), bool)
    groups = table.groupby([table["frame"].astype(np.int64), table["scan"].astype(str)], sort=False)
    for k, f in enumerate(order):
        key = (f, str(chosen[f]["scan"]))
        if key not in groups.groups:
            raise InputError(f"no per-vertex rows for frame {f} and scan {chosen[f]['scan']}",
                             path=d / "vertex_distances.parquet")
        g = groups.get_group(key)
        v = g["vertex"].to_numpy(np.int64)
        if v.size and (v.min() < 0 or v.max() >= n_v):
            raise InputError(f"frame {f}: vertex {int(v.max())} is beyond the reconstruction's {n_v} vertices "
                             "(another mesh)", path=d / "vertex_distances.parquet")
        values[k, v] = g["distance_mm"].to_numpy(np.float32)
        covered[k, v] = g["covered"].to_numpy(bool)
        measured[k, v] = True
    known = values[covered]
    vmax = colour_top(known)
    pairs = [{"frame": f, "scan": Path(str(chosen[f]["scan"])).name,
              **{k: chosen[f].get(k) for k in ("covered_share", "rms_mm", "p95_mm", "max_mm", "align")}}
             for f in order]
    rms = np.full(n_f, np.nan)
    for k, f in enumerate(order):
        given = chosen[f].get("rms_mm")
        sel = values[k][covered[k]]
        rms[position[f]] = float(given) if given is not None else float(np.sqrt(np.mean(sel**2))) if sel.size \
            else np.nan
    return ScanMap(slots, quantise_gaps(values, covered, measured, vmax), vmax,
                   float(known.max()) if known.size else 0.0, pairs, rms, warnings)


def page_map(m: ScanMap, folder: str | Path) -> dict[str, Any]:
    """The map as the page's ``maps`` entry, whole: a scan exists for a few frames of a shot, so their codes go
    with the page's header (shown on any frame at once) rather than in the blocks of frames."""
    return {"key": "scan", "label": "distance to the scan", "note": f"lgi compare's per-vertex distances in {folder}",
            "vmax_mm": m.vmax_mm, "max_mm": m.max_mm, "top": TOP_WITH_GAPS, "slots": m.slots.tolist(),
            "gaps": [{"code": NOT_COVERED, "label": "not covered by the scan"},
                     {"code": NOT_MEASURED, "label": "outside the compared region"}],
            "pairs": m.pairs, "values": blob(m.codes)}


def summary_rows(m: ScanMap, folder: str | Path) -> list[list[str]]:
    """(label, text) rows for the page's run summary."""
    rows = [["scans", f"{len(m.pairs)} frames compared with scans by lgi compare ({Path(folder).resolve()})"]]
    for p in m.pairs[:LISTED]:
        share = p.get("covered_share")
        rms = p.get("rms_mm")
        rows.append([f"scan, frame {p['frame']}", f"{p['scan']}: " + (f"{share * 100:.1f} % covered, " if share
                     is not None else "") + (f"RMS {rms:.3f} mm" if rms is not None else "")
                     + (f", aligned {p['align']}" if p.get("align") not in (None, "none") else "")])
    if len(m.pairs) > LISTED:
        rows.append(["scans", f"... and {len(m.pairs) - LISTED} more in {Path(folder) / 'summary.csv'}"])
    return rows
