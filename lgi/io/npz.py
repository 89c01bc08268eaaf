"""Deterministic ``.npz`` files: the same arrays always give the same bytes.

``numpy.savez`` stamps each zip entry with the current time, so two runs that compute identical arrays
write different files. Content-addressed caches and resumable flows need byte-identical outputs, so
every stored archive goes through :func:`save_npz` (entries in the given order, a fixed timestamp, no
compression; readable by ``numpy.load`` as usual).
"""

from __future__ import annotations

import io
import os
import zipfile

import numpy as np

_EPOCH = (1980, 1, 1, 0, 0, 0)


def save_npz(path: str | os.PathLike[str], **arrays: np.ndarray) -> None:
    """Write ``arrays`` to ``path`` as an uncompressed npz with fixed metadata (not atomic by itself)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asanyarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())


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



def load_npy(path: str | os.PathLike[str], mmap: bool = False) -> np.ndarray:
    """An ``.npy`` array (memory-mapped with ``mmap``, never unpickled), or an InputError naming the file."""
    from lgi.errors import InputError

    try:
        return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"not a readable array ({exc})", path=path) from None
