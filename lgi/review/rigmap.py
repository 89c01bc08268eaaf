"""The review page's rig map: where the actor's rig, driven by ``lgi rig-solve``'s curves, falls short of the
reconstruction, per vertex and frame.

``lgi rig-solve`` writes the curves and, across the shot, the per-vertex error (``vertex_error.npz``); the page
shows the same distance frame by frame: the rig's playback of the solved curves (weights, correctives and the
jaw joint, :func:`lgi.retarget.solve.playback`) against the reconstructed mesh, in mm, over the rig's face
region. Vertices outside it (the rig moves none of them; the solve does not fit them) carry the page's
"not measured" code and are drawn as the shaded skin, never as 0 mm.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lgi.errors import InputError
from lgi.units import MM_PER_CM

#: Frames played back at a time (bounds the memory of a long shot of a large mesh).
CHUNK = 64


@dataclass
class RigMap:
    """The rig's shortfall over a shot.

    Attributes
    ----------
    distance_mm : (F, V) float32, mm
        Per frame of the reconstruction (in its order) and vertex, the distance from the rig's playback to the
        reconstructed mesh; NaN outside ``region``.
    region : (V,) bool
        The rig's face region (the vertices its shapes move).
    rms_mm : (F,) float64, mm
        Per frame, the RMS over the region (what ``residuals.csv`` holds).
    rig : str
        The rig dataset's folder.
    summary : dict
        ``lgi rig-solve``'s ``solve.json``.
    """

    distance_mm: np.ndarray
    region: np.ndarray
    rms_mm: np.ndarray
    rig: str
    summary: dict[str, Any]


def read_rig_map(solve_dir: str | Path, rig_dir: str | Path | None, frames: np.ndarray,
                 vertices: np.ndarray) -> RigMap:
    """The rig map of ``lgi rig-solve``'s folder ``solve_dir`` for a reconstruction.

    Parameters
    ----------
    solve_dir : path
        ``lgi rig-solve``'s OUT_DIR (``solve.json``, ``curves.csv`` or ``curves.parquet``).
    rig_dir : path or None
        The rig dataset (``lgi rig-generate``'s); None: the one ``solve.json`` names.
    frames : (F,) int
        The reconstruction's frame numbers.
    vertices : (F, V, 3) float32, cm
        The reconstruction's meshes.

    Raises
    ------
    InputError
        A folder that is not rig-solve's, a rig that is gone or on another mesh, curves that lack a frame of the
        reconstruction or a control of the rig.
    """
    from lgi.retarget.solve import JAW_CURVES, load_rig, playback

    solve_dir = Path(solve_dir)
    path = solve_dir / "solve.json"
    try:
        summary = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("no solve.json: not a folder lgi rig-solve wrote", path=solve_dir) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"not readable ({exc})", path=path) from None
    if rig_dir is None:
        rig_dir = summary.get("rig")
        if not rig_dir:
            raise InputError("does not name its rig (written by an older lgi rig-solve): give the rig with --rig",
                             path=path)
        if not Path(rig_dir).is_dir():
            raise InputError(f"names the rig {rig_dir}, which is not there: give the rig with --rig", path=path)
    rig, _ = load_rig(rig_dir)
    n_f, n_v = vertices.shape[:2]
    if len(rig.neutral) != n_v:
        raise InputError(f"the rig has {len(rig.neutral)} vertices and the reconstruction {n_v}: another mesh",
                         path=rig_dir)
    names = [*rig.controls, *(JAW_CURVES if rig.jaw is not None else ())]
    table = _curves_table(solve_dir)
    missing = sorted(set(names) - set(table.columns))
    if missing and set(missing) <= set(JAW_CURVES):
        raise InputError("has no jaw curves, and the rig has a jaw joint: solved onto an older copy of the rig "
                         "(its jaw in the shapes); run lgi rig-solve again", path=_curves_path(solve_dir))
    if missing:
        raise InputError(f"lacks the rig's controls {missing[:3]}: solved onto another rig",
                         path=_curves_path(solve_dir))
    absent = [int(f) for f in frames if int(f) not in table.index]
    if absent:
        raise InputError(f"lacks {len(absent)} of the reconstruction's frames: solved from another shot",
                         path=_curves_path(solve_dir), frame=absent[0])
    curves = table.loc[[int(f) for f in frames], names].to_numpy(np.float64)
    region = rig.face_region()
    idx = np.flatnonzero(region)
    dist = np.full((n_f, n_v), np.nan, np.float32)
    for lo in range(0, n_f, CHUNK):
        play = playback(rig, curves[lo:lo + CHUNK], idx)
        dist[lo:lo + CHUNK, idx] = np.linalg.norm(play - vertices[lo:lo + CHUNK, idx].astype(np.float32),
                                                  axis=2) * MM_PER_CM
    rms = np.sqrt(np.nanmean(dist[:, idx].astype(np.float64) ** 2, axis=1)) if idx.size else np.zeros(n_f)
    return RigMap(dist, region, rms, str(Path(rig_dir).resolve()), summary)


def _curves_path(solve_dir: Path) -> Path:
    p = solve_dir / "curves.parquet"
    return p if p.is_file() else solve_dir / "curves.csv"


def _curves_table(solve_dir: Path):
    """frame x control table of the curves (csv or parquet)."""
    import pandas as pd

    path = _curves_path(solve_dir)
    try:
        t = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
        return t.pivot(index="frame", columns="control", values="value")
    except FileNotFoundError:
        raise InputError("no curves.csv or curves.parquet: not a folder lgi rig-solve wrote", path=solve_dir) from None
    except (KeyError, ValueError, OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise InputError(f"not lgi rig-solve's curves table ({exc})", path=path) from None


def page_map(m: RigMap, folder: str | Path, block: int) -> dict[str, Any]:
    """The map as the page's ``maps`` entry: codes per frame in blocks of ``block`` frames, the vertices outside
    the rig's region as "not measured"."""
    from lgi.review.pack import NOT_MEASURED, TOP_WITH_GAPS, blob, colour_top, quantise_gaps

    inside = m.distance_mm[:, m.region]
    finite = inside[np.isfinite(inside)]
    vmax = colour_top(finite)
    measured = np.broadcast_to(m.region, m.distance_mm.shape)
    values = np.nan_to_num(m.distance_mm, nan=0.0)
    blocks = [blob(quantise_gaps(values[lo:lo + block], measured[lo:lo + block], measured[lo:lo + block], vmax))
              for lo in range(0, len(values), block)]
    return {"key": "rig", "label": "rig playback - reconstruction",
            "note": f"the rig {m.rig} played with lgi rig-solve's curves ({folder})", "vmax_mm": vmax,
            "max_mm": float(finite.max()) if finite.size else 0.0, "top": TOP_WITH_GAPS,
            "gaps": [{"code": NOT_MEASURED, "label": "outside the rig's face region"}], "blocks": blocks}


def summary_rows(m: RigMap, folder: str | Path) -> list[list[str]]:
    """(label, text) rows for the page's run summary."""
    s = m.summary
    rows = [["rig solve", f"{Path(folder).resolve()} (rig {m.rig})"]]
    if s.get("rms_mm") is not None:
        rows.append(["rig playback", f"RMS {s['rms_mm']:.3f} mm, p95 {s.get('p95_mm', float('nan')):.3f} mm, max "
                                     f"{s.get('max_mm', float('nan')):.3f} mm (worst frame {s.get('worst_frame')})"])
    return rows
