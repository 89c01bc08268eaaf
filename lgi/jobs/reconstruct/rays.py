"""The bundles file that puts markers seen by one camera on their viewing rays (written by
:func:`lgi.jobs.reconstruct.shot.constrain_to_rays`, met by a second reconstruction): its name, its ray columns,
and their reading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

CONSTRAINED = "bundles_constrained.parquet"
RAY_COLUMNS = ("ray_ox", "ray_oy", "ray_oz", "ray_dx", "ray_dy", "ray_dz")


def read_constraints(bundles: str | Path, frames: np.ndarray, names: list[str]) -> tuple[
        tuple[np.ndarray, np.ndarray, np.ndarray] | None, Path | None]:
    """The rays of a bundles file written by :func:`~lgi.jobs.reconstruct.shot.constrain_to_rays` (its
    ``constraint`` and ``ray_*`` columns): mask (F, M) bool, origins and unit directions (F, M, 3) cm, head frame
    (NaN off the rays); and the file. (None, None) for any other bundles file."""
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
