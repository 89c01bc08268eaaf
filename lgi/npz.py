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
