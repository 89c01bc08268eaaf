"""Writing large tables as CSV.

A reconstruction's diagnostics hold a row per bundle and frame (108,000 for 1000 frames of the ICT layout);
pandas' writer took 4.6 s for them, 5 ms of every frame's budget. pyarrow's C++ writer takes 0.4 s.
Floats are written at full precision (shortest round-trip form), missing values as empty fields, strings
quoted only where needed.
"""

from __future__ import annotations

import os

import numpy as np
import pandas as pd


def write_csv(table: pd.DataFrame, path: str | os.PathLike[str]) -> None:
    """Write ``table`` (no index) to ``path`` as CSV with pyarrow."""
    out = CsvAppender(path)
    out.append(table)
    out.close()


class CsvAppender:
    """A CSV written table by table (no index): the header from the first, every later table's rows after it in
    the first's columns; the bytes :func:`write_csv` writes for the tables joined.

    ``resume``: ``(size, schema)`` of a file :meth:`flush` reported (its bytes, and the columns' types as
    :meth:`schema_bytes` gave them): the file is cut back to that size and the tables go on after it."""

    def __init__(self, path: str | os.PathLike[str], resume: tuple[int, bytes] | None = None) -> None:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        self.path = path
        self._writer = None
        self._schema = None
        self._sink = None
        if resume is not None:
            os.truncate(path, resume[0])
            self._schema = pa.ipc.read_schema(pa.py_buffer(resume[1]))
            self._sink = pa.OSFile(os.fspath(path), "ab")
            self._writer = pacsv.CSVWriter(self._sink, self._schema, write_options=pacsv.WriteOptions(
                quoting_style="needed", include_header=False))

    def append(self, table: pd.DataFrame) -> None:
        import pyarrow as pa
        import pyarrow.csv as pacsv

        arrow = pa.Table.from_pandas(table, preserve_index=False).replace_schema_metadata(None)
        if self._writer is None:
            self._schema = arrow.schema
            self._sink = pa.OSFile(os.fspath(self.path), "wb")
            self._writer = pacsv.CSVWriter(self._sink, self._schema,
                                           write_options=pacsv.WriteOptions(quoting_style="needed"))
        elif not arrow.schema.equals(self._schema):
            arrow = arrow.cast(self._schema)
        self._writer.write_table(arrow)

    def flush(self) -> tuple[int, bytes]:
        """Put the rows written so far on disk; returns the file's size and its columns' types (for ``resume``)."""
        if self._sink is None:
            return 0, b""
        self._sink.flush()
        fd = os.open(self.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        return self._sink.tell(), self._schema.serialize().to_pybytes()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
        if self._sink is not None:
            self._sink.close()
            self._sink = None


def read_table(path: str | os.PathLike[str], what: str, columns: tuple[str, ...], numeric: tuple[str, ...] = (),
               key: str | None = None, allow_missing: tuple[str, ...] = (), need_rows: bool = True) -> pd.DataFrame:
    """Read a user's CSV table, refusing what is wrong with the file, line and row named.

    Parameters
    ----------
    what : str
        The table's name in messages ("helmet marker file").
    columns : tuple of str
        Required columns (header names, surrounding spaces and a UTF-8 byte-order mark ignored).
    numeric : tuple of str
        Columns that must hold finite numbers (returned as float64).
    key : str, optional
        A column naming the row's marker, given in messages.
    allow_missing : tuple of str
        Numeric columns whose empty cells become NaN instead of an error.

    Returns
    -------
    DataFrame, numeric columns float64, the others str.
    """
    from lgi.errors import InputError

    if not os.path.isfile(path):
        raise InputError(f"{what} not found", path=path)
    try:
        df = pd.read_csv(path, dtype=str, keep_default_na=False, encoding="utf-8-sig", skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise InputError(f"{what} is empty (no header line {','.join(columns)})", path=path) from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"cannot read the {what} as CSV: {exc}", path=path) from None
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise InputError(f"missing columns {missing} (the {what} needs {','.join(columns)})", path=path)
    if need_rows and df.empty:
        raise InputError(f"{what} has a header but no rows", path=path)

    def ref(r: int) -> dict:
        out = {"path": path, "line": r + 2}
        if key is not None and key in df.columns:
            out["marker"] = str(df[key].iloc[r])
        return out

    for col in numeric:
        text = df[col].str.strip()
        num = pd.to_numeric(text, errors="coerce").to_numpy(np.float64)
        blank = text.isin(["", "NA"]).to_numpy()
        empty = blank | text.str.lower().isin(["nan"]).to_numpy()
        bad = ~np.isfinite(num) & ~(empty & (col in allow_missing))
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            if blank[r]:
                raise InputError(f"missing {col} value", **ref(r))
            raise InputError(f"non-numeric or non-finite {col} value {df[col].iloc[r]!r}", **ref(r))
        df[col] = np.where(empty, np.nan, num)
    return df
