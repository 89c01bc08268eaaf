"""The bundles file: per-frame 3D marker positions in long format.

Columns ``frame, marker, x, y, z`` (CSV or Parquet, chosen by the extension). One row per seen marker
and frame; a marker not seen in a frame has no row, or a row whose x, y and z are all empty/NaN.
Coordinates are in the dataset's units. Validation rejects, naming frame and marker: unknown marker
names, duplicate (frame, marker) rows, non-integer frames, non-numeric values, infinite coordinates,
and rows with some but not all coordinates missing.

Optional uncertainty columns, one of: ``sigma`` (one standard deviation per coordinate, isotropic, the
positions' units) or the six ``cov_xx, cov_xy, cov_xz, cov_yy, cov_yz, cov_zz`` (the position's covariance in
the bundles' frame, the positions' units squared). A row may leave them empty (no value given). Validation
rejects, naming the row: non-numeric, negative or non-finite sigma, a covariance that is not positive
semi-definite or has some of its six entries empty, and an uncertainty on a row without a position; and, for the
file: both ``sigma`` and ``cov_*`` columns, or only some of the six ``cov_*`` columns.
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
#: The optional uncertainty columns: an isotropic standard deviation, or the covariance's six entries.
SIGMA_COLUMN = "sigma"
COV_COLUMNS = ["cov_xx", "cov_xy", "cov_xz", "cov_yy", "cov_yz", "cov_zz"]
#: (row, column) of each ``cov_*`` entry in the 3x3 matrix.
_COV_INDEX = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
#: A covariance is positive semi-definite when its smallest eigenvalue is at least this times minus its largest
#: (rounding of a rank-deficient matrix's entries).
PSD_TOLERANCE = 1e-12


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
    covariance : (F, M, 3, 3) float64, optional
        Each position's covariance, the positions' units squared, in the same frame (for ``lgi track``'s bundles:
        the head-stabilised frame, cm^2). NaN where the marker was not seen or no value was given; None when the
        file has no uncertainty columns. A file's ``sigma`` becomes ``sigma^2 I``.
    """

    frames: np.ndarray
    markers: list[str]
    positions: np.ndarray
    covariance: np.ndarray | None = None

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


