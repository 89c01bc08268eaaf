"""Arrays on disk, read (and written) by row range with file reads: a long take's per-frame arrays cost the rows
in use, not the take.

:class:`StoredArray` reads rows of an array stored in a file (an entry of an npz, :func:`lgi.io.npz.npz_member`);
:class:`ScratchArray` is one in an unnamed temporary file that the process writes and reads back (a shot's
per-frame state between its preparation and its blocks), gone when it is dropped or the process ends.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

import numpy as np


def _read_at(fd: int, buf: memoryview, offset: int) -> int:
    """Read into ``buf`` from ``offset`` of ``fd``; the bytes read (fewer at the file's end)."""
    got = 0
    while got < len(buf):
        k = os.preadv(fd, [buf[got:]], offset + got)
        if not k:
            break
        got += k
    return got


class StoredArray:
    """A read-only C-order array of plain data stored at ``offset`` in a file, read by row range with file reads.

    Not memory-mapped: every page a map has read stays the process's resident memory until the map is dropped,
    so one pass over a mapped 36,000-frame take would count the whole take (measured: a pass over a 2.9 GB
    ``meshes.npz`` map peaked at 2.9 GB resident). Reads here cost the rows asked for.

    Indexing by an integer, a slice or an integer array (rows), optionally followed by more indices, gives a new
    array; iteration reads blocks of rows; ``np.asarray`` reads it all.
    """

    #: Rows read at a time by iteration.
    BLOCK = 32

    def __init__(self, path: str | os.PathLike[str], offset: int, shape: tuple[int, ...], dtype: np.dtype) -> None:
        self.path = os.fspath(path)
        self.offset = int(offset)
        self.shape = tuple(int(n) for n in shape)
        self.dtype = np.dtype(dtype)
        #: An open file the rows are read from (None: the file at ``path``, opened for each read).
        self._fd: int | None = None

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64))

    @property
    def nbytes(self) -> int:
        return self.size * self.dtype.itemsize

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"StoredArray({self.path!r}, shape={self.shape}, dtype={self.dtype})"

    def rows(self, lo: int, hi: int) -> np.ndarray:
        """Rows lo:hi (clamped to the array) as a new array."""
        n = self.shape[0]
        lo, hi = max(0, min(lo, n)), max(0, min(hi, n))
        hi = max(hi, lo)
        out = np.empty((hi - lo, *self.shape[1:]), self.dtype)
        buf = memoryview(out.reshape(-1).view(np.uint8))
        start = self.offset + lo * self._row_bytes
        if self._fd is not None:
            got = _read_at(self._fd, buf, start)
        else:
            with open(self.path, "rb", buffering=0) as fp:
                got = _read_at(fp.fileno(), buf, start)
        if got < len(buf):
            from lgi.errors import InputError

            raise InputError(f"truncated: rows {lo}:{hi} of {self.shape} end past the file's end", path=self.path)
        return out

    @property
    def _row_bytes(self) -> int:
        return int(np.prod(self.shape[1:], dtype=np.int64)) * self.dtype.itemsize

    def _take(self, idx: np.ndarray) -> np.ndarray:
        n = self.shape[0]
        idx = np.where(idx < 0, idx + n, idx)
        if len(idx) and (idx.min() < 0 or idx.max() >= n):
            raise IndexError(f"row index out of range for {n} rows")
        out = np.empty((len(idx), *self.shape[1:]), self.dtype)
        # Runs of consecutive rows are read at once (a sorted selection is a few reads).
        starts = np.flatnonzero(np.r_[True, np.diff(idx) != 1]) if len(idx) else np.zeros(0, np.int64)
        for a, b in zip(starts, [*starts[1:], len(idx)], strict=True):
            out[a:b] = self.rows(int(idx[a]), int(idx[a]) + (b - a))
        return out

    def __getitem__(self, key):
        rest: tuple = ()
        if isinstance(key, tuple):
            key, rest = (key[0], key[1:]) if key else (slice(None), ())
        if isinstance(key, (int, np.integer)):
            i = int(key) + (self.shape[0] if key < 0 else 0)
            if not 0 <= i < self.shape[0]:
                raise IndexError(f"row {int(key)} out of range for {self.shape[0]} rows")
            out = self.rows(i, i + 1)[0]
        elif isinstance(key, slice):
            lo, hi, step = key.indices(self.shape[0])
            out = self.rows(lo, hi) if step == 1 else self._take(np.arange(lo, hi, step))
        else:
            idx = np.asarray(key)
            if idx.dtype == bool:
                if idx.shape != self.shape[:1]:
                    raise IndexError(f"boolean index of shape {idx.shape} for {self.shape[0]} rows")
                idx = np.flatnonzero(idx)
            elif not np.issubdtype(idx.dtype, np.integer):
                raise IndexError(f"rows are indexed by integers, slices or a mask, not {idx.dtype}")
            out = self._take(idx.reshape(-1)).reshape(*idx.shape, *self.shape[1:])
        if not rest:
            return out
        return out[rest] if isinstance(key, (int, np.integer)) else out[(slice(None), *rest)]

    def __iter__(self):
        for lo in range(0, self.shape[0], self.BLOCK):
            yield from self.rows(lo, lo + self.BLOCK)

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = self.rows(0, self.shape[0])
        return out if dtype is None else out.astype(dtype, copy=False)

    def astype(self, dtype) -> np.ndarray:
        """The whole array as ``dtype`` (read whole)."""
        return np.asarray(self).astype(dtype)


