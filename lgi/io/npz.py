"""Deterministic ``.npz`` files: the same arrays always give the same bytes.

``numpy.savez`` stamps each zip entry with the current time, so two runs that compute identical arrays
write different files. Content-addressed caches and resumable flows need byte-identical outputs, so
every stored archive goes through :func:`save_npz` (entries in the given order, a fixed timestamp, no
compression; readable by ``numpy.load`` as usual).

A long shot's meshes do not fit in memory: :class:`NpzWriter` writes an entry block by block (the same bytes as
:func:`save_npz` of the whole array), and :func:`npz_member` opens an entry of a stored archive without reading
it (a :class:`StoredArray`), so that a reader takes a range of frames.
"""

from __future__ import annotations

import io
import os
import zipfile

import numpy as np

_EPOCH = (1980, 1, 1, 0, 0, 0)


def _entry(name: str) -> zipfile.ZipInfo:
    info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
    info.external_attr = 0o644 << 16
    return info


def save_npz(path: str | os.PathLike[str], **arrays: np.ndarray) -> None:
    """Write ``arrays`` to ``path`` as an uncompressed npz with fixed metadata (not atomic by itself)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            zf.writestr(_entry(name), buf.getvalue())


class NpzWriter:
    """An npz written entry by entry, a large entry block by block along its first axis: the file holds the
    bytes :func:`save_npz` writes for the same arrays, without the whole array in memory.

    Use as a context manager; :meth:`add` writes a whole array, :meth:`begin` / :meth:`write` / :meth:`end` one
    of known shape in blocks (entries one at a time, in order).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = path
        self._zf = zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True)
        self._open: tuple[object, str, np.dtype, tuple[int, ...], int] | None = None

    def __enter__(self) -> NpzWriter:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()

    def close(self) -> None:
        """Write the archive's directory; every entry must be ended."""
        if self._open is not None:
            raise ValueError(f"{self.path}: entry {self._open[1]!r} not ended")
        self._zf.close()

    def abort(self) -> None:
        """Close an archive left unfinished: an entry begun is cut short, so the file is no result (remove it)."""
        if self._open is not None:
            self._open[0].close()
            self._open = None
        self._zf.close()

    def add(self, name: str, array: np.ndarray) -> None:
        """Write a whole array as entry ``name``."""
        array = np.ascontiguousarray(array)
        self.begin(name, array.shape, array.dtype)
        self.write(array)
        self.end()

    def begin(self, name: str, shape: tuple[int, ...], dtype: np.dtype | str) -> None:
        """Start entry ``name`` of ``shape`` and ``dtype``; its rows (along the first axis) follow by
        :meth:`write`."""
        if self._open is not None:
            raise ValueError(f"{self.path}: entry {self._open[1]!r} not ended")
        dtype = np.dtype(dtype)
        if dtype.hasobject:
            raise ValueError("object arrays are not stored")
        head = io.BytesIO()
        # The header numpy.lib.format.write_array gives a C-ordered array: version 1.0 while it fits, else 2.0.
        fmt = np.lib.format
        d = {"descr": fmt.dtype_to_descr(dtype), "fortran_order": False, "shape": tuple(int(n) for n in shape)}
        try:
            fmt.write_array_header_1_0(head, d)
        except ValueError:
            head = io.BytesIO()
            fmt.write_array_header_2_0(head, d)
        info = _entry(name)
        rows = int(shape[0]) if len(shape) else 1
        info.file_size = len(head.getvalue()) + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        dest = self._zf.open(info, "w")
        dest.write(head.getvalue())
        self._open = (dest, name, dtype, tuple(shape), rows)
        self._rows = 0

    def write(self, rows: np.ndarray) -> None:
        """Append rows (along the first axis) to the entry begun."""
        if self._open is None:
            raise ValueError(f"{self.path}: no entry begun")
        dest, name, dtype, shape, n = self._open
        rows = np.ascontiguousarray(rows, dtype=dtype)
        if rows.shape[1:] != shape[1:] or self._rows + len(rows) > n:
            raise ValueError(f"{self.path}: rows of shape {rows.shape} do not fit entry {name!r} {shape} after "
                             f"{self._rows} rows")
        dest.write(memoryview(rows.reshape(-1)).cast("B"))
        self._rows += len(rows)

    def end(self) -> None:
        """Close the entry begun, which must have all its rows."""
        dest, name, _, shape, n = self._open
        if self._rows != n:
            raise ValueError(f"{self.path}: entry {name!r} has {self._rows} of its {n} rows")
        dest.close()
        self._open = None


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
        row = out[0].nbytes if hi > lo else 0
        buf = memoryview(out.reshape(-1).view(np.uint8))
        got = 0
        with open(self.path, "rb", buffering=0) as fp:
            fp.seek(self.offset + lo * row)
            while got < len(buf):
                k = fp.readinto(buf[got:])
                if not k:
                    from lgi.errors import InputError

                    raise InputError(f"truncated: rows {lo}:{hi} of {self.shape} end past the file's end",
                                     path=self.path)
                got += k
        return out

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


