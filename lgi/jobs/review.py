"""The review job: a reconstruction as a self-contained page to scrub through in 3D (``lgi review``).

:func:`review` reads a reconstruction's outputs (``meshes.npz``, ``diagnostics.csv``, ``per_frame.csv``) and the
index it was made with, and writes ``REVIEW_DIR``: ``index.html``, ``viewer.js`` (the WebGL viewer, lgi's own),
``review_meta.js`` (topology, markers and their status per frame, curves, summary), ``review_frames.js`` (the
quantisation, the colour maps' scales, the files' names), ``frames/overview.html`` (every Nth frame, loaded first,
for the whole shot at once) and ``frames/block_NNNNN.html``, the frames :data:`BLOCK` at a time with their colour
maps and diagnostics, which the page loads around the cursor (in a hidden frame that hands the block over) and
drops far from it. The page opens
from the file system with no server and no network, and a long take costs the browser (and this job) the blocks
in use, not the take.

The job reads the take twice a block at a time (``meshes.npz`` by frame range, ``diagnostics.csv`` by chunks of
rows): a first pass fixes what must be the shot's (the quantisation step, the colour bars' tops), the second
writes the blocks. Its memory does not grow with the take's length.

The command line, ``lgi demo``, ``lgi reconstruct --review`` and the flows all call :func:`review`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from lgi.dataset.mesh import triangulate
from lgi.errors import InputError, cell_text
from lgi.io.atomic import atomic_dir, check_not_in_store, check_output, reads, remove_recorded
from lgi.io.npz import load_meshes
from lgi.io.stored import ScratchArray
from lgi.review.pack import (
    NOT_MEASURED,
    PAGE_POLICY,
    TOP_WITH_GAPS,
    ColourTop,
    DisplacementRange,
    blob,
    codes_blob,
    json_blob,
    quantise_gaps,
    quantise_map,
    with_policy,
    write_block_page,
    write_script,
)
from lgi.units import MM_PER_CM

log = logging.getLogger(__name__)

#: The folder of the block files, in a review folder.
FRAMES_DIR = "frames"
#: What a review folder holds (anything else in an existing one makes the job refuse to replace it).
REVIEW_ENTRIES = ("index.html", "viewer.js", "review_meta.js", "review_frames.js", FRAMES_DIR)
#: Frames per block file: what the page loads when the cursor comes near it and drops far from it. A far jump waits
#: for the block's page to be framed and decoded, which grow with the block: on a 2-core machine a noisy take's
#: blocks of 16 ICT frames took about 0.105 s, over the 0.1 s a scrub must stay within (docs/review.md,
#: table:review-blocks). A 36,000-frame take is 4,500 files.
BLOCK = 8
#: Where a block page opened on its own puts its block (``window.LGI_REVIEW_BLOCKS[k]``; framed by the review page,
#: it hands the block over instead).
BLOCK_REGISTRY = "LGI_REVIEW_BLOCKS"
#: At most this many frames in the overview (every Nth frame of the shot, the page's rough mesh while a block
#: loads): about 40 kB each for ICT, so 10 MB however long the take.
OVERVIEW_FRAMES = 256
#: The overview's file, in :data:`FRAMES_DIR`.
OVERVIEW_FILE = "overview.html"
#: The overview's frames are at least this many frames apart (a short shot's overview stays small: its blocks
#: come at once anyway).
OVERVIEW_MIN_STRIDE = 16
#: Rows of diagnostics.csv parsed at a time (108 ICT markers: about 46 frames, some 6 MB of pandas objects with the
#: shape lists). With 20,000 rows a 36,000-frame ICT take peaked at 522 MiB against 449 at 1,000 frames: the more
#: chunks, the likelier one lands on a block's peak; with 5,000, 439 MiB in the same time.
DIAG_CHUNK_ROWS = 5_000
#: The status of a marker in a frame, in the order of the page's codes (the diagnostics' ``status`` values, and
#: ``ray`` where the ``constraint`` column says a viewing ray held the marker).
STATUSES = ("contained", "projected", "neighbour", "fitted", "missing", "bridged", "ray", "other")
#: The diagnostics columns the first pass reads (the status grid, the correction map, the curves, the warnings).
_FIRST_PASS_COLUMNS = ("frame", "marker", "status", "constraint", "residual_before_mm", "residual_mm", "fallback",
                       "jaw_open_deg")


@dataclass(frozen=True)
class ReviewOptions:
    """Options of the review job (the ``lgi review`` flags).

    Attributes
    ----------
    truth : str or None
        An npz with ``vertices`` (F, V, 3) cm, the true surfaces (``lgi synth``'s ``truth.npz``): adds the
        distance-to-truth colour map and the error curve.
    compare : str or None
        Another reconstruction of the same shot on the same mesh (e.g. ``--method blendshape``): adds the
        distance-between-them colour map.
    scans : str or None
        The folder ``lgi compare --out`` wrote for this reconstruction: adds the distance-to-the-scan colour map
        (mm) on the frames compared with a scan, and its RMS as points on the curves.
    rig_solve : str or None
        The folder ``lgi rig-solve`` wrote for this reconstruction: adds the distance from the rig's playback of
        its curves to the reconstruction (mm) as a colour map, and its RMS per frame as a curve.
    rig : str or None
        With ``rig_solve``: the rig dataset (default: the one its ``solve.json`` names).
    fps : float
        The shot's frame rate, frames per second: the page's playback rate at speed 1.
    step_um : float, um
        Quantisation step of the positions the page shows (within half of it; coarser only when the shot moves
        more than 32767 steps). The colour maps are computed from the exact meshes.
    """

    truth: str | None = None
    compare: str | None = None
    fps: float = 30.0
    scans: str | None = None
    step_um: float = 10.0
    rig_solve: str | None = None
    rig: str | None = None

    def __post_init__(self) -> None:
        if self.rig and not self.rig_solve:
            raise InputError("--rig goes with --rig-solve (the rig its curves drive)")
        if not isinstance(self.fps, (int, float)) or not math.isfinite(self.fps) or self.fps <= 0:
            raise InputError(f"--fps must be a positive number of frames per second, not {self.fps!r}")
        if not isinstance(self.step_um, (int, float)) or not 0 <= self.step_um <= 1000:
            raise InputError(f"--step must be a number of um in [0, 1000], not {self.step_um!r}")

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def _read_meshes(recon_dir: Path, what: str) -> dict[str, Any]:
    """A reconstruction's ``meshes.npz``: ``vertices`` (F, V, 3) float cm read by frame range (a
    :class:`~lgi.io.stored.StoredArray`; its values are checked block by block as they are read), ``frames`` (F,)."""
    path = recon_dir / "meshes.npz"
    if not recon_dir.is_dir():
        raise InputError(f"{what} is not a folder", path=recon_dir)
    if not path.is_file():
        raise InputError(f"no meshes.npz: {what} is not a reconstruction (lgi reconstruct writes meshes.npz, "
                         "diagnostics.csv and per_frame.csv)", path=path)
    m = load_meshes(path, required=("vertices", "frames"))
    v = m["vertices"]
    if v.ndim != 3 or v.shape[2] != 3 or v.dtype.kind != "f" or len(m["frames"]) != len(v):
        raise InputError(f"vertices {v.shape} / frames {m['frames'].shape} are not a shot's (F, V, 3) and (F,)",
                         path=path)
    return m


@dataclass
class _Rows:
    """A shot-sized array of meshes (the reconstruction's, the truth's, another reconstruction's) in the shot's
    frame order, read a block of frames at a time.

    Attributes
    ----------
    source : (F', V, 3) float array or StoredArray, cm
    index : (F,) int64 or None
        Per frame of the shot, its row in ``source``; None: the same rows.
    path : Path
        The file, for errors.
    finite : bool
        Refuse non-finite values (the meshes shown; a truth may be NaN where it has no value).
    frames : (F,) int64
        The shot's frame numbers, for errors.
    """

    source: Any
    index: np.ndarray | None
    path: Path
    finite: bool
    frames: np.ndarray

    def rows(self, lo: int, hi: int) -> np.ndarray:
        """(hi - lo, V, 3) float32 cm: frames lo:hi of the shot."""
        v = self.source[lo:hi] if self.index is None else self.source[self.index[lo:hi]]
        v = np.asarray(v, np.float32)
        if self.finite:
            bad = np.flatnonzero(~np.isfinite(v).all(axis=(1, 2)))
            if bad.size:
                raise InputError("vertices hold non-finite values", path=self.path, frame=int(self.frames[lo + bad[0]]))
        return v


def _aligned(other: Any, other_frames: np.ndarray | None, frames: np.ndarray, path: Path, n_v: int,
             what: str) -> _Rows:
    """``other`` (F', V, 3) on the shot's frames, by frame number when it has them, else by position (nothing
    read: the rows are read per block)."""
    if other.ndim != 3 or other.shape[1:] != (n_v, 3):
        raise InputError(f"{what} has vertices of shape {other.shape}; the reconstruction has (F, {n_v}, 3) "
                         "(another mesh topology?)", path=path)
    if other_frames is None:
        if len(other) < len(frames):
            raise InputError(f"{what} has {len(other)} frames, the reconstruction {len(frames)}", path=path)
        return _Rows(other, None, path, False, frames)
    other_frames = np.asarray(other_frames, np.int64)
    if len(other_frames) == len(frames) and np.array_equal(other_frames, frames):
        return _Rows(other, None, path, False, frames)
    pos = pd.Series(np.arange(len(other_frames)), index=other_frames)
    pos = pos[~pos.index.duplicated()]  # the first row of a frame stored twice, as a dict of them gave
    idx = pd.Series(frames).map(pos)
    if idx.isna().any():
        absent = frames[idx.isna().to_numpy()]
        raise InputError(f"{what} lacks {len(absent)} of the reconstruction's frames", path=path,
                         frame=int(absent[0]))
    return _Rows(other, idx.to_numpy(np.int64), path, False, frames)


def _rows(d: pd.DataFrame, fpos: pd.Series, mpos: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """Per diagnostics row, its frame's position in the shot and its marker's in the index (-1 where unknown).
    ``fpos``: position by frame number; ``mpos``: position by marker name."""
    fi = pd.to_numeric(d["frame"], errors="coerce").map(fpos).fillna(-1).to_numpy(np.int64)
    mi = d["marker"].astype(str).map(mpos).fillna(-1).to_numpy(np.int64)
    return fi, mi


def _numbers(d: pd.DataFrame, col: str) -> np.ndarray:
    """A diagnostics column as float64 (NaN where absent or not a number)."""
    if col not in d:
        return np.full(len(d), np.nan)
    return pd.to_numeric(d[col], errors="coerce").to_numpy(np.float64)


class _Diagnostics:
    """A reconstruction's ``diagnostics.csv`` read in chunks of :data:`DIAG_CHUNK_ROWS` rows, never whole.

    The constructor is the first pass (the columns of :data:`_FIRST_PASS_COLUMNS` only): it checks the file, keeps
    the shot's (F, M) status codes (a byte per frame and marker) and correction residuals (in a scratch file), per
    frame what the curves and warnings need, and the last chunk holding rows of each block of frames.
    :meth:`blocks` is the second pass: every column, the rows of one block at a time, in block order. lgi writes
    the rows in frame order, so a block waits for one or two chunks; rows in another order still come out right,
    held until their block is complete.

    Parameters
    ----------
    path : Path
    frames : (F,) int64
        The shot's frame numbers (meshes.npz's): rows of other frames, or a frame without rows, are refused (the
        two files of different runs).
    markers : list of M str
        The index's markers (a row of another marker is refused).
    block : int
        Frames per block.
    """

    def __init__(self, path: Path, frames: np.ndarray, markers: list[str], block: int) -> None:
        if not path.is_file():
            raise InputError("no diagnostics.csv: not a reconstruction's folder (lgi reconstruct writes it)",
                             path=path)
        self.path, self.frames, self.markers, self.block = path, frames, markers, block
        self.columns = list(next(self._chunks(nrows=0)).columns)
        missing = [c for c in ("frame", "marker", "status") if c not in self.columns]
        if missing:
            raise InputError(f"lacks the columns {missing}", path=path)
        n_f, n_m = len(frames), len(markers)
        self._fpos = pd.Series(np.arange(n_f), index=np.asarray(frames, np.int64))
        self._mpos = pd.Series(np.arange(n_m), index=markers)
        #: (F, M) uint8: each marker's status code (:data:`STATUSES`) per frame; "missing" without a row.
        self.status = np.full((n_f, n_m), STATUSES.index("missing"), np.uint8)
        #: (F, M) float32 mm: how far the correction took each bundle (residual before - after, >= 0; 0 unknown),
        #: in a scratch file (read a block at a time, 15 MB at 36,000 ICT frames).
        self.correction = ScratchArray((n_f, n_m), np.float32)
        #: Rows per raw status value (the summary's shares).
        self.status_counts: Counter[str] = Counter()
        self.fallbacks, self.first_fallback = 0, ""
        self._rows_per_frame = np.zeros(n_f, np.int64)
        self._counts = {k: np.zeros(n_f, np.int64) for k in ("contained", "projected", "missing")}
        self._worst = {k: np.full(n_f, -np.inf) for k in ("residual_before_mm", "residual_mm")}
        self._jaw = np.full(n_f, np.nan)
        self.has_jaw = "jaw_open_deg" in self.columns
        n_blocks = -(-n_f // block)
        self._last_chunk = np.full(n_blocks, -1, np.int64)
        codes = {s: i for i, s in enumerate(STATUSES)}
        usecols = [c for c in _FIRST_PASS_COLUMNS if c in self.columns]
        for i, d in enumerate(self._chunks(usecols=usecols)):
            unknown = sorted(set(d["marker"].astype(str).unique()) - set(markers))
            if unknown:
                raise InputError(f"names markers the index does not have ({unknown[:3]})", path=path)
            st = d["status"].astype(str).to_numpy()
            self.status_counts.update(pd.Series(st).value_counts().to_dict())
            if "fallback" in d:
                fb = d["fallback"].astype(object).where(d["fallback"].notna(), "").astype(str)
                hit = fb != ""
                if hit.any():
                    self.first_fallback = self.first_fallback or str(fb[hit].iloc[0])
                    self.fallbacks += int(hit.sum())
            fi, mi = _rows(d, self._fpos, self._mpos)
            if (fi < 0).any():
                # Rows of frames meshes.npz lacks: the two files are of different runs (or one was cut short).
                bad = d["frame"].iloc[int(np.flatnonzero(fi < 0)[0])]
                raise InputError(f"has rows of frame {cell_text(bad)}, which meshes.npz does not have: the two files "
                                 "are not of the same reconstruction (run it again)", path=path)
            ok = (fi >= 0) & (mi >= 0)
            if "constraint" in d:
                st = np.where(d["constraint"].astype(str).to_numpy() == "ray", "ray", st)
            code = pd.Series(st).map(codes).fillna(len(STATUSES) - 1).to_numpy(np.uint8)
            f, m = fi[ok], mi[ok]
            self.status[f, m] = code[ok]
            before, after = _numbers(d, "residual_before_mm"), _numbers(d, "residual_mm")
            if f.size:
                # The chunk's frames, read, updated and written back (a span of about 185 frames in lgi's order).
                lo, hi = int(f.min()), int(f.max()) + 1
                span = self.correction.rows(lo, hi)
                span[f - lo, m] = np.clip(np.nan_to_num(before - after), 0.0, None)[ok]
                self.correction.write(lo, span)
            for key, v in (("residual_before_mm", before), ("residual_mm", after)):
                good = ok & np.isfinite(v)
                np.maximum.at(self._worst[key], fi[good], v[good])
            raw = d["status"].astype(str).to_numpy()[ok]
            np.add.at(self._rows_per_frame, f, 1)
            np.add.at(self._counts["contained"], f, raw == "contained")
            np.add.at(self._counts["projected"], f, raw == "projected")
            np.add.at(self._counts["missing"], f, np.isin(raw, ["missing", "bridged"]))
            if self.has_jaw:
                np.fmax.at(self._jaw, f, _numbers(d, "jaw_open_deg")[ok])
            self._last_chunk[np.unique(f // block)] = i
        if not self.status_counts:
            raise InputError("holds no rows (a header alone): not the diagnostics of this reconstruction's frames",
                             path=path)
        lacking = np.flatnonzero(self._rows_per_frame == 0)
        if lacking.size:
            raise InputError(f"has no rows of frame {int(frames[lacking[0]])} of meshes.npz ({lacking.size} frames "
                             "without any): the two files are not of the same reconstruction (run it again)",
                             path=path)

    def _chunks(self, usecols: list[str] | None = None, nrows: int | None = None) -> Iterator[pd.DataFrame]:
        """The file's rows, :data:`DIAG_CHUNK_ROWS` at a time (the same chunks on every pass)."""
        try:
            if nrows is not None:
                yield pd.read_csv(self.path, nrows=nrows, keep_default_na=False, na_values=[""])
                return
            with pd.read_csv(self.path, keep_default_na=False, na_values=[""], usecols=usecols,
                             chunksize=DIAG_CHUNK_ROWS) as reader:
                yield from reader
        except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError, ValueError) as exc:
            raise InputError(f"not a readable CSV ({exc})", path=self.path) from None

    def blocks(self) -> Iterator[tuple[int, pd.DataFrame]]:
        """Block by block in order: (block, its rows with every column, in file order)."""
        pending: dict[int, list[pd.DataFrame]] = {}
        empty = pd.DataFrame({c: pd.Series(dtype=object) for c in self.columns})
        nxt, n_blocks = 0, len(self._last_chunk)

        def complete(upto: float) -> Iterator[tuple[int, pd.DataFrame]]:
            nonlocal nxt
            while nxt < n_blocks and self._last_chunk[nxt] <= upto:
                parts = pending.pop(nxt, [])
                yield nxt, pd.concat(parts, ignore_index=True) if parts else empty
                nxt += 1

        yield from complete(-1)
        for i, d in enumerate(self._chunks()):
            fi, mi = _rows(d, self._fpos, self._mpos)
            b = np.where((fi >= 0) & (mi >= 0), fi // self.block, -1)
            for k in np.unique(b[b >= 0]):
                pending.setdefault(int(k), []).append(d[b == k])
            yield from complete(i)
        yield from complete(math.inf)

    def block_payload(self, rows: pd.DataFrame, lo: int, n: int) -> dict[str, Any]:
        """A block's diagnostics for the page: which (frame, marker) has a row (``present``, (n, M) uint8) and
        every other column in (frame, marker) order as blobs (:func:`_diag_columns`)."""
        n_m = len(self.markers)
        slot = np.full((n, n_m), -1, np.int64)
        if len(rows):
            fi, mi = _rows(rows, self._fpos, self._mpos)
            slot[fi - lo, mi] = np.arange(len(rows))  # a (frame, marker) given twice: its last row
        order = slot.ravel()
        present = order >= 0
        cols = _diag_columns(rows, np.where(present, order, 0)) if len(rows) else []
        return {"present": blob(present.astype(np.uint8)), "diagnostics": cols}

    def per_frame(self) -> pd.DataFrame:
        """What ``per_frame.csv`` holds, for a reconstruction without it (frames of the shot with rows)."""
        n = self._rows_per_frame
        has = n > 0
        worst = {k: np.where(np.isfinite(v), v, np.nan)[has] for k, v in self._worst.items()}
        return pd.DataFrame({"frame": self.frames[has], "contained": self._counts["contained"][has] / n[has],
                             "projected": self._counts["projected"][has], "missing": self._counts["missing"][has],
                             **worst})

    def jaw(self) -> np.ndarray | None:
        """(F,) float deg: per frame the largest ``jaw_open_deg`` of its rows (NaN without), or None without the
        column."""
        return self._jaw if self.has_jaw else None


def _diag_columns(d: pd.DataFrame, order: np.ndarray) -> list[dict[str, Any]]:
    """The diagnostics' columns in (frame, marker) order as page blobs: numbers as float32, text as codes into
    its distinct values (a gzip-compressed JSON list: a block's shape lists repeat, and pack many times)."""
    cols = []
    for name in d.columns:
        if name in ("frame", "marker"):
            continue
        s = d[name].iloc[order]
        if pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s):
            cols.append({"name": name, "kind": "number", "data": blob(s.to_numpy(np.float32))})
        else:
            cats, codes = np.unique(s.fillna("").astype(str).to_numpy(), return_inverse=True)
            kind = np.uint8 if len(cats) <= 255 else np.uint16 if len(cats) <= 65535 else np.int32
            cols.append({"name": name, "kind": "text", "values": json_blob(cats.tolist()),
                         "data": blob(codes.astype(kind))})
    return cols


@dataclass
class _Map:
    """A colour map of the page on every frame, computed a block of frames at a time: seen whole in the first pass
    (its bar's top, :class:`~lgi.review.pack.ColourTop`), coded per block in the second.

    Attributes
    ----------
    key, label, note : str
    values : callable
        ``values(lo, vertices)``: (B, V) float mm for frames ``lo .. lo + B`` of the shot, given their meshes
        ``vertices`` (B, V, 3) cm.
    region : (V,) bool or None
        The vertices that have a value (the others are coded "not measured"); None: all.
    gaps : list of dict or None
        The page's legend of the codes above the ramp.
    top : ColourTop
        The values seen in the first pass: the bar's top (:attr:`vmax`, mm) and the largest value.
    """

    key: str
    label: str
    note: str
    values: Callable[[int, np.ndarray], np.ndarray]
    region: np.ndarray | None = None
    gaps: list[dict[str, Any]] | None = None
    top: ColourTop = field(default_factory=ColourTop)
    _vmax: float | None = None

    def observe(self, values: np.ndarray) -> None:
        """First pass: take in a block's values (B, V) mm."""
        self.top.add(values if self.region is None else values[:, self.region])

    @property
    def vmax(self) -> float:
        """The colour bar's top, mm (fixed after the first pass)."""
        if self._vmax is None:
            self._vmax = self.top.top()
        return self._vmax

    def codes(self, values: np.ndarray) -> np.ndarray:
        """(B, V) uint8: the page's codes of a block's values."""
        if self.region is None:
            return quantise_map(values, self.vmax)
        measured = np.broadcast_to(self.region, values.shape)
        return quantise_gaps(np.nan_to_num(values, nan=0.0), measured, measured, self.vmax)

    def entry(self) -> dict[str, Any]:
        """The map's entry in the page's header (its blocks' codes go in the block files)."""
        e = {"key": self.key, "label": self.label, "note": self.note, "vmax_mm": self.vmax,
             "max_mm": self.top.largest}
        if self.region is not None:
            e.update(top=TOP_WITH_GAPS, gaps=self.gaps or [])
        return e


def _distance_mm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(B, V) float32 mm between two blocks of meshes (B, V, 3) cm."""
    return np.linalg.norm(a.astype(np.float32) - b.astype(np.float32), axis=2) * MM_PER_CM


def _correction_map(diag: _Diagnostics, arrays: dict[str, np.ndarray],
                    n_markers: int) -> Callable[[int, np.ndarray], np.ndarray]:
    """``values(lo, vertices)`` of the correction map: per frame and vertex an upper bound of the size of the
    correction that took the surface through the bundles (mm).

    The reconstruction stores, per frame and bundle, the distance to the bundle before and after the correction,
    not the correction's vectors; the correction is the index's field of each bundle (1 at it, 0 at the others)
    times the bundle's residual vector. By the triangle inequality its size at a vertex is at most
    sum over bundles of |field(v)| x (before - after), which this gives (exact where one bundle dominates, as near
    each bundle)."""
    import scipy.sparse as sp

    n_v = arrays["neutral"].shape[0]
    if "corr_indptr" not in arrays:
        return lambda lo, v: np.zeros((len(v), n_v), np.float32)
    c = sp.csr_matrix((np.abs(arrays["corr_data"]), arrays["corr_indices"], arrays["corr_indptr"]),
                      shape=(n_markers, n_v))
    ct = c.T.tocsr()

    def values(lo: int, v: np.ndarray) -> np.ndarray:
        r = diag.correction.rows(lo, lo + len(v)).astype(np.float64)
        return np.asarray((ct @ r.T).T, np.float32)

    return values


def _overview_frames(n_f: int) -> np.ndarray:
    """Positions in the shot of the overview's frames: every Nth, at most :data:`OVERVIEW_FRAMES`."""
    stride = max(OVERVIEW_MIN_STRIDE, -(-n_f // OVERVIEW_FRAMES))
    return np.arange(0, n_f, stride)


def _curve(key: str, label: str, unit: str, values: np.ndarray, **extra: Any) -> dict[str, Any]:
    """A per-frame curve for the page: (F,) values as a float32 blob (NaN where the frame has none), 4 bytes a
    frame however long the take (a JSON list of 36,000 numbers was 0.7 MB a curve)."""
    return {"key": key, "label": label, "unit": unit, "values": blob(np.asarray(values, np.float32)), **extra}


def _per_frame_table(recon: Path, diag: _Diagnostics) -> pd.DataFrame:
    """The reconstruction's ``per_frame.csv``, or the same table from its diagnostics when it has none."""
    per_frame_path = recon / "per_frame.csv"
    if per_frame_path.is_file():
        try:
            per_frame = pd.read_csv(per_frame_path)
        except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
            raise InputError(f"not a readable CSV ({exc})", path=per_frame_path) from None
    else:
        per_frame = diag.per_frame()
    return per_frame


def _maps(o: ReviewOptions, recon: Path, meshes, frames: np.ndarray, n_v: int, diag: _Diagnostics,
          a, n_markers: int) -> tuple[list[_Map], Any, Any]:
    """The page's colour maps (against the truth, the correction, against ``--compare``, the rig's playback),
    the scans' distances and the rig's map, from the options' files."""
    maps: list[_Map] = []
    if o.truth:
        from lgi.io.npz import load_meshes

        t = Path(o.truth)
        tz = load_meshes(t, required=("vertices",))
        truth = _aligned(tz["vertices"], tz.get("frames"), frames, t, n_v, "the truth")
        maps.append(_Map("truth", "distance to the truth", f"against {t.name}",
                         lambda lo, v: _distance_mm(v, truth.rows(lo, lo + len(v)))))
    maps.append(_Map("correction", "correction size (bound)",
                     "sum over bundles of |correction field| x (residual before - after)",
                     _correction_map(diag, a, n_markers)))
    if o.compare:
        c = Path(o.compare)
        cm = _read_meshes(c, "--compare")
        compare = _aligned(cm["vertices"], cm["frames"], frames, c / "meshes.npz", n_v,
                           "--compare's reconstruction")
        compare.finite = True
        maps.append(_Map("compare", "distance from --compare", str(c),
                         lambda lo, v: _distance_mm(v, compare.rows(lo, lo + len(v)))))
    scans = None
    if o.scans:
        from lgi.review.scans import read_scan_map

        scans = read_scan_map(o.scans, frames, meshes["vertices"])
    rigmap = None
    if o.rig_solve:
        from lgi.review.rigmap import read_rig_map

        rigmap = read_rig_map(o.rig_solve, o.rig, frames, n_v)
        maps.append(_Map("rig", "rig playback - reconstruction",
                         f"the rig {rigmap.rig} played with lgi rig-solve's curves ({o.rig_solve})",
                         rigmap.distance, region=rigmap.region,
                         gaps=[{"code": NOT_MEASURED, "label": "outside the rig's face region"}]))
    return maps, scans, rigmap


def _first_pass(verts: _Rows, maps: list[_Map], neutral: np.ndarray, n_f: int, block: int):
    """What must be the shot's, not a block's: the displacements' range (the quantisation) and each map's top (the
    colour bars'); and the curves that need the meshes (RMS and largest distance to the truth, the rig's RMS)."""
    span = DisplacementRange(neutral)
    error_rms, error_max, rig_rms = (np.full(n_f, np.nan) for _ in range(3))
    for lo in range(0, n_f, block):
        v = verts.rows(lo, lo + block)
        span.add(v)
        for m in maps:
            d = m.values(lo, v)
            m.observe(d)
            if m.key == "truth":
                error_rms[lo:lo + len(v)] = np.sqrt(np.mean(d**2, axis=1))
                error_max[lo:lo + len(v)] = d.max(axis=1)
            elif m.key == "rig" and m.region.any():
                rig_rms[lo:lo + len(v)] = np.sqrt(np.nanmean(d[:, m.region].astype(np.float64) ** 2, axis=1))
    return span, error_rms, error_max, rig_rms


def _curves(o: ReviewOptions, meshes, diag: _Diagnostics, per_frame: pd.DataFrame, frames: np.ndarray,
            n_markers: int, errors: tuple[np.ndarray, np.ndarray, np.ndarray], scans, rigmap) -> list[dict]:
    """The page's per-frame curves; ``errors``: the first pass's RMS and largest distance to the truth and the
    rig's RMS, (F,) each."""
    error_rms, error_max, rig_rms = errors
    n_f = len(frames)
    curves = []
    pf = per_frame.set_index("frame").reindex(frames) if "frame" in per_frame else per_frame
    jaw = meshes.get("jaw")
    if jaw is not None and jaw.ndim == 2 and len(jaw) == n_f:
        curves.append(_curve("jaw", "jaw opening", "deg", jaw[:, 0]))
    elif diag.jaw() is not None:
        curves.append(_curve("jaw", "jaw opening", "deg", diag.jaw()))
    for col, label in (("residual_before_mm", "largest bundle residual before correction"),
                       ("residual_mm", "largest bundle residual after correction")):
        if col in pf:
            curves.append(_curve(col, label, "mm", pf[col].astype(float)))
    n_m = max(n_markers, 1)
    if "projected" in pf and "missing" in pf:
        share = (pf["projected"].astype(float) + pf["missing"].astype(float)) / n_m * 100
        curves.append(_curve("unsure", "bundles missing or projected", "%", share))
    if o.truth:
        curves.append(_curve("error_rms", "error against the truth, RMS", "mm", error_rms))
        curves.append(_curve("error_max", "error against the truth, max", "mm", error_max))
    if scans is not None:
        # Points, not a line: the frames with a scan are usually a few, far apart.
        curves.append(_curve("scan_rms", "distance to the scan, RMS of the covered vertices", "mm", scans.rms_mm,
                             points=True, missing="no scan at this frame"))
    if rigmap is not None:
        curves.append(_curve("rig_rms", "rig playback - reconstruction, RMS over the face region", "mm", rig_rms))
    return curves


@reads("recon_dir")
def review(recon_dir: str | Path, index_dir: str | Path, out: str | Path, options: ReviewOptions | None = None,
           summary: dict[str, Any] | None = None, warnings: list[str] | None = None) -> dict[str, Any]:
    """Write the review page of a reconstruction into ``out``; returns what it wrote (paths, sizes, maps).

    Parameters
    ----------
    recon_dir : path
        A reconstruction (``meshes.npz`` with ``vertices`` (F, V, 3) float32 cm and ``frames`` (F,);
        ``diagnostics.csv``; ``per_frame.csv``, recomputed from the diagnostics when absent).
    index_dir : path
        The index it was reconstructed with (mesh topology, marker layout, neutral, correction fields).
    out : path
        The review folder (replaced as a whole; refused if it holds files lgi does not write there).
    options : ReviewOptions
    summary : dict, optional
        The reconstruct job's summary (:func:`lgi.jobs.reconstruct.summarise`), shown on the page; without it
        the page shows what the diagnostics say.
    warnings : list of str, optional
        Warnings of the run to show.

    Bad input raises :class:`~lgi.errors.InputError` naming the file, before anything is written. The meshes
    (and the truth's, ``--compare``'s) are read :data:`BLOCK` frames at a time, twice; the diagnostics
    :data:`DIAG_CHUNK_ROWS` rows at a time, twice.
    """
    from lgi.index.build import LGIIndex

    o = options or ReviewOptions()
    t0 = time.perf_counter()
    block = int(BLOCK)
    recon = Path(recon_dir)
    inputs = [recon, index_dir] + [p for p in (o.truth, o.compare, o.scans, o.rig_solve, o.rig) if p]
    check_output(out, "dir", owned=REVIEW_ENTRIES, what="lgi review folder", inputs=inputs)
    check_not_in_store(out)
    out = Path(out)
    meshes = _read_meshes(recon, "RECON_DIR")
    if summary is None:
        summary = _run_record(recon)
    index = LGIIndex.load(index_dir)
    a = index.arrays
    frames = np.asarray(meshes["frames"], np.int64)
    verts = _Rows(meshes["vertices"], None, recon / "meshes.npz", True, frames)
    n_f, n_v = meshes["vertices"].shape[:2]
    if n_v != index.n_vertices:
        raise InputError(f"meshes.npz has {n_v} vertices, the index {index.n_vertices}: not reconstructed with "
                         f"this index ({index_dir})", path=recon / "meshes.npz")
    markers = index.marker_names
    diag = _Diagnostics(recon / "diagnostics.csv", frames, markers, block)
    per_frame = _per_frame_table(recon, diag)
    maps, scans, rigmap = _maps(o, recon, meshes, frames, n_v, diag, a, len(markers))
    span, error_rms, error_max, rig_rms = _first_pass(verts, maps, a["neutral"], n_f, block)
    layout = span.layout(o.step_um * 1e-4)
    curves = _curves(o, meshes, diag, per_frame, frames, len(markers), (error_rms, error_max, rig_rms), scans,
                     rigmap)
    info = _summary(recon, index_dir, index, diag.status_counts, summary, o, n_f, n_v)
    warn = list(warnings or []) + _warnings(diag, per_frame, len(markers), summary)
    if scans is not None:
        from lgi.review.scans import summary_rows

        info += summary_rows(scans, o.scans)
        warn += scans.warnings
    if rigmap is not None:
        from lgi.review import rigmap as rm

        info += rm.summary_rows(rigmap, o.rig_solve)

    tris = triangulate(a["face_vertices"], a["face_offsets"])[0].astype(np.int32)
    meta = {
        "format": "lgi-review", "version": 2, "fps": o.fps,
        "title": f"{recon.resolve().name}: {n_f} frames x {n_v} vertices",
        "frames": frames.tolist(), "n_vertices": n_v, "markers": markers, "statuses": list(STATUSES),
        "triangles": blob(tris.ravel()), "marker_vertices": blob(a["marker_vertices"].astype(np.int32).ravel()),
        "marker_weights": blob(a["marker_weights"].astype(np.float32).ravel()),
        # Every frame's marker statuses (a byte each): the markers' colours never wait for a block.
        "status": blob(diag.status.ravel()),
        "curves": curves, "summary": info, "warnings": warn,
        # Frames marked on the curves (positions in the shot): those compared with a scan.
        "marks": [{"label": "scan", "frames": np.flatnonzero(scans.slots >= 0).tolist()}] if scans is not None
        else [],
        "quantisation": {"scale_cm": layout.scale, "error_bound_mm": layout.error_bound_cm * MM_PER_CM,
                         "moving_vertices": int(len(layout.moving))},
    }

    # ---- second pass: the blocks, and the overview's frames as they go by (into scratch files: the overview of a
    # long take is 256 frames, 32 MB of ICT codes)
    overview = _overview_frames(n_f)
    ov_codes = ScratchArray((len(overview), len(layout.moving), 3), np.int16)
    ov_maps = {m.key: ScratchArray((len(overview), n_v), np.uint8) for m in maps}
    files: list[str] = []
    static = resources.files("lgi.review") / "static"
    with atomic_dir(out, REVIEW_ENTRIES, "lgi review folder") as tmp:
        (tmp / "index.html").write_text(with_policy((static / "index.html").read_text("utf-8"), PAGE_POLICY), "utf-8")
        (tmp / "viewer.js").write_bytes((static / "viewer.js").read_bytes())
        (tmp / FRAMES_DIR).mkdir()
        block_bytes = 0
        for b, rows in diag.blocks():
            lo = b * block
            v = verts.rows(lo, lo + block)
            codes = layout.codes(v)
            coded = {m.key: m.codes(m.values(lo, v)) for m in maps}
            payload = {"block": b, "lo": lo, "n": len(v), "codes": codes_blob(codes),
                       "maps": {k: blob(c) for k, c in coded.items()}, **diag.block_payload(rows, lo, len(v))}
            name = f"{FRAMES_DIR}/block_{b:05d}.html"
            block_bytes += write_block_page(tmp / name, payload, BLOCK_REGISTRY)
            files.append(name)
            at = np.flatnonzero((overview >= lo) & (overview < lo + len(v)))
            if at.size:  # the overview's frames are in order: this block's are consecutive rows
                ov_codes.write(int(at[0]), codes[overview[at] - lo])
                for k, c in coded.items():
                    ov_maps[k].write(int(at[0]), c[overview[at] - lo])
        page_maps = [m.entry() for m in maps]
        if scans is not None:
            from lgi.review.scans import page_map

            page_maps.insert(len(page_maps) - (rigmap is not None), page_map(scans, o.scans))
        # The overview is framed as the blocks are (a script's source would stay in the browser's memory: 16 MB
        # at 36,000 ICT frames).
        block_bytes += write_block_page(tmp / FRAMES_DIR / OVERVIEW_FILE, {
            "block": "overview", "frames": overview.tolist(), "codes": codes_blob(ov_codes),
            "maps": {k: blob(np.asarray(c)) for k, c in ov_maps.items()}}, BLOCK_REGISTRY)
        frames_payload = {
            "format": "lgi-review-frames", "version": 2, "n_frames": n_f, "rest": blob(layout.rest.ravel()),
            "moving": blob(layout.moving), "scale": layout.scale, "block": block, "files": files,
            "overview": f"{FRAMES_DIR}/{OVERVIEW_FILE}", "maps": page_maps}
        sizes = {"review_meta.js": write_script(tmp / "review_meta.js", "LGI_REVIEW_META", meta),
                 "review_frames.js": write_script(tmp / "review_frames.js", "LGI_REVIEW_FRAMES", frames_payload),
                 FRAMES_DIR: block_bytes}
    sizes.update({n: (out / n).stat().st_size for n in ("index.html", "viewer.js")})
    return {"page": str((out / "index.html").resolve()), "bytes": int(sum(sizes.values())), "files": sizes,
            "frames": n_f, "vertices": n_v, "blocks": len(files), "block": block, "overview": len(overview),
            "maps": [mp["key"] for mp in page_maps], "seconds": time.perf_counter() - t0,
            "quantisation_error_mm": layout.error_bound_cm * MM_PER_CM, "moving_vertices": int(len(layout.moving))}


def _run_record(recon: Path) -> dict[str, Any] | None:
    """The reconstruction's ``run.json`` (its method, options and noise), or None when it has none or it cannot
    be read (the page then says so; a review does not fail on it)."""
    path = recon / "run.json"
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s: not read (%s); the page shows no options or noise estimate", path, exc)
        return None
    return record if isinstance(record, dict) else None


def _summary(recon: Path, index_dir: str | Path, index, status_counts: Counter[str],
             summary: dict[str, Any] | None, o: ReviewOptions, n_f: int, n_v: int) -> list[list[str]]:
    """(label, text) rows of the run's summary for the page; ``status_counts``: the diagnostics' rows per status."""
    total = max(sum(status_counts.values()), 1)
    rows = [["reconstruction", str(recon.resolve())], ["index", str(Path(index_dir).resolve())],
            ["dataset", str(index.manifest.get("dataset_info", {}).get("name", "?"))],
            ["shot", f"{n_f} frames x {n_v} vertices, {index.n_markers} markers"],
            ["bundle statuses", ", ".join(f"{s} {100 * status_counts[s] / total:.1f} %"
                                          for s in sorted(status_counts))]]
    if summary:
        from lgi.jobs.reconstruct import report_lines

        if summary.get("noise_estimate_mm") is not None:
            axes = summary.get("noise_estimate_axes_mm")
            per_axis = "" if not axes or None in axes else " (x {:.4f}, y {:.4f}, z {:.4f})".format(*axes)
            rows.append(["noise estimate", f"{summary['noise_estimate_mm']:.4f} mm{per_axis} (coherence "
                                           f"{summary.get('noise_coherence', float('nan')):.2f})"])
        if summary.get("noise_mm") is not None:
            rows.append(["noise used", f"{summary['noise_mm']:.4f} mm"])
        if summary.get("method"):
            rows.append(["method", str(summary["method"])])
        if summary.get("options"):
            rows.append(["options", ", ".join(f"{k}={v}" for k, v in summary["options"].items())])
        try:
            rows += [["report", line] for line in report_lines(summary)]
        except (KeyError, TypeError, ValueError):
            pass  # a summary from another version: its figures above are enough
    else:
        rows.append(["noise estimate", "not stored with the reconstruction (no run.json: written by an older lgi)"])
    counts = index.manifest.get("counts", {})
    if counts:
        rows.append(["index counts", ", ".join(f"{k} {v}" for k, v in counts.items())])
    if o.truth:
        rows.append(["truth", str(Path(o.truth).resolve())])
    if o.compare:
        rows.append(["compare", str(Path(o.compare).resolve())])
    return rows


def _warnings(diag: _Diagnostics, per_frame: pd.DataFrame, n_markers: int,
              summary: dict[str, Any] | None) -> list[str]:
    """What a supervisor should look at first, from the diagnostics."""
    out = []
    if "missing" in per_frame and len(per_frame):
        share = per_frame["missing"].to_numpy(float) / max(n_markers, 1)
        bad = np.flatnonzero(share > 0.2)
        if bad.size:
            out.append(f"{bad.size} frames miss over 20 % of their bundles (first: frame "
                       f"{int(per_frame['frame'].iloc[bad[0]])})")
    if "residual_mm" in per_frame and len(per_frame):
        r = per_frame["residual_mm"].to_numpy(float)
        if np.isfinite(r).any() and np.nanmax(r) > 0.01:
            f = int(per_frame["frame"].iloc[int(np.nanargmax(r))])
            out.append(f"largest bundle residual after correction {np.nanmax(r):.3f} mm (frame {f})")
    if diag.fallbacks:
        out.append(f"{diag.fallbacks} bundle-frames fell back ({diag.first_fallback})")
    if summary and summary.get("noise_estimated") and not math.isfinite(summary.get("noise_estimate_mm") or 0.0):
        out.append("noise not estimated: no marker is seen for 7 frames in a row")
    return out


def review_report(r: dict[str, Any]) -> list[str]:
    """The lines ``lgi review`` prints."""
    per_1000 = r["bytes"] / max(r["frames"], 1) * 1000 / 1e6
    return [f"review page of {r['frames']} frames x {r['vertices']} vertices: {r['page']}",
            f"  {r['bytes'] / 1e6:.1f} MB ({per_1000:.1f} MB per 1000 frames, in {r['blocks']} blocks of "
            f"{r['block']} frames loaded as they are shown; {r['moving_vertices']} vertices move; "
            f"positions within {r['quantisation_error_mm'] * 1000:.2f} um), colour maps: {', '.join(r['maps'])}; "
            "open it in a browser (no server needed)"]


def review_beside(out: str | Path, index_dir: str | Path, summary: dict[str, Any] | None = None,
                  options: ReviewOptions | None = None, warnings: list[str] | None = None) -> dict[str, Any]:
    """The review page of the reconstruction in ``out``, written to ``out/review`` (``--review``, the demo and the
    flows)."""
    return review(out, index_dir, Path(out) / "review", options, summary, warnings)


def remove_review(out: str | Path) -> None:
    """Remove ``out/review`` if it is a review folder (a re-run without ``--review``: the old page would show
    another run)."""
    remove_recorded(Path(out) / "review", REVIEW_ENTRIES, "earlier review page")
