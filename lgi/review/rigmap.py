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
    """The rig's shortfall over a shot, computed a block of frames at a time (:meth:`distance`): a long take's
    (F, V) distances are never held whole.

    Attributes
    ----------
    model : Rig
        The loaded rig (:func:`lgi.retarget.solve.load_rig`).
    curves : (F, C) float64
        Per frame of the reconstruction (in its order), the rig's controls (and jaw curves) ``lgi rig-solve``
        solved.
    region : (V,) bool
        The rig's face region (the vertices its shapes move).
    rig : str
        The rig dataset's folder.
    summary : dict
        ``lgi rig-solve``'s ``solve.json``.
    """

    model: Any
    curves: np.ndarray
    region: np.ndarray
    rig: str
    summary: dict[str, Any]

    def distance(self, lo: int, vertices: np.ndarray) -> np.ndarray:
        """(B, V) float32 mm: per frame ``lo .. lo + B`` of the shot and vertex, the distance from the rig's
        playback to ``vertices`` (B, V, 3) cm, those frames' reconstructed meshes; NaN outside ``region``."""
        from lgi.retarget.solve import playback

        idx = np.flatnonzero(self.region)
        n_b = len(vertices)
        dist = np.full((n_b, len(self.region)), np.nan, np.float32)
        for a in range(0, n_b, CHUNK):
            b = min(n_b, a + CHUNK)  # the block's frames: the curves go on past a block that is not the shot's last
            play = playback(self.model, self.curves[lo + a:lo + b], idx)
            dist[a:b, idx] = np.linalg.norm(play - vertices[a:b, idx].astype(np.float32), axis=2) * MM_PER_CM
        return dist


def read_rig_map(solve_dir: str | Path, rig_dir: str | Path | None, frames: np.ndarray, n_vertices: int) -> RigMap:
    """The rig map of ``lgi rig-solve``'s folder ``solve_dir`` for a reconstruction (checked and loaded; the
    distances are computed per block of frames by :meth:`RigMap.distance`).

    Parameters
    ----------
    solve_dir : path
        ``lgi rig-solve``'s OUT_DIR (``solve.json``, ``curves.csv`` or ``curves.parquet``).
    rig_dir : path or None
        The rig dataset (``lgi rig-generate``'s); None: the one ``solve.json`` names.
    frames : (F,) int
        The reconstruction's frame numbers.
    n_vertices : int
        The reconstruction's vertex count.

    Raises
    ------
    InputError
        A folder that is not rig-solve's, a rig that is gone or on another mesh, curves that lack a frame of the
        reconstruction or a control of the rig.
    """
    from lgi.retarget.solve import JAW_CURVES, load_rig

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
    n_v = int(n_vertices)
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
    return RigMap(rig, curves, rig.face_region(), str(Path(rig_dir).resolve()), summary)


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


def summary_rows(m: RigMap, folder: str | Path) -> list[list[str]]:
    """(label, text) rows for the page's run summary."""
    s = m.summary
    rows = [["rig solve", f"{Path(folder).resolve()} (rig {m.rig})"]]
    if s.get("rms_mm") is not None:
        rows.append(["rig playback", f"RMS {s['rms_mm']:.3f} mm, p95 {s.get('p95_mm', float('nan')):.3f} mm, max "
                                     f"{s.get('max_mm', float('nan')):.3f} mm (worst frame {s.get('worst_frame')})"])
    return rows