def rows_from(a, start: int):
    """Rows ``start:`` of ``a``, an array (a view) or a :class:`StoredArray` (one on the same file; nothing read)."""
    if not isinstance(a, StoredArray):
        return a[start:]
    start = min(max(int(start), 0), a.shape[0])
    tail = StoredArray(a.path, a.offset + start * a._row_bytes, (a.shape[0] - start, *a.shape[1:]), a.dtype)
    tail._fd = a._fd
    tail._owner = a  # a scratch file stays open while its tail is read
    return tail


@contextlib.contextmanager
def scratch_space(dir: str | os.PathLike[str] | None = None) -> Iterator[None]:
    """Writes to scratch files in ``dir`` (default the system's temporary folder): a full, over-quota or
    read-only folder becomes a :class:`lgi.errors.StorageError` naming it and how to point lgi elsewhere,
    instead of a bare "No space left on device" that names no folder."""
    try:
        yield
    except OSError as exc:
        from lgi.io.atomic import storage_error

        where = os.fspath(dir) if dir is not None else tempfile.gettempdir()
        full = storage_error(exc, where, done="; lgi keeps a long take's per-frame state in scratch files there "
                                              "(set TMPDIR to a folder with room)")
        if full is None:
            raise
        raise full from exc


class ScratchArray(StoredArray):
    """A (N, ...) array in an unnamed temporary file (in ``dir``, default the system's, ``TMPDIR``): written by
    row range (:meth:`write`), read as a :class:`StoredArray`. Its pages are the page cache's, not the process's
    resident memory, and the file has no name, so nothing is left behind however the process ends.
    """

    def __init__(self, shape: tuple[int, ...], dtype, dir: str | os.PathLike[str] | None = None) -> None:
        self._dir = dir
        with scratch_space(dir):
            self._file = tempfile.TemporaryFile(dir=dir)
        super().__init__("<scratch>", 0, shape, dtype)
        self._fd = self._file.fileno()
        # Sparse: the space is taken as rows are written, so a full folder shows in write().
        os.ftruncate(self._fd, self.nbytes)

    @classmethod
    def of(cls, array: np.ndarray, dir: str | os.PathLike[str] | None = None) -> ScratchArray:
        """A scratch copy of ``array`` (written a block of rows at a time)."""
        out = cls(np.shape(array), np.asarray(array[:0]).dtype, dir)
        step = max(1, (64 << 20) // max(out._row_bytes, 1))
        for lo in range(0, len(array), step):
            out.write(lo, array[lo:lo + step])
        return out

    def write(self, lo: int, rows: np.ndarray) -> None:
        """Write ``rows`` (n, ...) as rows lo:lo + n."""
        rows = np.ascontiguousarray(rows, self.dtype)
        if rows.shape[1:] != self.shape[1:] or lo < 0 or lo + len(rows) > self.shape[0]:
            raise ValueError(f"rows {rows.shape} at {lo} do not fit {self.shape}")
        buf = memoryview(rows.reshape(-1).view(np.uint8))
        offset = lo * self._row_bytes
        done = 0
        with scratch_space(self._dir):
            while done < len(buf):
                done += os.pwritev(self._fd, [buf[done:]], offset + done)

    def close(self) -> None:
        self._file.close()
