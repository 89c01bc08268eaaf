"""Writing large tables as CSV.

A reconstruction's diagnostics hold a row per bundle and frame (108,000 for 1000 frames of the ICT layout);
pandas' writer took 4.6 s for them, 5 ms of every frame's budget. pyarrow's C++ writer takes 0.4 s.
Floats are written at full precision (shortest round-trip form), missing values as empty fields, strings
quoted only where needed.
"""

from __future__ import annotations

import csv
import os

import numpy as np
import pandas as pd

from lgi.errors import InputError, cell_text


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


#: Bytes of a CSV read at a time by :func:`check_field_counts`.
FIELD_CHUNK = 1 << 22
#: The longest header line read.
HEADER_BYTES = 1 << 20
#: Bytes of a line kept for a message (it quotes 200 characters of it).
QUOTE_BYTES = 1024


def check_field_counts(path: str | os.PathLike[str], what: str) -> None:
    """Refuse, reading :data:`FIELD_CHUNK` bytes at a time, a CSV line with more fields than the header, before a parser
    makes a row of it (a line of two million fields took a parser 23 GB), naming the line and quoting the
    start of it.

    Parameters
    ----------
    path : a CSV file (commas between fields, double quotes around fields that hold commas or line ends)
    what : the table's name in messages ("bundles file")

    Raises
    ------
    InputError
        Naming the file and line.
    """

    with open(path, "rb") as fh:
        header = fh.readline(HEADER_BYTES)
        if len(header) == HEADER_BYTES and not header.endswith(b"\n"):
            raise InputError(f"the {what}'s header line is longer than {HEADER_BYTES:,} bytes", path=path, line=1)
        if not header.strip():
            return  # an empty file, or a blank first line: the reader says what is wrong
        fields = len(next(csv.reader([header.decode("utf-8-sig", errors="replace")]), [""]))
        # line: the file's line at the chunk's start; row_line: where the row read on into it began (a quoted
        # field may hold line ends, so rows and lines differ).
        line, row_line, pending, head, quotes = 2, 2, 0, b"", 0
        while True:
            data = fh.read(FIELD_CHUNK)
            if not data:
                break
            b = np.frombuffer(data, np.uint8)
            is_quote = b == 34
            lines = np.flatnonzero(b == 10)
            if quotes or is_quote.any():
                # Commas and line ends inside quotes are a field's text: an odd number of quotes before them.
                outside = (np.cumsum(is_quote, dtype=np.int32) + quotes) % 2 == 0
                quotes = int((quotes + is_quote.sum()) % 2)
                nl, cm = lines[outside[lines]], np.flatnonzero((b == 44) & outside)
            else:
                nl, cm = lines, np.flatnonzero(b == 44)
            ends = np.searchsorted(cm, nl)
            commas = np.diff(ends, prepend=0)
            if len(commas):
                commas[0] += pending
            bad = np.flatnonzero(commas + 1 > fields)
            if bad.size:
                i = int(bad[0])
                text = head + data[:nl[0]] if i == 0 else data[nl[i - 1] + 1:nl[i]]
                at = row_line if i == 0 else line + int(np.searchsorted(lines, nl[i - 1] + 1))
                raise InputError(f"{int(commas[i]) + 1:,} fields where the header has {fields}: "
                                 f"{cell_text(text.decode('utf-8', errors='replace'))}", path=path, line=at)
            if len(nl):
                row_line = line + int(np.searchsorted(lines, nl[-1] + 1))
                pending = len(cm) - int(ends[-1])
                head = data[nl[-1] + 1:][:QUOTE_BYTES]
            else:
                pending += len(cm)
                head = (head + data)[:QUOTE_BYTES]
            line += len(lines)
        if pending + 1 > fields:
            raise InputError(f"{pending + 1:,} fields where the header has {fields}: "
                             f"{cell_text(head.decode('utf-8', errors='replace'))}", path=path, line=row_line)


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
    if not os.path.isfile(path):
        raise InputError(f"{what} not found", path=path)
    check_field_counts(path, what)
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
            raise InputError(f"non-numeric or non-finite {col} value {cell_text(df[col].iloc[r])}", **ref(r))
        df[col] = np.where(empty, np.nan, num)
    return df
