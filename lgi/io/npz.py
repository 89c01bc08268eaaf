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

from lgi.errors import InputError
from lgi.io.stored import StoredArray

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
        #: Where the entry's rows start in the file (a stored entry's bytes are the array's own).
        self.rows_offset = self._zf.fp.tell()

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

    def flush(self) -> int:
        """Put the rows written so far on disk (flushed and synced); returns how many rows of the entry begun
        there are: they are at :attr:`rows_offset`, each ``prod(shape[1:])`` items, as a later run that goes on
        from them reads them (:class:`~lgi.io.stored.StoredArray`)."""
        fp = self._zf.fp
        fp.flush()
        os.fsync(fp.fileno())
        return self._rows

    def end(self) -> None:
        """Close the entry begun, which must have all its rows."""
        dest, name, _, shape, n = self._open
        if self._rows != n:
            raise ValueError(f"{self.path}: entry {name!r} has {self._rows} of its {n} rows")
        dest.close()
        self._open = None


def npz_member(path: str | os.PathLike[str], name: str) -> StoredArray | np.ndarray:
    """Entry ``name`` of a stored (uncompressed) npz, read by row range as it is used (a :class:`StoredArray`),
    so that a frame range of a long shot's meshes costs its own size. An :class:`~lgi.errors.InputError` names
    the file when it is not such an archive or has no such entry."""
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
    compressed by another tool is loaded whole. Errors as :func:`load_npz`, and for vertices that hold no frame."""
    try:
        with zipfile.ZipFile(path) as zf:
            infos = {i.filename: i for i in zf.infolist()}
    except (OSError, zipfile.BadZipFile, EOFError):
        return load_npz(path, required)  # its message names what is wrong
    entry = infos.get("vertices.npy")
    if entry is None or entry.compress_type != zipfile.ZIP_STORED:
        return _with_frames(load_npz(path, required), path)
    out = {}
    for name in infos:
        if name.endswith(".npy"):
            key = name[:-4]
            out[key] = npz_member(path, key) if key == "vertices" else np.array(npz_member(path, key))
    missing = [k for k in required if k not in out]
    if missing:
        from lgi.errors import InputError

        raise InputError(f"missing arrays {missing}", path=path)
    return _with_frames(out, path)


def _with_frames(out: dict[str, np.ndarray], path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """``out``, refused when its vertices hold no frame (a reader would have nothing to read)."""
    v = out.get("vertices")
    if v is not None and (len(v.shape) == 0 or v.shape[0] == 0):
        from lgi.errors import InputError

        raise InputError(f"holds no frames (vertices of shape {tuple(v.shape)})", path=path)
    return out


def load_npy(path: str | os.PathLike[str], mmap: bool = False) -> np.ndarray:
    """An ``.npy`` array (memory-mapped with ``mmap``, never unpickled), or an InputError naming the file."""
    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"not a readable array ({exc})", path=path) from None
