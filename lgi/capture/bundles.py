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

The file is read a batch of rows at a time (:data:`BATCH_ROWS`), so reading holds a batch, not the file: a
36,000-frame take of 108 markers is 3.9 million rows.
"""

from __future__ import annotations

import csv
import os
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import pandas as pd

from lgi.errors import InputError, cell_text
from lgi.io.atomic import atomic_file
from lgi.io.csvio import check_field_counts
from lgi.io.stored import ScratchArray, scratch_space
from lgi.memory import release_free_memory

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
    positions : (F, M, 3) float64, a numpy array or a :class:`~lgi.io.stored.ScratchArray`
        NaN where a marker was not seen. ``read_bundles(..., on_disk=True)`` gives a ScratchArray (an unnamed
        temporary file, read by frame range with ``rows(lo, hi)``; ``np.asarray`` reads it whole).
    covariance : (F, M, 3, 3) float64, optional, the same kind of array as ``positions``
        Each position's covariance, the positions' units squared, in the same frame (for ``lgi track``'s bundles:
        the head-stabilised frame, cm^2). NaN where the marker was not seen or no value was given; None when the
        file has no uncertainty columns. A file's ``sigma`` becomes ``sigma^2 I``.
    """

    frames: np.ndarray
    markers: list[str]
    positions: np.ndarray | ScratchArray
    covariance: np.ndarray | ScratchArray | None = None

    @property
    def seen(self) -> np.ndarray:
        """(F, M) bool: marker seen in frame."""
        return np.all(np.isfinite(self.positions), axis=2)


#: Frame numbers above this are refused (they would not survive the int64 and float conversions downstream).
MAX_FRAME = 10**9
#: Bundles are head-stabilised positions in cm: anything farther than 10 m from the origin is not a face.
MAX_COORDINATE_CM = 1000.0
#: Rows read, checked and put in place at a time.
BATCH_ROWS = 1 << 15
#: A CSV is read in blocks of this many bytes per batch row (a bundles row is 30 to 80 characters).
CSV_ROW_BYTES = 64
#: A Parquet file's column chunks are read this many bytes at a time.
PARQUET_READ_BYTES = 1 << 16
#: With ``on_disk``, the result is filled in memory a window of consecutive frames of at most this many bytes
#: (positions and covariances) at a time.
WINDOW_BYTES = 8 << 20


class _Untyped(Exception):
    """A field of the CSV does not parse as its column's type: the file is read again as text (see
    :func:`_csv_typed_batches`)."""


def _where(path: Path, n: int, is_csv: bool, frame: int | None, marker: str | None) -> dict:
    """The file's data row n (0-based, the header not counted) as :class:`InputError`'s keywords."""
    # Parquet has no lines: its row (0-based, as pandas and pyarrow count them) is given instead.
    where = {"line": n + 2} if is_csv else {"path": f"{path} (row {n})"}
    return {"path": path, "frame": frame, "marker": marker, **where}


@dataclass
class _Batch:
    """Consecutive rows of a bundles file: ``df``'s row r is the file's data row ``base + r``."""

    path: Path
    df: pd.DataFrame
    base: int
    is_csv: bool

    def ref(self, r: int) -> dict:
        """Where row r is, as :class:`InputError`'s keywords: path, line (CSV) or row (Parquet), frame, marker."""
        df = self.df
        frame = df["frame"].iloc[r] if "frame" in df else None
        try:
            frame = int(frame)
        except (TypeError, ValueError):
            frame = None
        marker = df["marker"].iloc[r] if "marker" in df else None
        if marker is None or (isinstance(marker, float) and np.isnan(marker)) or str(marker).strip() == "":
            marker = None
        return _where(self.path, self.base + r, self.is_csv, frame, None if marker is None else str(marker))


