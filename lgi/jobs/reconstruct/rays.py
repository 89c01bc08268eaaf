"""Markers seen by one camera: their viewing rays put into a bundles file (a second reconstruction meets them),
and read back from it."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from lgi.units import MM_PER_CM

if TYPE_CHECKING:
    from lgi.jobs.reconstruct.shot import Shot

log = logging.getLogger(__name__)


CONSTRAINED = "bundles_constrained.parquet"
RAY_COLUMNS = ("ray_ox", "ray_oy", "ray_oz", "ray_dx", "ray_dy", "ray_dz")


def read_constraints(bundles: str | Path, frames: np.ndarray, names: list[str]) -> tuple[
        tuple[np.ndarray, np.ndarray, np.ndarray] | None, Path | None]:
    """The rays of a bundles file written by :func:`constrain_to_rays` (its ``constraint`` and ``ray_*``
    columns): mask (F, M) bool, origins and unit directions (F, M, 3) cm, head frame (NaN off the rays); and
    the file. (None, None) for any other bundles file."""
    path = Path(bundles)
    if path.suffix.lower() != ".parquet":
        return None, None
    import pyarrow.parquet as pq

    if "constraint" not in pq.read_schema(str(path)).names:
        return None, None
    df = pd.read_parquet(path, columns=["frame", "marker", "constraint", *RAY_COLUMNS])
    ray = (df["constraint"] == "ray").to_numpy()
    row = {int(f): k for k, f in enumerate(frames)}
    col = {n: k for k, n in enumerate(names)}
    f = df["frame"][ray].map(row).to_numpy(np.int64)
    m = df["marker"][ray].map(col).to_numpy(np.int64)
    mask = np.zeros((len(frames), len(names)), bool)
    mask[f, m] = True
    geo = np.full((2, len(frames), len(names), 3), np.nan)
    geo[0, f, m] = df.loc[ray, list(RAY_COLUMNS[:3])].to_numpy(np.float64)
    geo[1, f, m] = df.loc[ray, list(RAY_COLUMNS[3:])].to_numpy(np.float64)
    return (mask, geo[0], geo[1]), path


def constrain_to_rays(shot: Shot, vertices: np.ndarray, out: str | Path) -> dict[str, Any]:
    """Put each marker seen by one camera (``shot.options.observations``) on its viewing ray, at the ray's point
    closest to where ``vertices`` (a reconstruction of the shot without it, (F, V, 3) float32, cm) put the
    marker; write the shot's bundles as given plus those points to ``out`` (Parquet, with a ``constraint``
    column: "bundle" or "ray"), the bundles file a second reconstruction reads. Returns counts."""
    from lgi.capture.bundles import COLUMNS
    from lgi.capture.observations import points_on_rays, read_rays
    from lgi.io.atomic import atomic_file

    o = shot.options
    seen = np.all(np.isfinite(shot.given), axis=2)
    rays = read_rays(o.observations, shot.index.marker_names, shot.frames, seen, o.calib)
    pos = shot.given.copy()
    layout = shot.index.layout()
    before = np.zeros(len(rays))
    if len(rays):
        rows = np.unique(rays.frame)
        at = np.searchsorted(rows, rays.frame)
        surface = layout.evaluate(np.asarray(vertices[rows], np.float64))[at, rays.marker]
        before = rays.distance(surface)
        pos[rays.frame, rays.marker] = points_on_rays(rays, surface)
    geo = np.full((2, *pos.shape), np.nan)
    geo[0, rays.frame, rays.marker] = rays.origin
    geo[1, rays.frame, rays.marker] = rays.direction
    f, m = np.nonzero(np.all(np.isfinite(pos), axis=2))
    kind = np.where(seen[f, m], "bundle", "ray")
    names = np.asarray(shot.index.marker_names, object)
    table = pd.DataFrame({"frame": np.asarray(shot.frames, np.int64)[f], "marker": names[m],
                          "x": pos[f, m, 0], "y": pos[f, m, 1], "z": pos[f, m, 2], "constraint": kind,
                          **{c: geo[k // 3, f, m, k % 3] for k, c in enumerate(RAY_COLUMNS)}})
    with atomic_file(out, suffix=".parquet", durable=False) as tmp:
        table[[*COLUMNS, "constraint", *RAY_COLUMNS]].to_parquet(tmp, index=False)
    if len(rays):
        log.info("%d markers seen by one camera put on their rays (%d frames); the first reconstruction was "
                 "%.3f mm from them (median, max %.3f mm)", len(rays), len(np.unique(rays.frame)),
                 float(np.median(before)) * MM_PER_CM, float(before.max()) * MM_PER_CM)
    else:
        log.warning("%s: no marker is seen by one camera alone where the shot lacks its bundle: no ray constraint",
                    o.observations)
    return {"rays": len(rays), "ray_frames": int(len(np.unique(rays.frame))),
            "ray_offset_before_mm": float(np.median(before) * MM_PER_CM) if len(rays) else 0.0}