def npz_member(path: str | os.PathLike[str], name: str) -> StoredArray | np.ndarray:
    """Entry ``name`` of a stored (uncompressed) npz, read by row range as it is used (a :class:`StoredArray`),
    so that a frame range of a long shot's meshes costs its own size. An :class:`~lgi.errors.InputError` names
    the file when it is not such an archive or has no such entry."""
    from lgi.errors import InputError

    try:
        with zipfile.ZipFile(path) as zf:
            info = zf.getinfo(f"{name}.npy")
            if info.compress_type != zipfile.ZIP_STORED:
                raise InputError(f"entry {name!r} is compressed (not written by lgi)", path=path)
        with open(path, "rb") as fp:
            fp.seek(info.header_offset)
            local = fp.read(30)
            if local[:4] != b"PK\x03\x04":
                raise InputError(f"entry {name!r}: bad local header", path=path)
            fp.seek(info.header_offset + 30 + int.from_bytes(local[26:28], "little")
                    + int.from_bytes(local[28:30], "little"))
            version = np.lib.format.read_magic(fp)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran, dtype = read(fp)
            offset = fp.tell()
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except KeyError:
        raise InputError(f"no array {name!r}", path=path) from None
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"not a readable npz file ({exc})", path=path) from None
    if dtype.hasobject:
        raise InputError(f"holds an array that is not plain data ({name!r})", path=path)
    if dtype.isnative:  # "<f4" read from the header, as numpy's own float32 (which USD's buffers take)
        dtype = dtype.newbyteorder("=")
    size = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if size > info.file_size or offset + size > os.path.getsize(path):
        raise InputError(f"entry {name!r} is truncated", path=path)
    if size == 0:
        return np.zeros(shape, dtype)
    if fortran and len(shape) > 1:  # never written by lgi: its rows are not contiguous, so it is read whole
        return np.array(np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order="F"))
    return StoredArray(path, offset, shape, dtype)


def load_npz(path: str | os.PathLike[str], required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Every array of an npz (never unpickling), or an :class:`~lgi.errors.InputError` naming the file:
    unreadable, truncated, holding a pickled object, or missing one of ``required``."""
    from lgi.errors import InputError

    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except ValueError as exc:  # numpy refuses pickled members with a ValueError
        raise InputError(f"holds an array that is not plain data ({exc})", path=path) from None
    except (OSError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"not a readable npz file ({exc})", path=path) from None
    missing = [k for k in required if k not in out]
    if missing:
        raise InputError(f"missing arrays {missing}", path=path)
    return out



def load_meshes(path: str | os.PathLike[str], required: tuple[str, ...] = ("vertices",)) -> dict[str, np.ndarray]:
    """A reconstruction's ``meshes.npz`` for a reader that goes frame by frame: ``vertices`` read by frame range
    (:func:`npz_member`) when stored uncompressed, as lgi writes it, the other arrays loaded; an archive
    compressed by another tool is loaded whole. Errors as :func:`load_npz`."""
    try:
        with zipfile.ZipFile(path) as zf:
            infos = {i.filename: i for i in zf.infolist()}
    except (OSError, zipfile.BadZipFile, EOFError):
        return load_npz(path, required)  # its message names what is wrong
    entry = infos.get("vertices.npy")
    if entry is None or entry.compress_type != zipfile.ZIP_STORED:
        return load_npz(path, required)
    out = {}
    for name in infos:
        if name.endswith(".npy"):
            key = name[:-4]
            out[key] = npz_member(path, key) if key == "vertices" else np.array(npz_member(path, key))
    missing = [k for k in required if k not in out]
    if missing:
        from lgi.errors import InputError

        raise InputError(f"missing arrays {missing}", path=path)
    return out


def load_npy(path: str | os.PathLike[str], mmap: bool = False) -> np.ndarray:
    """An ``.npy`` array (memory-mapped with ``mmap``, never unpickled), or an InputError naming the file."""
    from lgi.errors import InputError

    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"not a readable array ({exc})", path=path) from None