def _csv_header(path: Path) -> list[str]:
    """The CSV's column names (stripped), from its first line; empty if it cannot be read."""
    import csv

    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            return [c.strip() for c in next(csv.reader([fh.readline()]), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def _read_csv_typed(path: Path, extra: list[str]) -> pd.DataFrame | None:
    """A well-formed bundles CSV read with typed columns by pyarrow (0.05 s for 108,000 rows, where reading
    every field as text for the checks below took 0.8 s), or None when any field does not parse: the text
    path then finds the row and says what is wrong with it. ``extra``: the uncertainty columns the file has."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    # Marker names as a dictionary (pandas: categorical): a long take repeats a hundred names millions of times.
    types = {"frame": pa.float64(), "marker": pa.dictionary(pa.int32(), pa.string()), "x": pa.float64(),
             "y": pa.float64(), "z": pa.float64(), **{c: pa.float64() for c in extra}}
    try:
        table = pacsv.read_csv(path, convert_options=pacsv.ConvertOptions(
            column_types=types, include_columns=COLUMNS + extra, null_values=["", "nan", "NaN", "NA"],
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
    extra = [c for c in _csv_header(path) if c in (SIGMA_COLUMN, *COV_COLUMNS)] if is_csv else []
    try:
        df = _read_csv_typed(path, extra) if is_csv else None
        if is_csv and df is None:
            df = pd.read_csv(path, dtype=dict.fromkeys(["marker", "frame", "x", "y", "z", *extra], str),
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
    sigma_col, cov_cols = _uncertainty_columns(path, df)
    for col in ("frame", "x", "y", "z", *sigma_col, *cov_cols):
        # A typed table (Parquet) can hold true/false, which pandas would take as 0/1.
        if pd.api.types.is_bool_dtype(df[col]) or (df[col].dtype == object and
                                                   df[col].map(lambda v: isinstance(v, bool)).any()):
            raise InputError(f"column {col!r} holds true/false values, not numbers", path=path)
    codes, names = _marker_codes(df["marker"])
    no_name = codes < 0
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
        xyz[:, k] = _numbers(path, df, col, is_csv)
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

    if markers is None:
        markers = [names[c] for c in pd.unique(codes)]
    col_of = {m: i for i, m in enumerate(markers)}
    column = np.array([col_of.get(n, -1) for n in names], np.int64)[codes]
    unknown = column < 0
    if unknown.any():
        r = int(np.flatnonzero(unknown)[0])
        raise InputError("unknown marker name (not in the marker layout)", **_row_ref(path, df, r, is_csv))
    frames, frame_row = np.unique(df["frame"].to_numpy(), return_inverse=True)
    dup = pd.Series(frame_row.astype(np.int64) * len(markers) + column).duplicated(keep="first").to_numpy()
    if dup.any():
        r = int(np.flatnonzero(dup)[0])
        raise InputError("duplicate (frame, marker) row", **_row_ref(path, df, r, is_csv))

    cov_rows = _row_covariances(path, df, is_csv, xyz, sigma_col, cov_cols)

    pos = np.full((len(frames), len(markers), 3), np.nan)
    where = (frame_row, column)
    pos[where] = xyz
    cov = None
    if cov_rows is not None:
        cov = np.full((len(frames), len(markers), 3, 3), np.nan)
        cov[where] = cov_rows
    return Bundles(frames=frames, markers=list(markers), positions=pos, covariance=cov)


def _marker_codes(column: pd.Series) -> tuple[np.ndarray, list[str]]:
    """The marker column as codes (N,) int64 into its distinct names as written (code -1: a row without a name,
    empty, blank or missing), and those names."""
    if isinstance(column.dtype, pd.CategoricalDtype):
        names = [str(c) for c in column.cat.categories]
        codes = column.cat.codes.to_numpy().astype(np.int64)
    else:
        codes, uniq = pd.factorize(column.astype(str).where(column.notna(), ""))
        names = [str(c) for c in uniq]
    blank = np.array([n.strip() == "" for n in names] + [True])  # the last entry stands for code -1
    return np.where(blank[codes], -1, codes), names


def _numbers(path: Path, df: pd.DataFrame, col: str, is_csv: bool) -> np.ndarray:
    """A column as float64, empty/NaN cells as NaN; a cell that is not a number is an error naming its row."""
    raw = df[col]
    if pd.api.types.is_numeric_dtype(raw):
        return pd.to_numeric(raw, errors="coerce").to_numpy(float)
    text = raw.astype(str).str.strip()
    empty = text.isin(["", "nan", "NaN", "NA"]) | raw.isna()
    num = pd.to_numeric(text.where(~empty, "nan"), errors="coerce")
    badnum = num.isna() & ~empty
    if badnum.any():
        r = int(np.flatnonzero(badnum.to_numpy())[0])
        raise InputError(f"non-numeric {col} value {cell_text(raw.iloc[r])}", **_row_ref(path, df, r, is_csv))
    return num.to_numpy(float)


def _uncertainty_columns(path: Path, df: pd.DataFrame) -> tuple[list[str], list[str]]:
    """The file's uncertainty columns: ``(["sigma"], [])``, ``([], COV_COLUMNS)`` or neither; refuses both, and
    some of the six ``cov_*`` without the others."""
    sigma = [SIGMA_COLUMN] if SIGMA_COLUMN in df.columns else []
    cov = [c for c in COV_COLUMNS if c in df.columns]
    if sigma and cov:
        raise InputError(f"both a {SIGMA_COLUMN!r} column and covariance columns ({', '.join(cov)}): give one "
                         "uncertainty, sigma (isotropic) or the six cov_* entries", path=path)
    if cov and len(cov) < len(COV_COLUMNS):
        missing = [c for c in COV_COLUMNS if c not in cov]
        raise InputError(f"covariance columns {', '.join(missing)} missing: give all six of "
                         f"{', '.join(COV_COLUMNS)} or none", path=path)
    return sigma, cov


def _row_covariances(path: Path, df: pd.DataFrame, is_csv: bool, xyz: np.ndarray, sigma_col: list[str],
                     cov_cols: list[str]) -> np.ndarray | None:
    """(N, 3, 3) covariance per row from the ``sigma`` or ``cov_*`` columns (NaN where none is given), or None
    without them; a bad value is an error naming its row."""
    if not sigma_col and not cov_cols:
        return None
    vals = np.column_stack([_numbers(path, df, c, is_csv) for c in sigma_col + cov_cols])
    given = ~np.isnan(vals)
    some = given.any(axis=1)
    unseen = some & np.isnan(xyz).all(axis=1)
    if unseen.any():
        r = int(np.flatnonzero(unseen)[0])
        raise InputError("an uncertainty on a row without a position (x, y, z empty): give the position or leave "
                         "the uncertainty empty", **_row_ref(path, df, r, is_csv))
    partial = some & ~given.all(axis=1)
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise InputError(f"some covariance entries missing ({_entries(cov_cols, vals[r])}): give all six or none",
                         **_row_ref(path, df, r, is_csv))
    inf = np.isinf(vals).any(axis=1)
    if inf.any():
        r = int(np.flatnonzero(inf)[0])
        raise InputError(f"non-finite uncertainty ({_entries(sigma_col + cov_cols, vals[r])})",
                         **_row_ref(path, df, r, is_csv))
    cov = np.full((len(df), 3, 3), np.nan)
    if sigma_col:
        s = vals[:, 0]
        neg = s < 0
        if neg.any():
            r = int(np.flatnonzero(neg)[0])
            raise InputError(f"negative sigma {s[r]!r}: a standard deviation is >= 0", **_row_ref(path, df, r, is_csv))
        cov[some] = (s[some] ** 2)[:, None, None] * np.eye(3)
        return cov
    for k, (i, j) in enumerate(_COV_INDEX):
        cov[some, i, j] = cov[some, j, i] = vals[some, k]
    if some.any():
        eig = np.linalg.eigvalsh(cov[some])
        bad = eig[:, 0] < -PSD_TOLERANCE * np.maximum(np.abs(eig).max(axis=1), np.finfo(float).tiny)
        if bad.any():
            r = int(np.flatnonzero(some)[np.flatnonzero(bad)[0]])
            e = eig[np.flatnonzero(bad)[0]]
            raise InputError(f"the covariance ({_entries(cov_cols, vals[r])}) is not positive semi-definite "
                             f"(eigenvalues {', '.join(f'{v:.6g}' for v in e)})", **_row_ref(path, df, r, is_csv))
    return cov


def _entries(cols: list[str], values: np.ndarray) -> str:
    return ", ".join(f"{c}={v:g}" for c, v in zip(cols, values, strict=True))


def write_bundles(path: str | os.PathLike[str], bundles: Bundles) -> None:
    """Write a bundles file atomically (CSV or Parquet by extension); unseen markers get no row.

    With ``bundles.covariance``, the six ``cov_*`` columns too (empty where it is NaN), in CSV at full precision
    (the shortest text that reads back as the same float64), so a covariance reads back bit for bit."""
    path = Path(path)
    f, m = np.nonzero(bundles.seen)
    df = pd.DataFrame({
        "frame": bundles.frames[f],
        "marker": np.asarray(bundles.markers, dtype=object)[m],
        "x": bundles.positions[f, m, 0],
        "y": bundles.positions[f, m, 1],
        "z": bundles.positions[f, m, 2],
    })
    if bundles.covariance is not None:
        cov = np.asarray(bundles.covariance, np.float64)
        if cov.shape != (*bundles.positions.shape, 3):
            raise ValueError(f"covariance is {cov.shape}, the positions need {(*bundles.positions.shape, 3)}")
        csv = path.suffix.lower() != ".parquet"
        for name, (i, j) in zip(COV_COLUMNS, _COV_INDEX, strict=True):
            v = cov[f, m, i, j]
            df[name] = [repr(x) if x == x else "" for x in v.tolist()] if csv else v
    with atomic_file(path) as tmp:
        if path.suffix.lower() == ".parquet":
            df.to_parquet(tmp, index=False)
        else:
            df.to_csv(tmp, index=False, float_format="%.9g")