def _csv_header(path: Path) -> list[str]:
    """The CSV's column names (stripped), from its first line; empty if it cannot be read."""
    try:
        with open(path, encoding="utf-8-sig", newline="") as fh:
            return [c.strip() for c in next(csv.reader([fh.readline()]), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return []


def _csv_typed_batches(path: Path, extra: list[str]) -> Iterator[pd.DataFrame]:
    """A well-formed bundles CSV in batches of typed columns read by pyarrow (0.05 s for 108,000 rows, where reading
    every field as text for the checks took 0.8 s); raises :class:`_Untyped` at the first batch with a field that
    does not parse, for the text path to find the row and say what is wrong with it. ``extra``: the uncertainty
    columns the file has.

    Each batch is the header and the whole lines of the file's next block, parsed as a CSV of its own: pyarrow's
    streaming reader (``open_csv``) reads 32 blocks ahead, which held 130 MB of a 170 MB file in 4 MB blocks.
    """
    import pyarrow as pa
    import pyarrow.csv as pacsv

    # Marker names as a dictionary (pandas: categorical): a long take repeats a hundred names millions of times.
    types = {"frame": pa.float64(), "marker": pa.dictionary(pa.int32(), pa.string()), "x": pa.float64(),
             "y": pa.float64(), "z": pa.float64(), **{c: pa.float64() for c in extra}}
    convert = pacsv.ConvertOptions(column_types=types, include_columns=COLUMNS + extra,
                                   null_values=["", "nan", "NaN", "NA"], strings_can_be_null=False)
    # The C heap reuses what a batch freed for the next one; pyarrow's default pool (mimalloc) kept each parsing
    # thread's share of it besides (measured on 2 MB blocks: 28 MB resident here, 48 MB there).
    pool = pa.system_memory_pool()
    with open(path, "rb") as fh:
        header, rest = fh.readline(), b""
        while True:
            block = fh.read(BATCH_ROWS * CSV_ROW_BYTES)
            data = bytearray(header)
            data += rest
            data += block
            # pyarrow ends a row at every line end (quoted ones too), so whole lines are whole rows.
            end = data.rfind(b"\n") + 1 if block else len(data)
            if block and end <= len(header):  # no line ends in this block: read on
                rest = bytes(data[len(header):])
                continue
            rest = bytes(data[end:])
            try:
                table = pacsv.read_csv(pa.py_buffer(memoryview(data)[:end]), convert_options=convert,
                                       memory_pool=pool)
            except (pa.ArrowInvalid, pa.ArrowTypeError, KeyError, UnicodeDecodeError):
                raise _Untyped from None
            if table.column("frame").null_count:
                raise _Untyped
            yield table.to_pandas(memory_pool=pool)
            if not block:
                return


def _parquet_batches(path: Path, columns: list[str], names: list[str]) -> Iterator[pd.DataFrame]:
    """The Parquet file's ``columns`` in batches, renamed ``names``."""
    import pyarrow.parquet as pq

    # A row group's column chunks read as they are decoded (not all first: pre-buffering), in small reads, by one
    # thread: 50 MB resident for 3.9 million rows in row groups of a million, where the defaults held 100 MB.
    with pq.ParquetFile(path, pre_buffer=False, buffer_size=PARQUET_READ_BYTES) as pf:
        for batch in pf.iter_batches(batch_size=BATCH_ROWS, columns=columns, use_threads=False):
            df = batch.to_pandas()
            df.columns = names
            yield df


def read_bundles(path: str | os.PathLike[str], markers: list[str] | None = None, *, on_disk: bool = False) -> Bundles:
    """Read and validate a bundles file, a batch of rows at a time.

    Parameters
    ----------
    path
        ``.csv`` or ``.parquet``.
    markers
        The layout's marker names. Rows naming any other marker are an error; the result has these
        markers in this order (markers never seen are all NaN). Without it, markers are taken from
        the file in order of first appearance.
    on_disk
        The positions (and covariances) as :class:`~lgi.io.stored.ScratchArray` in unnamed temporary files, not
        in memory: reading then holds a batch of rows (:data:`BATCH_ROWS`) and a window of frames
        (:data:`WINDOW_BYTES`), not the result (a 36,000-frame take of 108 markers: 93 MB of positions, 280 MB of
        covariances). Either way the checked rows wait between the two passes in an unnamed temporary file (36 bytes
        a row, 84 with covariances; see :func:`_read`).

    Returns
    -------
    Bundles
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("bundles file not found", path=path)
    if path.suffix.lower() == ".parquet":
        import pyarrow.parquet as pq

        try:
            schema = pq.read_schema(path)
        except Exception as exc:  # pyarrow raises several kinds for unreadable files
            raise InputError(f"cannot read bundles file: {exc}", path=path) from None
        names = [str(c).strip() for c in schema.names]
        keep = [i for i, c in enumerate(names) if c in (*COLUMNS, SIGMA_COLUMN, *COV_COLUMNS)]
        batches = _parquet_batches(path, [schema.names[i] for i in keep], [names[i] for i in keep])
        return _read(path, batches, names, False, markers, on_disk)
    extra = [c for c in _csv_header(path) if c in (SIGMA_COLUMN, *COV_COLUMNS)]
    try:
        return _read(path, _csv_typed_batches(path, extra), COLUMNS + extra, True, markers, on_disk)
    except _Untyped:
        pass
    # A file pyarrow cannot type (a field that is not a number, blanks around a number, an empty frame) is read
    # whole as text: the checks then say which row is wrong and how.

    check_field_counts(path, "bundles file")
    try:
        df = pd.read_csv(path, dtype=dict.fromkeys(["marker", "frame", "x", "y", "z", *extra], str),
                         keep_default_na=False, encoding="utf-8-sig")
    except Exception as exc:  # pandas raises many kinds for unreadable files
        raise InputError(f"cannot read bundles file: {exc}", path=path) from None
    df.columns = [str(c).strip() for c in df.columns]
    return _read(path, iter([df]), list(df.columns), True, markers, on_disk)


def _read(path: Path, batches: Iterator[pd.DataFrame], columns: list[str], is_csv: bool,
          markers: list[str] | None, on_disk: bool) -> Bundles:
    """The bundles in the file whose rows ``batches`` gives and whose columns (stripped) are ``columns``.

    Pass 1 checks each batch's rows, collects the frame numbers and marker names, and keeps the rows' frame, marker
    column and values (:func:`_spool_dtype`) in an unnamed temporary file, the spool; pass 2 (:func:`_place`) puts
    the spooled rows in their places. So the file is parsed once: a second parse (0.9 s for 3.9 million rows, 170 MB
    of CSV) made the reading take 1.5 times as long as reading the file whole had.
    """
    missing = [c for c in COLUMNS if c not in columns]
    if missing:
        raise InputError(f"missing columns {missing} (need {COLUMNS})", path=path)
    col_of = {} if markers is None else {m: i for i, m in enumerate(markers)}
    uncertainty: tuple[list[str], list[str]] | None = None
    # The distinct frames so far, merged when the batches' own add up to as many (a sorted file's batches each
    # hold a few hundred frames, a shuffled file's nearly all of them).
    frames, pending, n_pending = np.zeros(0, np.int64), [], 0
    # The smallest and largest frame number of each BATCH_ROWS rows of the spool: pass 2 reads only those it needs.
    ranges: list[tuple[int, int]] = []
    n_rows = 0
    with scratch_space(), tempfile.TemporaryFile() as spool:
        for batch in _batches(path, batches, is_csv):
            if uncertainty is None:
                # After the rows, as before: a file with no rows says so whatever its columns.
                uncertainty = _uncertainty_columns(path, columns)
                row = _spool_dtype(bool(uncertainty[0] or uncertainty[1]))
            frame, column, xyz, cov = _batch_rows(batch, col_of, markers is None, *uncertainty)
            rows = np.empty(len(frame), row)
            rows["frame"], rows["column"], rows["xyz"] = frame, column, xyz
            if cov is not None:
                rows["cov"] = cov
            spool.write(rows.view(np.uint8))
            for c in range(n_rows // BATCH_ROWS, (n_rows + len(rows) - 1) // BATCH_ROWS + 1):
                part = frame[max(0, c * BATCH_ROWS - n_rows):(c + 1) * BATCH_ROWS - n_rows]
                lo, hi = int(part.min()), int(part.max())
                if c == len(ranges):
                    ranges.append((lo, hi))
                else:
                    ranges[c] = (min(lo, ranges[c][0]), max(hi, ranges[c][1]))
            n_rows += len(rows)
            pending.append(_distinct(frame))
            n_pending += len(pending[-1])
            if n_pending >= len(frames):
                frames, pending, n_pending = _distinct(np.concatenate([frames, *pending])), [], 0
        if uncertainty is None:
            raise InputError("bundles file has no rows", path=path)
        frames = _distinct(np.concatenate([frames, *pending]))
        markers = list(col_of) if markers is None else list(markers)
        # Pass 1's batches, freed, go back to the system before pass 2 takes its windows, which else came on top
        # (3.9 million rows on disk: 44 MB resident at most, not 56 MB).
        release_free_memory()
        positions, covariance = _place(path, is_csv, spool, row, ranges, n_rows, frames, markers, on_disk)
    return Bundles(frames=frames, markers=markers, positions=positions, covariance=covariance)


def _place(path: Path, is_csv: bool, spool: BinaryIO, row: np.dtype, ranges: list[tuple[int, int]], n_rows: int,
           frames: np.ndarray, markers: list[str],
           on_disk: bool) -> tuple[np.ndarray | ScratchArray, np.ndarray | ScratchArray | None]:
    """Pass 2: the ``n_rows`` spooled rows in their (frame, marker) places: (F, M, 3) positions and (F, M, 3, 3)
    covariances (None without them), NaN where no row gives a value, as numpy arrays or (``on_disk``)
    :class:`ScratchArray`. A (frame, marker) given twice is an error naming the second row.

    The result is filled a window of consecutive frames at a time from the parts of the spool whose frame range
    (``ranges``) meets the window: in memory, one window of all frames; on disk, windows of :data:`WINDOW_BYTES`,
    each written once. A file sorted by frame is so read from the spool about once, a shuffled one once per window.
    """
    shapes = [(len(markers), 3)] + ([(len(markers), 3, 3)] if "cov" in row.names else [])
    n_frames = len(frames)
    if on_disk:
        out = [ScratchArray((n_frames, *shape), np.float64) for shape in shapes]
        span = max(1, WINDOW_BYTES // sum(int(np.prod(shape)) * np.dtype(np.float64).itemsize for shape in shapes))
    else:
        span = n_frames
    buf = np.empty(BATCH_ROWS, row)
    first_dup: tuple[int, int, int] | None = None  # row, frame, marker column
    for wlo in range(0, n_frames, span):
        whi = min(n_frames, wlo + span)
        window = [np.full((whi - wlo, *shape), np.nan) for shape in shapes]
        given = np.zeros((whi - wlo, len(markers)), bool)
        for c, (lo, hi) in enumerate(ranges):
            if hi < frames[wlo] or lo > frames[whi - 1]:
                continue
            rows = buf[:min(BATCH_ROWS, n_rows - c * BATCH_ROWS)]
            spool.seek(c * BATCH_ROWS * row.itemsize)
            spool.readinto(rows.view(np.uint8))
            frame = rows["frame"]
            sel = np.flatnonzero((frame >= frames[wlo]) & (frame <= frames[whi - 1]))
            f, column = np.searchsorted(frames, frame[sel]) - wlo, rows["column"][sel]
            # Given before, or earlier among these rows (which may span batches of the file).
            again = given[f, column] | pd.Series(f * len(markers) + column).duplicated().to_numpy()
            if again.any():
                r = int(sel[np.flatnonzero(again)[0]])
                if first_dup is None or c * BATCH_ROWS + r < first_dup[0]:
                    first_dup = (c * BATCH_ROWS + r, int(rows["frame"][r]), int(rows["column"][r]))
                break  # the window's other rows come later in the file
            given[f, column] = True
            window[0][f, column] = rows["xyz"][sel]
            if len(window) > 1:
                window[1][f, column] = _symmetric(rows["cov"][sel])
        if on_disk:
            for a, w in zip(out, window, strict=True):
                a.write(wlo, w)
        else:
            out = window
    if first_dup is not None:
        for a in out if on_disk else []:
            a.close()  # its file goes now, not when collected
        n, frame, column = first_dup
        raise InputError("duplicate (frame, marker) row", **_where(path, n, is_csv, frame, markers[column]))
    return out[0], out[1] if len(out) > 1 else None


def _distinct(a: np.ndarray) -> np.ndarray:
    """The distinct values of ``a`` (N,), ascending: ``np.unique``, without its hashing first (8 times slower on a
    shuffled file's 48,000 frame numbers of a batch)."""
    a = np.sort(a)
    first = np.ones(len(a), bool)
    first[1:] = a[1:] != a[:-1]
    return a[first]


def _spool_dtype(covariance: bool) -> np.dtype:
    """A spooled row: its frame number, marker column, position and (with ``covariance``) the six ``cov_*``
    entries (NaN: none given)."""
    fields = [("frame", np.int64), ("column", np.int32), ("xyz", np.float64, (3,))]
    return np.dtype(fields + ([("cov", np.float64, (len(COV_COLUMNS),))] if covariance else []))


def _batches(path: Path, batches: Iterator[pd.DataFrame], is_csv: bool) -> Iterator[_Batch]:
    """The file's non-empty batches; a failure to read them is an :class:`InputError` (a field that does not parse
    as typed, :class:`_Untyped`, is left to the caller)."""
    base = 0
    while True:
        try:
            df = next(batches)
        except StopIteration:
            return
        except _Untyped:
            raise
        except Exception as exc:  # pyarrow and pandas raise many kinds for unreadable files
            raise InputError(f"cannot read bundles file: {exc}", path=path) from None
        if len(df):
            yield _Batch(path, df, base, is_csv)
        base += len(df)


def _batch_rows(batch: _Batch, col_of: dict[str, int], new_markers: bool, sigma_col: list[str],
                cov_cols: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A batch's rows, checked: frame (N,) int64, marker column (N,) int64, position (N, 3) and the six ``cov_*``
    entries (N, 6) (None without uncertainty columns), in the file's units.

    ``col_of`` maps marker names to columns; with ``new_markers``, names it lacks are added in order of first
    appearance, otherwise they are unknown. A bad row is an error naming it, in the order of the checks below.
    """
    path, df = batch.path, batch.df
    for col in ("frame", "x", "y", "z", *sigma_col, *cov_cols):
        # A typed table (Parquet) can hold true/false, which pandas would take as 0/1.
        if pd.api.types.is_bool_dtype(df[col]) or (df[col].dtype == object and
                                                   df[col].map(lambda v: isinstance(v, bool)).any()):
            raise InputError(f"column {col!r} holds true/false values, not numbers", path=path)
    codes, names = _marker_codes(df["marker"])
    no_name = codes < 0
    if no_name.any():
        raise InputError("row without a marker name", **batch.ref(int(np.flatnonzero(no_name)[0])))

    frame_num = pd.to_numeric(df["frame"], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(frame_num) | (frame_num != np.round(frame_num))
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise InputError(f"frame {cell_text(df['frame'].iloc[r])} is not an integer", **batch.ref(r))
    big = np.abs(frame_num) > MAX_FRAME
    if big.any():
        r = int(np.flatnonzero(big)[0])
        raise InputError(f"frame {cell_text(df['frame'].iloc[r])} is outside -{MAX_FRAME}..{MAX_FRAME}",
                         **batch.ref(r))
    frame = frame_num.astype(np.int64)

    xyz = np.empty((len(df), 3))
    for k, col in enumerate("xyz"):
        xyz[:, k] = _numbers(batch, col)
    isnan = np.isnan(xyz)
    partial = isnan.any(1) & ~isnan.all(1)
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise InputError(f"some coordinates missing ({xyz[r].tolist()}): give all three or none", **batch.ref(r))
    inf = np.isinf(xyz).any(1)
    if inf.any():
        r = int(np.flatnonzero(inf)[0])
        raise InputError(f"non-finite coordinate {xyz[r].tolist()}", **batch.ref(r))
    # NaN compares false, and no coordinate is infinite any more.
    far = (np.abs(xyz) > MAX_COORDINATE_CM).any(1)
    if far.any():
        r = int(np.flatnonzero(far)[0])
        raise InputError(f"coordinate {xyz[r].tolist()} is beyond {MAX_COORDINATE_CM:g} cm from the origin (bundles "
                         "are in cm, in the head's frame)", **batch.ref(r))

    if new_markers:
        for c in pd.unique(codes):
            col_of.setdefault(names[c], len(col_of))
    column = np.array([col_of.get(n, -1) for n in names], np.int64)[codes]
    unknown = column < 0
    if unknown.any():
        raise InputError("unknown marker name (not in the marker layout)", **batch.ref(int(np.flatnonzero(unknown)[0])))
    # Within the batch; pass 2 finds a (frame, marker) that an earlier batch gave.
    dup = pd.Series((frame + MAX_FRAME) * (int(column.max()) + 1) + column).duplicated(keep="first").to_numpy()
    if dup.any():
        raise InputError("duplicate (frame, marker) row", **batch.ref(int(np.flatnonzero(dup)[0])))

    return frame, column, xyz, _row_covariances(batch, xyz, sigma_col, cov_cols)


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


def _numbers(batch: _Batch, col: str) -> np.ndarray:
    """A column as float64, empty/NaN cells as NaN; a cell that is not a number is an error naming its row."""
    raw = batch.df[col]
    if pd.api.types.is_numeric_dtype(raw):
        return pd.to_numeric(raw, errors="coerce").to_numpy(float)
    text = raw.astype(str).str.strip()
    empty = text.isin(["", "nan", "NaN", "NA"]) | raw.isna()
    num = pd.to_numeric(text.where(~empty, "nan"), errors="coerce")
    badnum = num.isna() & ~empty
    if badnum.any():
        r = int(np.flatnonzero(badnum.to_numpy())[0])
        raise InputError(f"non-numeric {col} value {cell_text(raw.iloc[r])}", **batch.ref(r))
    return num.to_numpy(float)


def _uncertainty_columns(path: Path, columns: list[str]) -> tuple[list[str], list[str]]:
    """The file's uncertainty columns among its ``columns``: ``(["sigma"], [])``, ``([], COV_COLUMNS)`` or neither;
    refuses both, and some of the six ``cov_*`` without the others."""
    sigma = [SIGMA_COLUMN] if SIGMA_COLUMN in columns else []
    cov = [c for c in COV_COLUMNS if c in columns]
    if sigma and cov:
        raise InputError(f"both a {SIGMA_COLUMN!r} column and covariance columns ({', '.join(cov)}): give one "
                         "uncertainty, sigma (isotropic) or the six cov_* entries", path=path)
    if cov and len(cov) < len(COV_COLUMNS):
        missing = [c for c in COV_COLUMNS if c not in cov]
        raise InputError(f"covariance columns {', '.join(missing)} missing: give all six of "
                         f"{', '.join(COV_COLUMNS)} or none", path=path)
    return sigma, cov


def _row_covariances(batch: _Batch, xyz: np.ndarray, sigma_col: list[str], cov_cols: list[str]) -> np.ndarray | None:
    """(N, 6) ``cov_*`` entries per row from the ``sigma`` or ``cov_*`` columns (NaN where none is given), or None
    without them; a bad value is an error naming its row."""
    if not sigma_col and not cov_cols:
        return None
    vals = np.column_stack([_numbers(batch, c) for c in sigma_col + cov_cols])
    given = ~np.isnan(vals)
    some = given.any(axis=1)
    unseen = some & np.isnan(xyz).all(axis=1)
    if unseen.any():
        raise InputError("an uncertainty on a row without a position (x, y, z empty): give the position or leave "
                         "the uncertainty empty", **batch.ref(int(np.flatnonzero(unseen)[0])))
    partial = some & ~given.all(axis=1)
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise InputError(f"some covariance entries missing ({_entries(cov_cols, vals[r])}): give all six or none",
                         **batch.ref(r))
    inf = np.isinf(vals).any(axis=1)
    if inf.any():
        r = int(np.flatnonzero(inf)[0])
        raise InputError(f"non-finite uncertainty ({_entries(sigma_col + cov_cols, vals[r])})", **batch.ref(r))
    if sigma_col:
        s = vals[:, 0]
        neg = s < 0
        if neg.any():
            r = int(np.flatnonzero(neg)[0])
            raise InputError(f"negative sigma {s[r]!r}: a standard deviation is >= 0", **batch.ref(r))
        # sigma^2 I's entries; a row without sigma is NaN throughout.
        return (s**2)[:, None] * np.array([float(i == j) for i, j in _COV_INDEX])
    if some.any():
        eig = np.linalg.eigvalsh(_symmetric(vals[some]))
        bad = eig[:, 0] < -PSD_TOLERANCE * np.maximum(np.abs(eig).max(axis=1), np.finfo(float).tiny)
        if bad.any():
            r = int(np.flatnonzero(some)[np.flatnonzero(bad)[0]])
            e = eig[np.flatnonzero(bad)[0]]
            raise InputError(f"the covariance ({_entries(cov_cols, vals[r])}) is not positive semi-definite "
                             f"(eigenvalues {', '.join(f'{v:.6g}' for v in e)})", **batch.ref(r))
    return vals


def _symmetric(entries: np.ndarray) -> np.ndarray:
    """(N, 3, 3) symmetric matrices from their six ``cov_*`` entries (N, 6)."""
    out = np.empty((len(entries), 3, 3))
    for k, (i, j) in enumerate(_COV_INDEX):
        out[:, i, j] = out[:, j, i] = entries[:, k]
    return out


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
