"""The bundles file: per-frame 3D marker positions in long format.

Columns ``frame, marker, x, y, z`` (CSV or Parquet, chosen by the extension). One row per seen marker
and frame; a marker not seen in a frame has no row, or a row whose x, y and z are all empty/NaN.
Coordinates are in the dataset's units. Validation rejects, naming frame and marker: unknown marker
names, duplicate (frame, marker) rows, non-integer frames, non-numeric values, infinite coordinates,
and rows with some but not all coordinates missing.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from lgi.errors import InputError, cell_text
from lgi.io.atomic import atomic_file

COLUMNS = ["frame", "marker", "x", "y", "z"]


@dataclass
class Bundles:
    """Marker positions over frames, dense.

    Attributes
    ----------
    frames : (F,) int64
        Frame numbers, ascending.
    markers : list of str, length M
    positions : (F, M, 3) float64
        NaN where a marker was not seen.
    """

    frames: np.ndarray
    markers: list[str]
    positions: np.ndarray

    @property
    def seen(self) -> np.ndarray:
        """(F, M) bool: marker seen in frame."""
        return np.all(np.isfinite(self.positions), axis=2)


def _row_ref(path: Path, df: pd.DataFrame, r: int, is_csv: bool) -> dict:
    frame = df["frame"].iloc[r] if "frame" in df else None
    try:
        frame = int(frame)
    except (TypeError, ValueError):
        frame = None
    marker = df["marker"].iloc[r] if "marker" in df else None
    if marker is None or (isinstance(marker, float) and np.isnan(marker)) or str(marker).strip() == "":
        marker = None
    # Parquet has no lines: its row (0-based, as pandas and pyarrow count them) is given instead.
    where = {"line": r + 2} if is_csv else {"path": f"{path} (row {r})"}
    return {"path": path, "frame": frame, "marker": None if marker is None else str(marker), **where}


#: Frame numbers above this are refused (they would not survive the int64 and float conversions downstream).
MAX_FRAME = 10**9
#: Bundles are head-stabilised positions in cm: anything farther than 10 m from the origin is not a face.
MAX_COORDINATE_CM = 1000.0


def _read_csv_typed(path: Path) -> pd.DataFrame | None:
    """A well-formed bundles CSV read with typed columns by pyarrow (0.05 s for 108,000 rows, where reading
    every field as text for the checks below took 0.8 s), or None when any field does not parse: the text
    path then finds the row and says what is wrong with it."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    types = {"frame": pa.float64(), "marker": pa.string(), "x": pa.float64(), "y": pa.float64(), "z": pa.float64()}
    try:
        table = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(
            column_types=types, include_columns=COLUMNS, null_values=["", "nan", "NaN", "NA"],
            strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowTypeError, KeyError, UnicodeDecodeError):
        return None
    if table.column("frame").null_count:
        return None
    return table.to_pandas()


