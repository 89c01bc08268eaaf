"""Structural checks of stored arrays: the compiled kernels index without bounds checks, so an index or a mesh
whose offsets or indices are out of range must be refused when it is loaded, not crash the process later."""

from __future__ import annotations

import os
from collections.abc import Mapping

import numpy as np

from lgi.errors import InputError


def _damaged(path: str | os.PathLike[str], what: str) -> InputError:
    return InputError(f"{what} (a damaged file: rebuild or re-import it)", path=path)


def check_kind(arrays: Mapping[str, np.ndarray], path: str | os.PathLike[str], ints: tuple[str, ...] = (),
               floats: tuple[str, ...] = ()) -> None:
    """Integer arrays hold integers, float arrays numbers (finite), for the names present in ``arrays``."""
    for name in ints:
        if name in arrays and arrays[name].dtype.kind not in "iu":
            raise _damaged(path, f"{name} holds {arrays[name].dtype} values, not integers")
    for name in floats:
        if name not in arrays:
            continue
        a = arrays[name]
        if a.dtype.kind not in "fiu":
            raise _damaged(path, f"{name} holds {a.dtype} values, not numbers")
        if not np.all(np.isfinite(a)):
            raise _damaged(path, f"{name} holds non-finite values")


def check_offsets(off: np.ndarray, n_items: int, name: str, path: str | os.PathLike[str],
                  n_groups: int | None = None) -> None:
    """CSR offsets: 1-D, starting at 0, non-decreasing, ending at ``n_items`` (``n_groups + 1`` long if given)."""
    off = np.asarray(off)
    if off.ndim != 1 or len(off) < 1 or (n_groups is not None and len(off) != n_groups + 1):
        raise _damaged(path, f"{name} has shape {off.shape}, expected ({'n' if n_groups is None else n_groups + 1},)")
    if off[0] != 0 or off[-1] != n_items or np.any(np.diff(off) < 0):
        raise _damaged(path, f"{name} is not a list of offsets from 0 to {n_items}")


def check_range(a: np.ndarray, lo: int, hi: int, name: str, path: str | os.PathLike[str],
                allow: int | None = None) -> None:
    """Every entry of ``a`` in ``lo <= a < hi`` (or equal to ``allow``, a placeholder such as -1)."""
    a = np.asarray(a)
    if a.size == 0:
        return
    ok = (a >= lo) & (a < hi)
    if allow is not None:
        ok |= a == allow
    if not ok.all():
        bad = a[~ok].ravel()[0]
        raise _damaged(path, f"{name} holds {int(bad)}, outside {lo}..{hi - 1}")


def check_grouped(a: np.ndarray, group_of_row: np.ndarray, bounds: np.ndarray, name: str,
                  path: str | os.PathLike[str], allow: int | None = None) -> None:
    """Rows of ``a`` belong to groups (``group_of_row``); a row's entries must lie in its group's range
    ``bounds[g] <= a < bounds[g + 1]`` (or equal ``allow``)."""
    a = np.asarray(a)
    if a.size == 0:
        return
    a2 = a.reshape(len(a), -1).astype(np.int64, copy=False)
    lo = bounds[group_of_row].astype(np.int64)
    width = (bounds[group_of_row + 1] - lo).astype(np.uint64)
    # One unsigned comparison per entry: below lo wraps around to a huge value.
    ok = (a2 - lo[:, None]).view(np.uint64) < width[:, None]
    if allow is not None:
        ok |= a2 == allow
    if not ok.all():
        r = int(np.flatnonzero(~ok.all(1))[0])
        raise _damaged(path, f"{name} row {r} points outside its own group")


def check_mesh(arrays: Mapping[str, np.ndarray], n_vertices: int, path: str | os.PathLike[str]) -> None:
    """A polygon mesh's topology: ``face_offsets`` over ``face_vertices`` (indices < ``n_vertices``), at least 3
    corners a face, and ``face_uvs`` (same length, indices into ``uvs``) when present."""
    check_kind(arrays, path, ints=("face_vertices", "face_offsets", "face_uvs"), floats=("uvs",))
    fv, fo = np.asarray(arrays["face_vertices"]), np.asarray(arrays["face_offsets"])
    if fv.ndim != 1:
        raise _damaged(path, f"face_vertices has shape {fv.shape}, expected one dimension")
    check_offsets(fo, len(fv), "face_offsets", path)
    if len(fo) > 1 and np.diff(fo).min() < 3:
        raise _damaged(path, "a face with fewer than 3 corners")
    check_range(fv, 0, n_vertices, "face_vertices", path)
    if "face_uvs" in arrays:
        fu = np.asarray(arrays["face_uvs"])
        if "uvs" not in arrays or fu.shape != fv.shape:
            raise _damaged(path, "face_uvs without uvs, or not one per face corner")
        check_range(fu, 0, len(arrays["uvs"]), "face_uvs", path)


def nonfinite_frames(vertices: np.ndarray, block: int = 64) -> np.ndarray:
    """Indices of the frames of ``vertices`` (F, V, 3) that hold a NaN or an infinity, checked ``block`` frames at
    a time, so that a long take read by frame range (:class:`lgi.io.npz.StoredArray`) is not read whole."""
    bad = [lo + np.flatnonzero(~np.isfinite(vertices[lo:lo + block]).all(axis=(1, 2)))
           for lo in range(0, len(vertices), block)]
    return np.concatenate(bad) if bad else np.zeros(0, np.int64)