def read_bundles(path: str | os.PathLike[str], markers: list[str] | None = None) -> Bundles:
    """Read and validate a bundles file.

    Parameters
    ----------
    path
        ``.csv`` or ``.parquet``.
    markers
        The layout's marker names. Rows naming any other marker are an error; the result has these
        markers in this order (markers never seen are all NaN). Without it, markers are taken from
        the file in order of first appearance.

    Returns
    -------
    Bundles
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("bundles file not found", path=path)
    is_csv = path.suffix.lower() != ".parquet"
    try:
        df = _read_csv_typed(path) if is_csv else None
        if is_csv and df is None:
            df = pd.read_csv(path, dtype={"marker": str, "frame": str, "x": str, "y": str, "z": str},
                             keep_default_na=False, encoding="utf-8-sig")
        elif not is_csv:
            df = pd.read_parquet(path)
    except Exception as exc:  # pandas raises many kinds for unreadable files
        raise InputError(f"cannot read bundles file: {exc}", path=path) from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in COLUMNS if c not in df.columns]
    if missing:
        raise InputError(f"missing columns {missing} (need {COLUMNS})", path=path)
    if df.empty:
        raise InputError("bundles file has no rows", path=path)
    for col in ("frame", "x", "y", "z"):
        # A typed table (Parquet) can hold true/false, which pandas would take as 0/1.
        if pd.api.types.is_bool_dtype(df[col]) or (df[col].dtype == object and
                                                   df[col].map(lambda v: isinstance(v, bool)).any()):
            raise InputError(f"column {col!r} holds true/false values, not numbers", path=path)
    no_name = df["marker"].isna().to_numpy() | (df["marker"].astype(str).str.strip() == "").to_numpy()
    if no_name.any():
        r = int(np.flatnonzero(no_name)[0])
        raise InputError("row without a marker name", **_row_ref(path, df, r, is_csv))

    frame_num = pd.to_numeric(df["frame"], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(frame_num) | (frame_num != np.round(frame_num))
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise InputError(f"frame {cell_text(df['frame'].iloc[r])} is not an integer", **_row_ref(path, df, r, is_csv))
    big = np.abs(frame_num) > MAX_FRAME
    if big.any():
        r = int(np.flatnonzero(big)[0])
        raise InputError(f"frame {cell_text(df['frame'].iloc[r])} is outside -{MAX_FRAME}..{MAX_FRAME}",
                         **_row_ref(path, df, r, is_csv))
    df["frame"] = frame_num.astype(np.int64)

    xyz = np.empty((len(df), 3))
    for k, col in enumerate("xyz"):
        raw = df[col]
        if not pd.api.types.is_numeric_dtype(raw):
            text = raw.astype(str).str.strip()
            empty = text.isin(["", "nan", "NaN", "NA"])
            num = pd.to_numeric(text.where(~empty, "nan"), errors="coerce")
            badnum = num.isna() & ~empty
            if badnum.any():
                r = int(np.flatnonzero(badnum.to_numpy())[0])
                raise InputError(f"non-numeric {col} value {cell_text(raw.iloc[r])}", **_row_ref(path, df, r, is_csv))
            xyz[:, k] = num.to_numpy(float)
        else:
            xyz[:, k] = pd.to_numeric(raw, errors="coerce").to_numpy(float)
    isnan = np.isnan(xyz)
    partial = isnan.any(1) & ~isnan.all(1)
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise InputError(f"some coordinates missing ({xyz[r].tolist()}): give all three or none",
                         **_row_ref(path, df, r, is_csv))
    inf = np.isinf(xyz).any(1)
    if inf.any():
        r = int(np.flatnonzero(inf)[0])
        raise InputError(f"non-finite coordinate {xyz[r].tolist()}", **_row_ref(path, df, r, is_csv))
    far = (np.abs(np.nan_to_num(xyz)) > MAX_COORDINATE_CM).any(1)
    if far.any():
        r = int(np.flatnonzero(far)[0])
        raise InputError(f"coordinate {xyz[r].tolist()} is beyond {MAX_COORDINATE_CM:g} cm from the origin (bundles "
                         "are in cm, in the head's frame)", **_row_ref(path, df, r, is_csv))

    names = df["marker"].astype(str).to_numpy()
    if markers is None:
        markers = list(dict.fromkeys(names.tolist()))
    col_of = {m: i for i, m in enumerate(markers)}
    unknown = np.array([n not in col_of for n in names])
    if unknown.any():
        r = int(np.flatnonzero(unknown)[0])
        raise InputError("unknown marker name (not in the marker layout)", **_row_ref(path, df, r, is_csv))
    dup = df.duplicated(subset=["frame", "marker"], keep="first").to_numpy()
    if dup.any():
        r = int(np.flatnonzero(dup)[0])
        raise InputError("duplicate (frame, marker) row", **_row_ref(path, df, r, is_csv))

    frames, frame_row = np.unique(df["frame"].to_numpy(), return_inverse=True)
    pos = np.full((len(frames), len(markers), 3), np.nan)
    pos[frame_row, [col_of[n] for n in names]] = xyz
    return Bundles(frames=frames, markers=list(markers), positions=pos)


def write_bundles(path: str | os.PathLike[str], bundles: Bundles) -> None:
    """Write a bundles file atomically (CSV or Parquet by extension); unseen markers get no row."""
    path = Path(path)
    f, m = np.nonzero(bundles.seen)
    df = pd.DataFrame({
        "frame": bundles.frames[f],
        "marker": np.asarray(bundles.markers, dtype=object)[m],
        "x": bundles.positions[f, m, 0],
        "y": bundles.positions[f, m, 1],
        "z": bundles.positions[f, m, 2],
    })
    with atomic_file(path) as tmp:
        if path.suffix.lower() == ".parquet":
            df.to_parquet(tmp, index=False)
        else:
            df.to_csv(tmp, index=False, float_format="%.9g")
